// The console's page: the fleet, its events and missions, live from the
// gateway's event feed (/api/events, Server-Sent Events), and an operator's
// controls, each one Coordinator call through /api/coordinator/NAME. A
// bearer token (?token=... in the URL) is sent with every call, so the
// coordinator's access policy decides what this browser may do.
"use strict";

const token = new URLSearchParams(location.search).get("token");
const MAX_EVENTS = 500;
const missions = new Map();

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
  for (const s of systems) {
    const row = body.insertRow();
    row.dataset.robot = s.robot_id;
    row.dataset.system = s.system;
    cell(row, s.robot_id);
    cell(row, s.system);
    cell(row, shortState(s.state, "SYSTEM_STATE_"), "state");
    cell(row, s.address);
    cell(row, hosted.get(s.robot_id + "/" + s.system) || 0);
  }
  const active = document.querySelector("#active tbody");
  active.replaceChildren();
  for (const b of behaviors.filter((b) => b.activation_id)) {
    const row = active.insertRow();
    cell(row, b.robot_id);
    cell(row, b.description.name);
    cell(row, "active");
    cell(row, b.activation_id);
  }
}

function addEvent(fleetEvent) {
  const body = document.querySelector("#events tbody");
  const row = body.insertRow(0);
  const e = fleetEvent.behavior_event;
  if (e) {
    const kind = ["activated", "finished", "paused", "resumed", "modified"].find((k) => e[k]);
    const finished = e.finished || {};
    row.dataset.behavior = e.behavior;
    row.dataset.kind = kind || "";
    cell(row, e.time || fleetEvent.wall_time);
    cell(row, e.robot_id);
    cell(row, e.behavior);
    cell(row, kind);
    const cause = (finished.cause || "").replace("TERMINATION_CAUSE_", "");
    cell(row, cause, cause ? "cause cause-" + cause : "cause");
    cell(row, finished.message);
  } else if (fleetEvent.system_state_changed) {
    const s = fleetEvent.system_state_changed.system;
    row.dataset.kind = "system";
    cell(row, fleetEvent.wall_time);
    cell(row, s.robot_id);
    cell(row, s.system);
    cell(row, shortState(s.state, "SYSTEM_STATE_"));
    cell(row, "");
    cell(row, s.state_message);
  }
  while (body.rows.length > MAX_EVENTS) body.deleteRow(body.rows.length - 1);
}

function renderMissions() {
  const body = document.querySelector("#missions tbody");
  body.replaceChildren();
  const sorted = [...missions.values()].sort((a, b) =>
    (b.start_time || "").localeCompare(a.start_time || ""));
  for (const m of sorted) {
    const row = body.insertRow();
    row.dataset.mission = m.mission_id;
    const state = shortState(m.state, "MISSION_STATE_");
    const last = m.steps.length ? m.steps[m.steps.length - 1] : null;
    cell(row, m.name || m.mission_id);
    cell(row, m.robot_id);
    cell(row, state, "state");
    cell(row, last ? last.behavior : "", "step");
    cell(row, m.steps.length, "steps");
    const controls = cell(row, "");
    for (const [label, method] of [["Pause", "PauseMission"], ["Resume", "ResumeMission"],
                                   ["Abort", "AbortMission"]]) {
      if (state !== "RUNNING" && state !== "PAUSED") break;
      const button = document.createElement("button");
      button.textContent = label;
      button.onclick = () => call(method, { mission_id: m.mission_id }).then(
        () => showError(null), showError);
      controls.appendChild(button);
    }
  }
}

function setCoordinator(up, message) {
  const badge = document.getElementById("coordinator");
  badge.className = "badge " + (up ? "up" : "down");
  badge.textContent = "coordinator: " + (up ? "up" : "unreachable " + (message || ""));
}

function follow() {
  const feed = new EventSource("/api/events");
  feed.addEventListener("fleet", (message) => {
    const event = JSON.parse(message.data);
    addEvent(event);
    refreshSystems().catch(showError);
  });
  feed.addEventListener("mission", (message) => {
    const status = JSON.parse(message.data);
    missions.set(status.mission_id, status);
    renderMissions();
  });
  feed.addEventListener("gateway", (message) => {
    const state = JSON.parse(message.data);
    setCoordinator(state.coordinator_up, state.message);
    if (state.coordinator_up) refreshSystems().catch(showError);
  });
}

document.getElementById("start-mission").addEventListener("submit", (event) => {
  event.preventDefault();
  const form = new FormData(event.target);
  const request = { file_path: form.get("file_path") };
  if (form.get("robot_id")) request.robot_id = form.get("robot_id");
  call("StartMission", request).then(() => showError(null), showError);
});

document.getElementById("emergency-land").addEventListener("submit", (event) => {
  event.preventDefault();
  const form = new FormData(event.target);
  call("EmergencyLand", { robot_id: form.get("robot_id"), reason: "console operator" })
    .then(() => showError(null), showError);
});

follow();
refreshSystems().catch(showError);
