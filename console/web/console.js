// The console's page: the fleet, its events and missions, live from the
// gateway's event feed (/api/events, Server-Sent Events), and an operator's
// controls, each one Coordinator call through /api/coordinator/NAME. A
// bearer token (?token=... in the URL) is sent with every call, so the
// coordinator's access policy decides what this browser may do.
"use strict";

const token = new URLSearchParams(location.search).get("token");
const MAX_EVENTS = 500;
const missions = new Map();
// The recording shown instead of the live fleet (openRecording), or null.
let replaying = null;
// While a recording's messages are applied, the map and tables are drawn
// once at the end.
let deferred = false;

async function call(name, request) {
  const headers = { "Content-Type": "application/json" };
  if (token) headers.Authorization = "Bearer " + token;
  const reply = await fetch("/api/coordinator/" + name, {
    method: "POST", headers, body: JSON.stringify(request || {}),
  });
  const body = await reply.json();
  if (!reply.ok) {
    const info = (body.details || []).find((d) => (d["@type"] || "").endsWith("ErrorInfo"));
    const error = new Error(body.message || reply.statusText);
    error.reason = info ? info.reason : "";
    throw error;
  }
  return body;
}

function showError(error) {
  document.getElementById("error").textContent =
    error ? (error.reason ? error.reason + ": " : "") + error.message : "";
}

function cell(row, text, className) {
  const td = row.insertCell();
  td.textContent = text === undefined || text === null ? "" : String(text);
  if (className) td.className = className;
  return td;
}

// A behavior event's stamp is simulated time (seconds since the simulation
// began, as a 1970 timestamp); a system's is wall time.
function formatTime(stamp) {
  const ms = Date.parse(stamp || "");
  if (Number.isNaN(ms)) return "";
  if (ms < 1e11) return "t = " + (ms / 1000).toFixed(2) + " s";
  return new Date(ms).toLocaleTimeString();
}

function shortState(name, prefix) {
  return (name || "").replace(prefix, "");
}

async function refreshSystems() {
  const { systems } = await call("ListSystems", {});
  const { behaviors } = await call("ListBehaviors", {});
  const hosted = new Map();
  for (const b of behaviors) {
    const key = b.robot_id + "/" + b.system;
    hosted.set(key, (hosted.get(key) || 0) + 1);
  }
  const body = document.querySelector("#systems tbody");
  body.replaceChildren();
  for (const s of systems) systemRow(body, s, hosted.get(s.robot_id + "/" + s.system) || 0);
  const active = document.querySelector("#active tbody");
  active.replaceChildren();
  for (const b of behaviors.filter((b) => b.activation_id)) {
    activeRow(active, b.robot_id, b.description.name, b.activation_id);
  }
}

// The tables follow the fleet's events, but with one ListSystems and
// ListBehaviors at a time and at most one pair per REFRESH_PERIOD_MS: the page
// asked for both lists at every event, so a page that opened on the hub's
// kept events, or watched a fleet of 20, sent thousands of them.
const REFRESH_PERIOD_MS = 500;
let refreshing = false;
let refreshWanted = false;

function refreshSoon() {
  if (refreshing) {
    refreshWanted = true;
    return;
  }
  refreshing = true;
  refreshSystems().catch(showError).finally(() => setTimeout(() => {
    refreshing = false;
    if (refreshWanted) {
      refreshWanted = false;
      refreshSoon();
    }
  }, REFRESH_PERIOD_MS));
}

function systemRow(body, s, behaviors) {
  const row = body.insertRow();
  row.dataset.robot = s.robot_id;
  row.dataset.system = s.system;
  cell(row, s.robot_id);
  cell(row, s.system);
  cell(row, shortState(s.state, "SYSTEM_STATE_"), "state");
  cell(row, s.address);
  cell(row, behaviors);
}

function activeRow(body, robot, behavior, activationId) {
  const row = body.insertRow();
  cell(row, robot);
  cell(row, behavior);
  cell(row, "active");
  cell(row, activationId);
}

// The planned path: the `path_m` of the robot's latest activation that has
// one (FOLLOW_PATH and the other path followers).
function notePlan(e) {
  const path = e.activated && e.activated.parameters && e.activated.parameters.path_m;
  if (!Array.isArray(path)) return;
  vehicle(e.robot_id).plan = path.map((p) => ({ x: Number(p.x) || 0, y: Number(p.y) || 0 }));
  renderVehicles();
}

function addEvent(fleetEvent) {
  const body = document.querySelector("#events tbody");
  const row = body.insertRow(0);
  const e = fleetEvent.behavior_event;
  if (e) {
    notePlan(e);
    const kind = ["activated", "finished", "paused", "resumed", "modified"].find((k) => e[k]);
    const finished = e.finished || {};
    row.dataset.behavior = e.behavior;
    row.dataset.kind = kind || "";
    cell(row, formatTime(e.time || fleetEvent.wall_time));
    cell(row, e.robot_id);
    cell(row, e.behavior);
    cell(row, kind);
    const cause = (finished.cause || "").replace("TERMINATION_CAUSE_", "");
    cell(row, cause, cause ? "cause cause-" + cause : "cause");
    cell(row, finished.message);
  } else if (fleetEvent.system_state_changed) {
    const s = fleetEvent.system_state_changed.system;
    row.dataset.kind = "system";
    cell(row, formatTime(fleetEvent.wall_time));
    cell(row, s.robot_id);
    cell(row, s.system);
    cell(row, shortState(s.state, "SYSTEM_STATE_"));
    cell(row, "");
    cell(row, s.state_message);
  }
  while (body.rows.length > MAX_EVENTS) body.deleteRow(body.rows.length - 1);
}

// What a mission step record runs: its behavior, "call NAME", its loop
// ("repeat 3 times"), "parallel, all of 2 branches" or "wait for ...".
function recordWhat(r) {
  if (!r) return "";
  if (r.behavior) return r.behavior;
  if (r.call) return "call " + r.call;
  if (r.loop) return r.loop;
  if (r.parallel) return "parallel, " + r.parallel;
  if (r.wait_for) return "wait for " + r.wait_for;
  return "";
}

// A record's node split at "/" ("steps/2/attempt/1/call/steps/0"); from its
// path (steps, then fallback lists) when it has no node.
function nodeParts(r) {
  if (r.node) return r.node.split("/");
  const path = r.path || [];
  if (!path.length) return [];
  const parts = ["steps", String(path[0])];
  for (const i of path.slice(1)) parts.push("fallback", String(i));
  return parts;
}

// Within one position, a step's attempts (and their calls, iterations and
// branches) come before its fallback.
const NODE_WORDS = ["steps", "attempt", "call", "iteration", "branch", "fallback"];

// The key that orders records depth-first in mission order: the node part by
// part (numbers as numbers), then the record's attempt, so that a call's
// attempt 1 and its steps come before its attempt 2.
function nodeKey(parts, attempt) {
  return [...parts, "attempt", String(attempt || 0)].map((p) =>
    (/^\d+$/.test(p) ? [1, Number(p)] : [0, NODE_WORDS.indexOf(p)]));
}

function compareKeys(a, b) {
  for (let i = 0; i < Math.min(a.length, b.length); ++i) {
    if (a[i][0] !== b[i][0]) return a[i][0] - b[i][0];
    if (a[i][1] !== b[i][1]) return a[i][1] - b[i][1];
  }
  return a.length - b.length;
}

// The groups a record's node passes through, outermost first: a fallback
// list, a loop's iteration, a parallel step's branch (with the robot of its
// first record). `depth` is that of the records inside the group.
function nodeGroups(parts, robot) {
  const groups = [];
  let lists = 0;  // "steps" and "fallback" parts so far
  for (let i = 0; i < parts.length; ++i) {
    const part = parts[i];
    if (part === "steps" || part === "fallback") ++lists;
    if (part === "fallback") {
      groups.push({ key: parts.slice(0, i + 1).join("/"), label: "fallback", depth: lists - 1 });
    } else if (part === "attempt" && (parts[i + 2] === "iteration" || parts[i + 2] === "branch")) {
      let label = parts[i + 2] + " " + parts[i + 3];
      if (parts[i + 2] === "branch" && robot) label += " (" + robot + ")";
      if (Number(parts[i + 1]) > 1) label += ", attempt " + parts[i + 1];
      groups.push({ key: parts.slice(0, i + 4).join("/"), label, depth: lists });
    }
  }
  return groups;
}

// A mission's records as the rows of a tree: depth-first by node (a parallel
// step's branches one after the other, though their records interleave), each
// record at its depth (0 for the mission's own steps, 1 inside a call, an
// iteration, a branch or a fallback, and so on), a group's row before its
// first record.
function missionTree(status) {
  const records = (status.steps || []).map((record, index) => {
    const parts = nodeParts(record);
    const lists = parts.filter((p) => p === "steps" || p === "fallback").length;
    return { record, index, parts, depth: Math.max(0, lists - 1),
             key: nodeKey(parts, record.attempt) };
  });
  records.sort((a, b) => compareKeys(a.key, b.key) || a.index - b.index);
  const rows = [];
  let open = [];
  for (const r of records) {
    const groups = nodeGroups(r.parts, r.record.robot_id);
    let same = 0;
    while (same < groups.length && same < open.length && groups[same].key === open[same].key) {
      ++same;
    }
    for (const g of groups.slice(same)) rows.push({ group: true, ...g });
    open = groups;
    rows.push({ group: false, record: r.record, node: r.parts.join("/"), depth: r.depth,
                position: r.parts[r.parts.length - 1] || "" });
  }
  return rows;
}

// The mission whose tree is shown: the one clicked, else the newest running
// (or paused) one, else the newest.
let selectedMission = null;

function renderTree(sorted) {
  const shown = missions.get(selectedMission) ||
    sorted.find((m) => /RUNNING|PAUSED/.test(m.state || "")) || sorted[0];
  const table = document.getElementById("mission-tree");
  const body = table.querySelector("tbody");
  body.replaceChildren();
  table.hidden = !shown;
  document.getElementById("mission-tree-title").textContent = shown
    ? "Steps of " + (shown.name || shown.mission_id) + " (" + shown.mission_id + ")" : "";
  if (!shown) return;
  table.dataset.mission = shown.mission_id;
  const indent = (levels) => (0.5 + 0.8 * Math.max(0, levels)) + "em";
  for (const item of missionTree(shown)) {
    const row = body.insertRow();
    row.dataset.depth = item.depth;
    if (item.group) {
      // The group's row, half way between its parent and its records.
      row.className = "group";
      row.dataset.group = item.key;
      const label = cell(row, item.label, "label");
      label.colSpan = 6;
      label.style.paddingLeft = indent(2 * item.depth - 1);
      continue;
    }
    const r = item.record;
    row.className = "record";
    row.dataset.node = item.node;
    const label = cell(row, "", "label");
    label.style.paddingLeft = indent(2 * item.depth);
    label.title = item.node;
    const name = document.createElement("span");
    name.className = "name";
    name.textContent = r.name || "step " + item.position;
    const what = document.createElement("span");
    what.className = "what";
    what.textContent = recordWhat(r);
    label.append(name, " ", what);
    cell(row, r.robot_id, "robot");
    cell(row, r.attempt || "", "attempt");
    cell(row, shortState(r.state, "MISSION_STEP_STATE_"), "state");
    const cause = r.cause === "TERMINATION_CAUSE_UNSPECIFIED" ? ""
      : shortState(r.cause, "TERMINATION_CAUSE_");
    cell(row, cause, cause ? "cause cause-" + cause : "cause");
    cell(row, r.message, "message");
  }
}

function renderMissions() {
  if (deferred) return;
  const body = document.querySelector("#missions tbody");
  body.replaceChildren();
  const sorted = [...missions.values()].sort((a, b) =>
    (b.start_time || "").localeCompare(a.start_time || ""));
  for (const m of sorted) {
    const row = body.insertRow();
    row.dataset.mission = m.mission_id;
    // A click shows its records as a tree (renderTree).
    row.className = "selectable" + (m.mission_id === selectedMission ? " selected" : "");
    row.onclick = () => {
      selectedMission = m.mission_id;
      renderMissions();
    };
    const state = shortState(m.state, "MISSION_STATE_");
    const last = m.steps.length ? m.steps[m.steps.length - 1] : null;
    cell(row, m.name || m.mission_id);
    // A fleet mission's robots, robot_id first.
    const robots = m.robot_ids || [];
    cell(row, robots.length > 1 ? robots.join(",") : m.robot_id, "robot");
    cell(row, state, "state");
    // The step it is at, and where in the mission's tree (its node).
    const step = cell(row, recordWhat(last), "step");
    if (last && last.node) step.title = last.node;
    cell(row, m.steps.length, "steps");
    const controls = cell(row, "");
    for (const [label, method] of [["Pause", "PauseMission"], ["Resume", "ResumeMission"],
                                   ["Abort", "AbortMission"]]) {
      if (replaying || (state !== "RUNNING" && state !== "PAUSED")) break;
      const button = document.createElement("button");
      button.textContent = label;
      button.onclick = () => call(method, { mission_id: m.mission_id }).then(
        () => showError(null), showError);
      controls.appendChild(button);
    }
  }
  renderTree(sorted);
}

// The world under the vehicles (GET /api/world): what stands at MAP_HEIGHT_M,
// in plan view (so doors stay open under their lintels).
const MAP_HEIGHT_M = 1.0;
let world = { boxes: [], markers: [] };

async function loadWorld() {
  const reply = await fetch("/api/world");
  if (reply.ok) world = await reply.json();
  renderVehicles();
}

// QR markers found: the beliefs <robot>/markers/<text> that
// attention_to_visual_markers writes (behaviorlib.v1.QrCodeBelief).
const markersFound = new Map();

function onBelief(belief) {
  if (!/^[^/]+\/markers\/.+$/.test(belief.key || "")) return;
  const value = belief.value;
  if (belief.deleted || !value || !value.position_m) {
    markersFound.delete(belief.key);
  } else {
    markersFound.set(belief.key, { text: value.text || "", position: value.position_m });
  }
  renderVehicles();
}

// Each robot's vehicle: its latest pose (the estimate while one arrives,
// else the simulator's ground truth), flight status and flown track.
const vehicles = new Map();
const MAX_TRACK = 2000;

function vehicle(robot) {
  if (!vehicles.has(robot)) {
    vehicles.set(robot, { robot, track: [], state: "", battery: null, estimateAt: 0 });
  }
  return vehicles.get(robot);
}

// nowMs: the time the sample is shown at (a recording's time when replaying).
function onVehicle(sample, nowMs = Date.now()) {
  const match = /^robots\/([^/]+)\/(.+)$/.exec(sample.topic || "");
  if (!match || !sample.sample) return;
  const v = vehicle(match[1]);
  const topic = match[2];
  if (topic === "map/occupied") {
    // The OctoMap's occupied voxels at the lidar's height (navigation_with_lidar).
    v.cells = (sample.sample.points_m || []).map((p) => ({ x: p.x || 0, y: p.y || 0 }));
  } else if (topic === "flight_state") {
    v.state = shortState(sample.sample.state, "FLIGHT_STATE_");
    v.battery = sample.sample.battery_ratio;
  } else if (topic.endsWith("pose")) {
    // An estimate older than a second (its localization ended) gives way to
    // the ground truth.
    if (topic === "self_localization/pose") {
      v.estimateAt = nowMs;
    } else if (nowMs - v.estimateAt < 1000) {
      return;
    }
    const p = sample.sample.pose.position_m || {};
    const point = { x: p.x || 0, y: p.y || 0, z: p.z || 0 };
    const last = v.track[v.track.length - 1];
    if (!last || Math.hypot(point.x - last.x, point.y - last.y, point.z - last.z) > 0.02) {
      v.track.push(point);
      if (v.track.length > MAX_TRACK) v.track.shift();
    }
    v.position = point;
  }
  renderVehicles();
}

function renderVehicles() {
  if (deferred) return;
  const body = document.querySelector("#vehicles tbody");
  body.replaceChildren();
  const content = document.getElementById("map-content");
  content.replaceChildren();
  const ns = "http://www.w3.org/2000/svg";
  let minX = -2, maxX = 2, minY = -2, maxY = 2;
  for (const box of world.boxes || []) {
    const c = box.center_m, s = box.size_m;
    if (c.z - s.z / 2 > MAP_HEIGHT_M || c.z + s.z / 2 < MAP_HEIGHT_M) continue;
    const rect = document.createElementNS(ns, "rect");
    rect.setAttribute("class", box.kind === "wall" ? "wall" : "obstacle");
    rect.setAttribute("x", -s.x / 2);
    rect.setAttribute("y", -s.y / 2);
    rect.setAttribute("width", s.x);
    rect.setAttribute("height", s.y);
    rect.setAttribute("transform",
      `translate(${c.x},${c.y}) rotate(${(box.yaw_rad || 0) * 180 / Math.PI})`);
    content.appendChild(rect);
    const r = Math.hypot(s.x, s.y) / 2;
    minX = Math.min(minX, c.x - r); maxX = Math.max(maxX, c.x + r);
    minY = Math.min(minY, c.y - r); maxY = Math.max(maxY, c.y + r);
  }
  for (const marker of world.markers || []) {
    const square = document.createElementNS(ns, "rect");
    square.setAttribute("class", "marker");
    square.setAttribute("x", marker.center_m.x - 0.1);
    square.setAttribute("y", marker.center_m.y - 0.1);
    square.setAttribute("width", 0.2);
    square.setAttribute("height", 0.2);
    content.appendChild(square);
  }
  for (const [key, marker] of markersFound) {
    const found = document.createElementNS(ns, "circle");
    found.setAttribute("class", "marker-found");
    found.dataset.key = key;
    found.setAttribute("cx", marker.position.x || 0);
    found.setAttribute("cy", marker.position.y || 0);
    found.setAttribute("r", 0.2);
    const title = document.createElementNS(ns, "title");
    title.textContent = marker.text;
    found.appendChild(title);
    content.appendChild(found);
  }
  for (const v of vehicles.values()) {
    const row = body.insertRow();
    row.dataset.robot = v.robot;
    cell(row, v.robot);
    cell(row, v.state, "flight-state");
    cell(row, v.battery === null ? "" : Math.round(v.battery * 100) + " %", "battery");
    for (const axis of ["x", "y", "z"]) {
      cell(row, v.position ? v.position[axis].toFixed(2) : "", "position-" + axis);
    }
    for (const p of v.track) {
      minX = Math.min(minX, p.x); maxX = Math.max(maxX, p.x);
      minY = Math.min(minY, p.y); maxY = Math.max(maxY, p.y);
    }
    for (const c of v.cells || []) {
      const cell = document.createElementNS(ns, "rect");
      cell.setAttribute("class", "cell");
      cell.setAttribute("x", c.x - 0.05);
      cell.setAttribute("y", c.y - 0.05);
      cell.setAttribute("width", 0.1);
      cell.setAttribute("height", 0.1);
      content.appendChild(cell);
    }
    if (v.plan) {
      const plan = document.createElementNS(ns, "polyline");
      plan.setAttribute("class", "plan");
      plan.setAttribute("points", v.plan.map((p) => p.x + "," + p.y).join(" "));
      content.appendChild(plan);
      for (const p of v.plan) {
        minX = Math.min(minX, p.x); maxX = Math.max(maxX, p.x);
        minY = Math.min(minY, p.y); maxY = Math.max(maxY, p.y);
      }
    }
    const track = document.createElementNS(ns, "polyline");
    track.setAttribute("class", "track");
    track.setAttribute("points", v.track.map((p) => p.x + "," + p.y).join(" "));
    content.appendChild(track);
    if (v.position) {
      const marker = document.createElementNS(ns, "circle");
      marker.setAttribute("class", "vehicle");
      marker.dataset.robot = v.robot;
      marker.setAttribute("cx", v.position.x);
      marker.setAttribute("cy", v.position.y);
      marker.setAttribute("r", 0.15);
      content.appendChild(marker);
    }
  }
  const margin = 1;
  // y up: the content is mirrored (scale(1,-1)), so its box is too.
  document.getElementById("map").setAttribute("viewBox",
    [minX - margin, -maxY - margin, maxX - minX + 2 * margin, maxY - minY + 2 * margin].join(" "));
}

function setCoordinator(up, message) {
  const badge = document.getElementById("coordinator");
  badge.className = "badge " + (up ? "up" : "down");
  badge.textContent = "coordinator: " + (up ? "up" : "unreachable " + (message || ""));
}

function onMission(status) {
  missions.set(status.mission_id, status);
  renderMissions();
}

function follow() {
  const feed = new EventSource("/api/events");
  // While a recording is shown, the live feed is not applied (the hub keeps
  // it: going back to live reloads the page).
  const live = (handle) => (message) => {
    if (!replaying) handle(JSON.parse(message.data));
  };
  feed.addEventListener("fleet", live((event) => {
    addEvent(event);
    refreshSoon();
  }));
  feed.addEventListener("mission", live(onMission));
  feed.addEventListener("vehicle", live((sample) => onVehicle(sample)));
  feed.addEventListener("belief", live(onBelief));
  feed.addEventListener("gateway", (message) => {
    if (replaying) return;
    const state = JSON.parse(message.data);
    setCoordinator(state.coordinator_up, state.message);
    if (state.coordinator_up) refreshSoon();
  });
}

document.getElementById("start-mission").addEventListener("submit", (event) => {
  event.preventDefault();
  const form = new FormData(event.target);
  const request = { file_path: form.get("file_path") };
  if (form.get("robot_id")) request.robot_id = form.get("robot_id");
  call("StartMission", request).then(() => showError(null), showError);
});

// CheckMission: every problem with its file and line, or each step's plan.
function showCheck(reply) {
  const lines = (reply.problems || []).map((p) => p.description);
  if (reply.problems_left_out) lines.push("... and " + reply.problems_left_out + " more");
  if (lines.length === 0) {
    lines.push("no problem found");
    for (const plan of reply.plans || []) {
      const steps = (plan.plan || []).map((s) =>
        String(s.kind).replace("KIND_", "").toLowerCase() + " " + s.behavior);
      lines.push(plan.node + "  " + (plan.name || plan.behavior) + ": " +
        (plan.no_plan ? "no plan: " + plan.no_plan : steps.join(", ")));
    }
  }
  document.getElementById("mission-check").textContent = lines.join("\n");
}

document.getElementById("check-mission").addEventListener("click", () => {
  const form = new FormData(document.getElementById("start-mission"));
  const request = { file_path: form.get("file_path") };
  if (form.get("robot_id")) request.robot_id = form.get("robot_id");
  call("CheckMission", request).then((reply) => {
    showError(null);
    showCheck(reply);
  }, showError);
});

document.getElementById("emergency-land").addEventListener("submit", (event) => {
  event.preventDefault();
  const form = new FormData(event.target);
  call("EmergencyLand", { robot_id: form.get("robot_id"), reason: "console operator" })
    .then(() => showError(null), showError);
});

// Flight recordings (GET /api/recordings, made by the flight recorder): one
// is opened whole, then shown as it was at the scrubber's time, by applying
// its messages up to then as the live ones are.
async function loadRecordings() {
  const reply = await fetch("/api/recordings");
  if (!reply.ok) return;
  const { recordings } = await reply.json();
  const select = document.getElementById("recordings");
  select.replaceChildren();
  for (const r of recordings) {
    const option = document.createElement("option");
    option.value = r.name;
    option.textContent = `${r.name} (${(r.bytes / 1e6).toFixed(1)} MB)`;
    select.appendChild(option);
  }
}

async function openRecording(name) {
  const reply = await fetch("/api/recordings/" + encodeURIComponent(name));
  const body = await reply.json();
  if (!reply.ok) throw new Error(body.message || reply.statusText);
  body.messages.sort((a, b) => a.t_ms - b.t_ms);
  replaying = body;
  const scrub = document.getElementById("scrub");
  scrub.max = String(Math.ceil(body.duration_ms));
  scrub.value = scrub.max;
  document.getElementById("scrubber").hidden = false;
  document.getElementById("live").hidden = false;
  const badge = document.getElementById("coordinator");
  badge.className = "badge recording";
  badge.textContent = `recording: ${name}` + (body.complete ? "" : " (still being written)");
  showRecordingAt(Number(scrub.value));
}

// The fleet as the recording had it `ms` after its first message.
function showRecordingAt(ms) {
  document.querySelector("#events tbody").replaceChildren();
  missions.clear();
  vehicles.clear();
  markersFound.clear();
  const systems = new Map();
  const active = new Map();
  deferred = true;
  try {
    for (const { t_ms: t, event, data } of replaying.messages) {
      if (t > ms) break;
      if (event === "fleet") {
        addEvent(data);
        const e = data.behavior_event;
        if (data.system_state_changed) {
          const s = data.system_state_changed.system;
          systems.set(s.robot_id + "/" + s.system, s);
        } else if (e && e.activated) {
          active.set(e.activation_id, e);
        } else if (e && e.finished) {
          active.delete(e.activation_id);
        }
      } else if (event === "mission") {
        onMission(data);
      } else if (event === "vehicle") {
        onVehicle(data, t);
      } else if (event === "belief") {
        onBelief(data);
      }
    }
  } finally {
    deferred = false;
  }
  const systemRows = document.querySelector("#systems tbody");
  systemRows.replaceChildren();
  for (const s of systems.values()) systemRow(systemRows, s, "");
  const activeRows = document.querySelector("#active tbody");
  activeRows.replaceChildren();
  for (const e of active.values()) activeRow(activeRows, e.robot_id, e.behavior, e.activation_id);
  renderMissions();
  renderVehicles();
  document.getElementById("scrub-time").textContent =
    `${(ms / 1000).toFixed(2)} s of ${(replaying.duration_ms / 1000).toFixed(2)} s`;
}

document.getElementById("open-recording").addEventListener("submit", (event) => {
  event.preventDefault();
  const name = new FormData(event.target).get("name");
  if (name) openRecording(name).then(() => showError(null), showError);
});
document.getElementById("scrub").addEventListener("input", (event) => {
  if (replaying) showRecordingAt(Number(event.target.value));
});
document.getElementById("live").addEventListener("click", () => location.reload());

follow();
refreshSoon();
loadWorld().catch(showError);
loadRecordings().catch(showError);
