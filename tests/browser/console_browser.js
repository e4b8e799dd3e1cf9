// Drives Debian's chromium (puppeteer-core) through the operator's console
// while a real mission flies: tests/browser/console_browser_test.py starts
// the stack and runs
//
//   node console_browser.js URL ROBOT MISSION_FILE SCREENSHOT
//
// It fails (exit 1, the reason on stderr) unless, in order:
// - the page loads and the coordinator's systems appear, UP;
// - the mission started from the page's form advances step by step;
// - a terminated behavior shows its cause (TAKE_OFF, GOAL_ACHIEVED);
// - the vehicle's marker moves on the map, over the world's walls and the
//   OctoMap's occupied voxels;
// - pressing "Emergency land" lands the vehicle (its flight state LANDED);
// - the flight's recording (the launcher's --record) opens in the page, and
//   scrubbing through it shows the flight again: fewer events at its start
//   than at its end, TAKE_OFF's GOAL_ACHIEVED, the vehicle at two places at least;
// - and no console error or uncaught exception happened on the way.
// Each wait is a bound for what must happen, never a measure of speed.
"use strict";

const puppeteer = require("puppeteer-core");

const [url, robot, missionFile, screenshot] = process.argv.slice(2);
const WAIT_MS = 180000;

function log(text) {
  console.log(`[${(process.uptime()).toFixed(1)} s] ${text}`);
}

// Presses a button as the DOM does (its click activates its form), not at
// the screen point puppeteer measured a moment before: the tables above the
// forms fill in as the feed arrives, so a button can move between the
// measure and the click, and the click then lands on something else.
async function press(page, selector) {
  await page.$eval(selector, (button) => button.click());
}

async function main() {
  const browser = await puppeteer.launch({
    executablePath: process.env.CHROMIUM || "/usr/bin/chromium",
    headless: true,
    // No sandbox: CI runs as root, where chromium's sandbox refuses to start.
    args: ["--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage"],
  });
  const errors = [];
  try {
    const page = await browser.newPage();
    page.on("console", (message) => {
      if (message.type() === "error") errors.push(`console: ${message.text()}`);
    });
    page.on("pageerror", (error) => errors.push(`uncaught: ${error}`));
    page.on("requestfailed", (request) => {
      // The event feed is cut when the page closes: not an error of the page.
      if (!request.url().endsWith("/api/events")) {
        errors.push(`request failed: ${request.url()} ${request.failure().errorText}`);
      }
    });
    await page.setViewport({ width: 1200, height: 1800 });
    await page.goto(url, { waitUntil: "domcontentloaded" });

    await page.waitForFunction(() => document.getElementById("coordinator").textContent
      .includes("up"), { timeout: WAIT_MS });
    await page.waitForFunction(() => [...document.querySelectorAll("#systems tbody tr")]
      .some((row) => row.querySelector(".state").textContent === "UP"), { timeout: WAIT_MS });
    const systems = await page.$$eval("#systems tbody tr", (rows) => rows.length);
    log(`${systems} systems shown`);

    // Where the vehicle stands before the mission (the simulator's ground truth).
    const marker = `#map circle.vehicle[data-robot="${robot}"]`;
    await page.waitForSelector(marker, { timeout: WAIT_MS });
    const start = await page.$eval(marker, (c) => [Number(c.getAttribute("cx")),
                                                   Number(c.getAttribute("cy"))]);
    log(`the vehicle stands at (${start.map((v) => v.toFixed(2)).join(", ")})`);

    await page.type("#start-mission input[name=file_path]", missionFile);
    // Check first: no problem, and a plan for each step (nothing starts).
    await press(page, "#check-mission");
    const checked = await (await page.waitForFunction(() => {
      const text = document.getElementById("mission-check").textContent;
      return text.length > 0 && text;
    }, { timeout: WAIT_MS })).jsonValue();
    if (!checked.startsWith("no problem found") || !checked.includes("steps/0")) {
      throw new Error(`the check shows: ${checked}`);
    }
    if (await page.$("#missions tbody tr")) throw new Error("a check started a mission");
    log(`checked: ${checked.split("\n").length - 1} steps planned`);
    await press(page, "#start-mission button[type=submit]");
    const stepsOf = () => page.$eval("#missions tbody tr", (row) => ({
      steps: Number(row.querySelector(".steps").textContent),
      step: row.querySelector(".step").textContent,
      state: row.querySelector(".state").textContent,
    }));
    // The mission's row as first drawn (read in the same check that finds it,
    // not one round trip later, when the fast flight may have gone on).
    const first = await (await page.waitForFunction(() => {
      const row = document.querySelector("#missions tbody tr");
      return row && {
        steps: Number(row.querySelector(".steps").textContent),
        step: row.querySelector(".step").textContent,
        state: row.querySelector(".state").textContent,
      };
    }, { polling: "mutation", timeout: WAIT_MS })).jsonValue();
    log(`mission shown: ${JSON.stringify(first)}`);

    await page.waitForSelector(
      'tr[data-behavior="TAKE_OFF"][data-kind="finished"] td.cause-GOAL_ACHIEVED',
      { timeout: WAIT_MS });
    log("TAKE_OFF finished, GOAL_ACHIEVED, in the timeline");

    // The leg flies 2 m from where the vehicle stood before the mission and
    // it hovers there: the marker must come more than 1 m from that place.
    // (Read after TAKE_OFF, the start could already be the leg's end when the
    // page lags a fast flight.)
    await page.waitForFunction((selector, x0, y0) => {
      const c = document.querySelector(selector);
      return Math.hypot(Number(c.getAttribute("cx")) - x0,
                        Number(c.getAttribute("cy")) - y0) > 1.0;
    }, { timeout: WAIT_MS }, marker, start[0], start[1]);
    log(`the marker moved from (${start.map((v) => v.toFixed(2)).join(", ")})`);

    // The world's walls, and the walls as the vehicle's OctoMap sees them.
    await page.waitForFunction(() => document.querySelectorAll("#map rect.wall").length > 4 &&
      document.querySelectorAll("#map rect.cell").length > 10, { timeout: WAIT_MS });
    const drawn = await page.evaluate(() => [document.querySelectorAll("#map rect.wall").length,
                                             document.querySelectorAll("#map rect.cell").length]);
    log(`the map shows ${drawn[0]} walls of the world and ${drawn[1]} occupied voxels`);

    // The hover step: the vehicle is in the air, and stays there.
    await page.waitForFunction(() => {
      const row = document.querySelector("#missions tbody tr");
      return row && Number(row.querySelector(".steps").textContent) >= 4 &&
        row.querySelector(".step").textContent === "WAIT";
    }, { timeout: WAIT_MS });
    const hovering = await stepsOf();
    if (!(hovering.steps > first.steps)) {
      throw new Error(`the mission's steps did not advance: ${JSON.stringify([first, hovering])}`);
    }
    log(`mission advanced to ${JSON.stringify(hovering)}`);
    const flying = await page.$eval(`#vehicles tr[data-robot="${robot}"] .flight-state`,
      (cell) => cell.textContent);
    if (flying === "LANDED") throw new Error("the vehicle is not in the air before the landing");

    await page.type("#emergency-land input[name=robot_id]", robot);
    await press(page, "#emergency-land button[type=submit]");
    await page.waitForFunction((r) => {
      const cell = document.querySelector(`#vehicles tr[data-robot="${r}"] .flight-state`);
      return cell && cell.textContent === "LANDED";
    }, { timeout: WAIT_MS }, robot);
    // On the ground: the position shown follows the vehicle down.
    await page.waitForFunction((r) => {
      const cell = document.querySelector(`#vehicles tr[data-robot="${r}"] .position-z`);
      return cell && Number(cell.textContent) < 0.3;
    }, { timeout: WAIT_MS }, robot);
    const error = await page.$eval("#error", (p) => p.textContent);
    if (error) throw new Error(`the page shows an error: ${error}`);
    log(`emergency land pressed in flight (${flying}): the vehicle LANDED`);

    await page.screenshot({ path: screenshot });
    log(`screenshot: ${screenshot}`);

    // The recording of this flight, still being written.
    await page.reload({ waitUntil: "domcontentloaded" });
    await page.waitForFunction(() => [...document.querySelectorAll("#recordings option")]
      .some((o) => o.value === "flight.mcap"), { timeout: WAIT_MS });
    await page.select("#recordings", "flight.mcap");
    await press(page, "#open-recording button[type=submit]");
    await page.waitForFunction(() => document.getElementById("coordinator").textContent
      .startsWith("recording: flight.mcap"), { timeout: WAIT_MS });
    const scrubTo = async (fraction) => page.evaluate((f) => {
      const scrub = document.getElementById("scrub");
      scrub.value = String(Math.round(Number(scrub.max) * f));
      scrub.dispatchEvent(new Event("input"));
      const marker = document.querySelector("#map circle.vehicle");
      return {
        events: document.querySelectorAll("#events tbody tr").length,
        takeOff: [...document.querySelectorAll('#events tbody tr[data-behavior="TAKE_OFF"]')]
          .some((row) => row.querySelector(".cause").textContent === "GOAL_ACHIEVED"),
        at: marker ? `${Number(marker.getAttribute("cx")).toFixed(1)},` +
          `${Number(marker.getAttribute("cy")).toFixed(1)}` : "",
      };
    }, fraction);
    const views = [];
    for (let i = 0; i <= 40; ++i) views.push(await scrubTo(i / 40));
    const atStart = views[0];
    const atEnd = views[views.length - 1];
    const places = new Set(views.map((v) => v.at).filter((at) => at));
    log(`recording: ${atStart.events} events at its start, ${atEnd.events} at its end, ` +
      `the vehicle at ${places.size} places`);
    if (!(atStart.events < atEnd.events)) throw new Error("scrubbing does not change the events");
    if (atStart.takeOff || !atEnd.takeOff) {
      throw new Error("TAKE_OFF's GOAL_ACHIEVED is not where the recording has it");
    }
    if (places.size < 2) {
      throw new Error(`the vehicle does not move in the recording: ${[...places]}`);
    }
  } catch (error) {
    // What the page showed when it failed, for the log.
    const pages = await browser.pages();
    const page = pages[pages.length - 1];
    if (page) {
      const shown = await page.evaluate(() => ({
        badge: document.getElementById("coordinator").textContent,
        error: document.getElementById("error").textContent,
        recordings: [...document.querySelectorAll("#recordings option")].map((o) => o.value),
      })).catch((e) => `unreadable: ${e}`);
      log(`the page when it failed: ${JSON.stringify(shown)}`);
    }
    if (errors.length) log(`errors in the page:\n${errors.join("\n")}`);
    throw error;
  } finally {
    await browser.close();
  }
  if (errors.length) throw new Error(`errors in the page:\n${errors.join("\n")}`);
}

main().then(() => log("ok"), (error) => {
  console.error(String(error.stack || error));
  process.exit(1);
});
