// Drives Debian's chromium (puppeteer-core) through the operator's console
// while a real mission flies: tests/browser/console_browser_test.py starts
// the stack and runs
//
//   node console_browser.js URL ROBOT MISSION_FILE SCREENSHOT
//
// It fails (exit 1, the reason on stderr) unless, in order:
// - the page loads and the coordinator's systems appear, UP;
// - the mission started from the page's form advances step by step;
// - its tree of step records shows its loop's iterations, their records one
//   level deeper than the mission's steps, each with its state and cause, as
//   the mission goes on;
// - a terminated behavior shows its cause (TAKE_OFF, GOAL_ACHIEVED);
// - the vehicle's marker moves on the map, over the world's walls and the
//   OctoMap's occupied voxels;
// - pressing "Emergency land" lands the vehicle (its flight state LANDED),
//   and the mission's tree shows its hover step INTERRUPTED;
// - the flight's recording (the launcher's --record) opens in the page, and
//   scrubbing through it shows the flight again: fewer events at its start
//   than at its end, TAKE_OFF's GOAL_ACHIEVED, the vehicle at two places at least;
// - a fleet mission's status given to the page (its parallel branches'
//   records interleaved, a call retried) is drawn as a tree: depth-first in
//   mission order, each branch under its header with its robot, a call's
//   steps under its attempt, and the missions table names both robots;
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

    // The hover step (steps/3): the vehicle is in the air, and stays there.
    await page.waitForFunction(() => {
      const row = document.querySelector("#missions tbody tr");
      return row && Number(row.querySelector(".steps").textContent) >= 6 &&
        row.querySelector(".step").textContent === "WAIT" &&
        row.querySelector(".step").title === "steps/3";
    }, { timeout: WAIT_MS });
    const hovering = await stepsOf();
    if (!(hovering.steps > first.steps)) {
      throw new Error(`the mission's steps did not advance: ${JSON.stringify([first, hovering])}`);
    }
    log(`mission advanced to ${JSON.stringify(hovering)}`);

    // The mission's tree (the row clicked): the loop `settle` at depth 0, each
    // iteration's header and its WAIT at depth 1, indented further, then the
    // mission's other steps at depth 0, the hover step still running. Each
    // record was drawn RUNNING first: FINISHED shows the tree follows them.
    await page.$eval("#missions tbody tr td", (td) => td.click());
    const treeOf = () => [...document.querySelectorAll("#mission-tree tbody tr")].map((row) => ({
      kind: row.className, depth: Number(row.dataset.depth),
      at: row.dataset.node || row.dataset.group,
      label: row.querySelector(".label").textContent,
      state: row.querySelector(".state") ? row.querySelector(".state").textContent : "",
      cause: row.querySelector(".cause") ? row.querySelector(".cause").textContent : "",
      indent: parseFloat(getComputedStyle(row.querySelector(".label")).paddingLeft),
    }));
    await page.waitForFunction((hover) => {
      const row = document.querySelector('#mission-tree tr[data-node="steps/3"]');
      return row && row.querySelector(".state").textContent === hover;
    }, { timeout: WAIT_MS }, "RUNNING");
    const tree = await page.evaluate(treeOf);
    const shape = tree.map((r) => `${r.kind} ${r.depth} ${r.at} ${r.label} ${r.state} ${r.cause}`);
    const loopIn = "steps/0/attempt/1/iteration/";
    const expected = [
      "record 0 steps/0 settle repeat 2 times FINISHED GOAL_ACHIEVED",
      `group 1 ${loopIn}0 iteration 0  `,
      `record 1 ${loopIn}0/steps/0 step 0 WAIT FINISHED GOAL_ACHIEVED`,
      `group 1 ${loopIn}1 iteration 1  `,
      `record 1 ${loopIn}1/steps/0 step 0 WAIT FINISHED GOAL_ACHIEVED`,
    ];
    if (JSON.stringify(shape.slice(0, expected.length)) !== JSON.stringify(expected)) {
      throw new Error(`the mission's tree starts:\n${shape.join("\n")}`);
    }
    const rest = tree.slice(expected.length);
    if (!rest.every((r) => r.kind === "record" && r.depth === 0) ||
        rest[0].at !== "steps/1" || rest[rest.length - 1].at !== "steps/3" ||
        !rest[rest.length - 1].label.endsWith("WAIT")) {
      throw new Error(`the mission's tree goes on:\n${shape.join("\n")}`);
    }
    if (tree.filter((r) => r.kind === "record").length !== hovering.steps) {
      throw new Error(`the tree does not show the ${hovering.steps} records:\n${shape.join("\n")}`);
    }
    if (!(tree[0].indent < tree[1].indent && tree[1].indent < tree[2].indent &&
          tree[2].indent === tree[4].indent && tree[5].indent === tree[0].indent)) {
      throw new Error(`the tree's indents: ${tree.map((r) => r.indent)}`);
    }
    log(`the mission's tree: ${shape.length} rows, the loop's WAITs at depth 1`);
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
    // The landing stood the mission down: its tree shows the hover step
    // (RUNNING before) ended, interrupted.
    await page.waitForFunction(() => {
      const row = document.querySelector('#mission-tree tr[data-node="steps/3"]');
      return row && row.querySelector(".state").textContent === "FINISHED" &&
        row.querySelector(".cause").textContent === "INTERRUPTED";
    }, { timeout: WAIT_MS });
    log("the tree shows the hover step INTERRUPTED");

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

    // A fleet mission's status as the coordinator writes it (records in the
    // order they were created: the branches interleave; the call `hop` failed
    // its attempt 1 and ran again), given to the page as the feed gives one:
    // the tree puts each branch's records together, in mission order.
    const fleet = await page.evaluate(() => {
      const run = "MISSION_STEP_STATE_RUNNING";
      const done = "MISSION_STEP_STATE_FINISHED";
      const ok = "TERMINATION_CAUSE_GOAL_ACHIEVED";
      const b0 = "steps/1/attempt/1/branch/0/steps/";
      const b1 = "steps/1/attempt/1/branch/1/steps/";
      const record = (node, robot, fields) => ({ node, robot_id: robot, attempt: 1, name: "",
        behavior: "", call: "", loop: "", parallel: "", wait_for: "", state: done,
        cause: ok, message: "", ...fields });
      onMission({ mission_id: "fleet-tree", name: "fleet_tree", robot_id: "drone1",
        robot_ids: ["drone1", "drone2"], state: "MISSION_STATE_RUNNING",
        start_time: "2100-01-01T00:00:00Z", steps: [
          record("steps/0", "drone1", { name: "settle", behavior: "WAIT" }),
          record("steps/1", "drone1", { name: "both", parallel: "all of 2 branches",
                                        state: run, cause: "" }),
          record(b0 + "0", "drone1", { behavior: "TAKE_OFF" }),
          record(b1 + "0", "drone2", { behavior: "TAKE_OFF" }),
          record(b0 + "1", "drone1", { name: "hop", call: "hop",
                                       cause: "TERMINATION_CAUSE_TIME_OUT" }),
          record(b1 + "1", "drone2", { name: "meet", wait_for: "step 'hop' achieved",
                                       state: run, cause: "" }),
          record(b0 + "1/attempt/1/call/steps/0", "drone1", { behavior: "GO_TO",
            cause: "TERMINATION_CAUSE_TIME_OUT" }),
          record(b0 + "1", "drone1", { name: "hop", call: "hop", attempt: 2, state: run,
                                       cause: "" }),
          record(b0 + "1/attempt/2/call/steps/0", "drone1", { behavior: "GO_TO", state: run,
                                                             cause: "" }),
        ] });
      document.querySelector('#missions tr[data-mission="fleet-tree"] td').click();
      return {
        robots: document.querySelector('#missions tr[data-mission="fleet-tree"] .robot')
          .textContent,
        tree: [...document.querySelectorAll("#mission-tree tbody tr")].map((row) =>
          `${row.dataset.depth} ${row.querySelector(".label").textContent}` +
          (row.dataset.node ? ` ${row.querySelector(".robot").textContent} ` +
           `${row.querySelector(".attempt").textContent} ` +
           `${row.querySelector(".cause").textContent}` : "")),
      };
    });
    const fleetTree = [
      "0 settle WAIT drone1 1 GOAL_ACHIEVED",
      "0 both parallel, all of 2 branches drone1 1 ",
      "1 branch 0 (drone1)",
      "1 step 0 TAKE_OFF drone1 1 GOAL_ACHIEVED",
      "1 hop call hop drone1 1 TIME_OUT",
      "2 step 0 GO_TO drone1 1 TIME_OUT",
      "1 hop call hop drone1 2 ",
      "2 step 0 GO_TO drone1 1 ",
      "1 branch 1 (drone2)",
      "1 step 0 TAKE_OFF drone2 1 GOAL_ACHIEVED",
      "1 meet wait for step 'hop' achieved drone2 1 ",
    ];
    if (fleet.robots !== "drone1,drone2" ||
        JSON.stringify(fleet.tree) !== JSON.stringify(fleetTree)) {
      throw new Error(`the fleet mission's row names ${fleet.robots}, its tree:\n` +
        fleet.tree.join("\n"));
    }
    log(`a fleet mission's tree: ${fleet.tree.length} rows, its branches apart`);
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
