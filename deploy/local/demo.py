"""The demo missions through the coordinator, and what the report is made
of: the coordinator's event stream (timeline), the simulator's ground truth
(trajectory), the behavior systems' /metrics (the paper's a, t1, t2, t3) and
/proc (memory, CPU), the coordinator's belief memory (QR markers found, the
other robots' positions, the saved map) and the map_coverage tool (how much
of the world's free space the saved map covers).
"""

import json
import os
import re
import subprocess
import threading
import time
import urllib.request

from google.protobuf import duration_pb2, timestamp_pb2

import rpc

COORDINATOR = "behaviorlib.v1.Coordinator"
SIMULATOR = "behaviorlib.v1.Simulator"
FINAL_MISSION_STATES = ("MISSION_STATE_SUCCEEDED", "MISSION_STATE_FAILED",
                        "MISSION_STATE_ABORTED")


def timestamp_s(text):
    """Seconds of a proto JSON Timestamp ("1970-01-01T00:00:12.5Z")."""
    if not text:
        return None
    t = timestamp_pb2.Timestamp()
    t.FromJsonString(text)
    return t.ToNanoseconds() * 1e-9


def duration_s(text):
    """Seconds of a proto JSON Duration ("12.5s")."""
    if not text:
        return None
    d = duration_pb2.Duration()
    d.FromJsonString(text)
    return d.ToNanoseconds() * 1e-9


def short_cause(cause):
    return (cause or "").replace("TERMINATION_CAUSE_", "")


class _StreamThread:
    """Reads a server stream on a daemon thread until stop()."""

    def __init__(self, name):
        self._call = None
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self.error = None

    def start(self):
        self._thread.start()

    def _open(self):
        raise NotImplementedError

    def _handle(self, reply):
        raise NotImplementedError

    def _run(self):
        try:
            self._call = self._open()
            for reply in self._call:
                self._handle(reply)
        except rpc.grpc.RpcError as error:
            if error.code() != rpc.grpc.StatusCode.CANCELLED:
                self.error = f"{error.code().name}: {error.details()}"

    def stop(self):
        if self._call is not None:
            self._call.cancel()
        self._thread.join(timeout=5)


class EventRecorder(_StreamThread):
    """The coordinator's WatchEvents for one robot, from the start of its
    retained history; each event kept with the wall time it arrived."""

    def __init__(self, coordinator, robot_id):
        super().__init__("coordinator-events")
        self._coordinator = coordinator
        self._robot_id = robot_id
        self._cv = threading.Condition()
        self.events = []  # FleetEvent dicts with "received_wall_s" added

    def _open(self):
        return self._coordinator.stream(COORDINATOR, "WatchEvents",
                                        {"since_seq": 0, "robot_ids": [self._robot_id]})

    def _handle(self, reply):
        if reply.WhichOneof("kind") != "event":
            return
        event = rpc.to_dict(reply.event)
        event["received_wall_s"] = time.time()
        with self._cv:
            self.events.append(event)
            self._cv.notify_all()

    def behavior_events(self):
        with self._cv:
            return [e["behavior_event"] for e in self.events if "behavior_event" in e]

    def wait_finished(self, activation_id, timeout_s):
        """The finished BehaviorEvent of `activation_id`, or None."""
        deadline = time.monotonic() + timeout_s
        with self._cv:
            while True:
                for e in self.events:
                    b = e.get("behavior_event", {})
                    if b.get("activation_id") == activation_id and "finished" in b:
                        return b
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                self._cv.wait(min(left, 0.2))


    def wait_settled(self, timeout_s):
        """Waits until every activation seen has its finished event (the
        mission's last deactivations reach the stream just after its end);
        True when they all have."""
        deadline = time.monotonic() + timeout_s
        with self._cv:
            while True:
                started, finished = set(), set()
                for e in self.events:
                    b = e.get("behavior_event", {})
                    if "activated" in b:
                        started.add(b.get("activation_id"))
                    elif "finished" in b:
                        finished.add(b.get("activation_id"))
                left = deadline - time.monotonic()
                if started <= finished or left <= 0:
                    return started <= finished
                self._cv.wait(min(left, 0.2))


class TrajectoryRecorder(_StreamThread):
    """The simulator's ground truth of one vehicle (Simulator.WatchState)."""

    def __init__(self, simulator, robot_id, rate_hz=20.0):
        super().__init__("simulator-state")
        self._simulator = simulator
        self._robot_id = robot_id
        self._rate_hz = rate_hz
        self._lock = threading.Lock()
        self.samples = []  # (t_sim_s, x, y, z, flight_state)

    def _open(self):
        return self._simulator.stream(SIMULATOR, "WatchState",
                                      {"robot_ids": [self._robot_id], "rate_hz": self._rate_hz})

    def _handle(self, reply):
        state = reply.state
        p = state.pose.position_m
        stamp = state.header.stamp.seconds + state.header.stamp.nanos * 1e-9
        flight_state = state.DESCRIPTOR.fields_by_name["flight_state"].enum_type \
            .values_by_number[state.flight_state].name
        with self._lock:
            self.samples.append((stamp, p.x, p.y, p.z, flight_state))

    def snapshot(self):
        with self._lock:
            return list(self.samples)


class BeliefRecorder(_StreamThread):
    """The coordinator's WatchBeliefs under a key prefix: every write (the
    current beliefs first), kept in order."""

    def __init__(self, coordinator, prefix):
        super().__init__("coordinator-beliefs")
        self._coordinator = coordinator
        self._prefix = prefix
        self._lock = threading.Lock()
        self.beliefs = []  # Belief dicts

    def _open(self):
        return self._coordinator.stream(COORDINATOR, "WatchBeliefs",
                                        {"prefix": self._prefix, "since_version": 0})

    def _handle(self, reply):
        belief = rpc.to_dict(reply.belief)
        with self._lock:
            self.beliefs.append(belief)

    def snapshot(self):
        with self._lock:
            return list(self.beliefs)


def swarm_tracks(beliefs, robot_id):
    """Every position of another robot that `robot_id` recorded
    ({robot}/swarm/{other}/position writes, from a BeliefRecorder): {other:
    [(stamp_s, x, y, z)]} in the order written."""
    prefix = f"{robot_id}/swarm/"
    tracks = {}
    for belief in beliefs:
        key = belief.get("key", "")
        rest = key[len(prefix):] if key.startswith(prefix) else ""
        value = belief.get("value")
        if (belief.get("deleted") or not rest.endswith("/position") or rest.count("/") != 1
                or not isinstance(value, dict)):
            continue
        stamp = timestamp_s(value.get("header", {}).get("stamp"))
        x, y, z = _vector(value.get("pose", {}).get("position_m"))
        tracks.setdefault(rest.split("/")[0], []).append((stamp, x, y, z))
    return tracks


def wait_for_systems(coordinator, robot_id, systems, timeout_s=20.0):
    """Waits until the coordinator has every one of `systems` UP (they
    register on their own when they start)."""
    deadline = time.monotonic() + timeout_s
    states = {}
    while time.monotonic() < deadline:
        reply = coordinator.call(COORDINATOR, "ListSystems", {"robot_id": robot_id})
        states = {s.get("system", s.get("address")): s.get("state", "")
                  for s in reply.get("systems", [])}
        if all(states.get(name) == "SYSTEM_STATE_UP" for name in systems):
            return
        time.sleep(0.1)
    raise RuntimeError(f"behavior systems not UP at the coordinator within {timeout_s} s: "
                       f"{states}")


# --- progress ----------------------------------------------------------------

class ProgressPrinter:
    """One line per mission step change (and per mission state change);
    `prefix` (e.g. "drone2: ") tells the robots' missions apart."""

    def __init__(self, out, prefix="", start=None):
        self._out = out
        self._prefix = prefix
        self._start = time.monotonic() if start is None else start
        self._seen = []  # (state, cause) per step record index
        self._state = None

    def _line(self, text):
        self._out(f"  [{time.monotonic() - self._start:6.1f} s] {self._prefix}{text}")

    def update(self, status):
        for i, record in enumerate(status.get("steps", [])):
            key = (record.get("state"), record.get("cause"))
            if i < len(self._seen) and self._seen[i] == key:
                continue
            if i >= len(self._seen):
                self._seen.append(key)
            else:
                self._seen[i] = key
            what = (record.get('behavior')
                    or (f"call {record['call']}" if record.get('call') else None)
                    or (f"parallel, {record['parallel']}" if record.get('parallel') else None)
                    or (f"wait for {record['wait_for']}" if record.get('wait_for') else '-'))
            if len(status.get("robot_ids", [])) > 1 and record.get("robot_id"):
                what += f" on {record['robot_id']}"
            label = f"{record.get('name', '?')} ({what})"
            attempt = int(record.get("attempt", 1))
            if attempt > 1:
                label += f" attempt {attempt}"
            state = record.get("state", "").replace("MISSION_STEP_STATE_", "").lower()
            if state == "finished":
                text = f"{label}: {short_cause(record.get('cause'))}"
            else:
                text = f"{label}: {state}"
            if record.get("message") and state != "running":
                text += f" - {record['message']}"
            self._line(text)
        state = status.get("state")
        if state != self._state:
            self._state = state
            if state and state != "MISSION_STATE_RUNNING":
                message = f" - {status['message']}" if status.get("message") else ""
                safety = " (safety steps)" if status.get("in_safety_steps") else ""
                self._line(f"mission {status.get('name', '')}: "
                           f"{state.replace('MISSION_STATE_', '')}{safety}{message}")


# --- the mission ---------------------------------------------------------------

def mission_request(path, robot_id, mission_id):
    """A StartMission request carrying the mission file's text: the
    coordinator reads files only inside its --mission-dir, and this file is
    the launcher's."""
    with open(path, encoding="utf-8") as f:
        text = f.read()
    return {"text": text, "source_name": path, "robot_id": robot_id, "mission_id": mission_id}


def run_mission(coordinator, mission_path, robot_id, mission_id, timeout_s, out, on_status):
    """StartMission with the file, then WatchMission until it ends; returns
    the final MissionStatus (dict), also handing each status to on_status.
    On a wall-clock time-out the mission is aborted."""
    progress = ProgressPrinter(out)
    started = coordinator.call(COORDINATOR, "StartMission",
                               mission_request(mission_path, robot_id, mission_id))
    status = started.get("status", {})
    on_status(status)
    progress.update(status)
    watch = coordinator.stream(COORDINATOR, "WatchMission", {"mission_id": mission_id},
                               timeout=timeout_s)
    try:
        for reply in watch:
            status = rpc.to_dict(reply.status)
            on_status(status)
            progress.update(status)
            if status.get("state") in FINAL_MISSION_STATES:
                break
    except rpc.grpc.RpcError as error:
        if error.code() != rpc.grpc.StatusCode.DEADLINE_EXCEEDED:
            raise
        out(f"  mission still {status.get('state')} after {timeout_s} s: aborting it")
        coordinator.call(COORDINATOR, "AbortMission",
                         {"mission_id": mission_id, "reason": "launcher time-out"})
    finally:
        watch.cancel()
    status = coordinator.call(COORDINATOR, "GetMission", {"mission_id": mission_id})["status"]
    on_status(status)
    return status


def run_missions(coordinator, missions, timeout_s, out, on_status):
    """Several robots' missions at once: StartMission for each of
    `missions` ([(robot_id, mission_path, mission_id)]) one after the other
    (the robot_id overrides the file's robot), then WatchMission on each
    until every one has ended. One progress line per step change, prefixed
    with the robot. Returns {robot_id: final MissionStatus (dict)}, also
    handing each status to on_status(robot_id, status). After `timeout_s`
    of wall time the missions still running are aborted."""
    lock = threading.Lock()

    def say(text):
        with lock:
            out(text)

    start = time.monotonic()
    deadline = start + timeout_s
    printers = {robot: ProgressPrinter(say, f"{robot}: ", start) for robot, _, _ in missions}
    statuses = {}

    def update(robot, status):
        with lock:
            statuses[robot] = status
        on_status(robot, status)
        printers[robot].update(status)

    started_ids = []
    try:
        for robot, path, mission_id in missions:
            reply = coordinator.call(COORDINATOR, "StartMission",
                                     mission_request(path, robot, mission_id))
            started_ids.append(mission_id)
            update(robot, reply.get("status", {}))
    except rpc.grpc.RpcError:
        for mission_id in started_ids:  # not left flying on its own
            try:
                coordinator.call(COORDINATOR, "AbortMission",
                                 {"mission_id": mission_id,
                                  "reason": "another robot's mission could not start"})
            except rpc.grpc.RpcError:
                pass
        raise

    errors = []

    def watch(robot, mission_id):
        if statuses.get(robot, {}).get("state") in FINAL_MISSION_STATES:
            return
        call = coordinator.stream(COORDINATOR, "WatchMission", {"mission_id": mission_id},
                                  timeout=max(0.1, deadline - time.monotonic()))
        try:
            for reply in call:
                status = rpc.to_dict(reply.status)
                update(robot, status)
                if status.get("state") in FINAL_MISSION_STATES:
                    break
        except rpc.grpc.RpcError as error:
            if error.code() not in (rpc.grpc.StatusCode.DEADLINE_EXCEEDED,
                                    rpc.grpc.StatusCode.CANCELLED):
                errors.append(error)
        finally:
            call.cancel()

    threads = [threading.Thread(target=watch, args=(robot, mission_id), daemon=True,
                                name=f"mission-{robot}") for robot, _, mission_id in missions]
    for thread in threads:
        thread.start()
    for thread in threads:
        while thread.is_alive():  # a signal reaches the launcher meanwhile
            thread.join(0.2)
    if errors:
        raise errors[0]
    for robot, _, mission_id in missions:
        state = statuses.get(robot, {}).get("state")
        if state not in FINAL_MISSION_STATES:
            say(f"  {robot}: mission still {state} after {timeout_s} s: aborting it")
            coordinator.call(COORDINATOR, "AbortMission",
                             {"mission_id": mission_id, "reason": "launcher time-out"})
    # An aborted mission ends once its safety steps have run.
    settle = time.monotonic() + 30.0
    final = {}
    for robot, _, mission_id in missions:
        while True:
            status = coordinator.call(COORDINATOR, "GetMission",
                                      {"mission_id": mission_id})["status"]
            if status.get("state") in FINAL_MISSION_STATES or time.monotonic() > settle:
                break
            time.sleep(0.2)
        on_status(robot, status)
        final[robot] = status
    return final


# --- belief memory ---------------------------------------------------------------

def write_belief(coordinator, key, value, writer="launcher"):
    """WriteBelief of a plain JSON value (a string, a number, a dict...)."""
    coordinator.call(COORDINATOR, "WriteBelief", {"key": key, "value": value, "writer": writer})


def list_beliefs(coordinator, prefix):
    """The current beliefs whose key starts with `prefix` (ListBeliefs), by
    key; values in JSON form."""
    reply = coordinator.call(COORDINATOR, "ListBeliefs", {"prefix": prefix})
    return {b["key"]: b for b in reply.get("beliefs", []) if not b.get("deleted")}


def _vector(value):
    """[x, y, z] of a Vector3 in JSON form (zeros are omitted there)."""
    value = value if isinstance(value, dict) else {}
    return [float(value.get(axis, 0.0)) for axis in ("x", "y", "z")]


def robot_findings(coordinator, robot_id):
    """What the application behaviors left in belief memory for `robot_id`
    (keys "{robot}/..."):
      map_file      the file SAVE_OCCUPANCY_GRID wrote ({robot}/map_file)
      markers       PAY_ATTENTION_TO_QR_CODES' codes ({robot}/markers/<text>):
                    [{text, position_m, sightings, marker_size_m, key}],
                    with marker_count from {robot}/markers
      swarm         PAY_ATTENTION_TO_ROBOT_MESSAGES' records ({robot}/swarm/...):
                    positions {other: {position_m, stamp_s, key}},
                    messages [{n, from, text, payload}], message_count,
                    malformed_count
    Only the keys found are present."""
    beliefs = list_beliefs(coordinator, robot_id + "/")
    found = {}
    map_file = beliefs.get(f"{robot_id}/map_file")
    if map_file is not None:
        found["map_file"] = map_file.get("value")

    markers_prefix = f"{robot_id}/markers/"
    markers = []
    for key, belief in beliefs.items():
        if not key.startswith(markers_prefix):
            continue
        value = belief.get("value") if isinstance(belief.get("value"), dict) else {}
        markers.append({"text": value.get("text", key[len(markers_prefix):]),
                        "position_m": _vector(value.get("position_m")),
                        "sightings": int(value.get("sightings", 0)),
                        "marker_size_m": value.get("marker_size_m"), "key": key})
    listed = beliefs.get(f"{robot_id}/markers")
    if markers or listed is not None:
        found["markers"] = sorted(markers, key=lambda m: m["text"])
        value = listed.get("value") if listed is not None else None
        found["marker_count"] = (int(value.get("count", 0)) if isinstance(value, dict)
                                 else len(markers))

    swarm_prefix = f"{robot_id}/swarm/"
    swarm = {"positions": {}, "messages": []}
    seen = False
    for key, belief in beliefs.items():
        if not key.startswith(swarm_prefix):
            continue
        seen = True
        rest = key[len(swarm_prefix):]
        value = belief.get("value")
        if rest.endswith("/position") and rest.count("/") == 1 and isinstance(value, dict):
            other = rest.split("/")[0]
            header = value.get("header", {})
            swarm["positions"][other] = {
                "position_m": _vector(value.get("pose", {}).get("position_m")),
                "stamp_s": timestamp_s(header.get("stamp")), "key": key}
        elif rest.startswith("messages/") and isinstance(value, dict):
            number = rest.split("/", 1)[1]
            swarm["messages"].append({"n": int(number) if number.isdigit() else number,
                                      "from": value.get("from", ""),
                                      "text": value.get("text", ""),
                                      "payload": value.get("payload")})
        elif rest in ("message_count", "malformed_count"):
            swarm[rest] = int(value or 0)
    if seen:
        swarm["messages"].sort(key=lambda m: (isinstance(m["n"], str), m["n"]))
        found["swarm"] = swarm
    return found


def measure_map_coverage(tool, world_path, map_file, timeout_s=120.0, cells_path=None):
    """Runs `tool --world WORLD --map FILE --json` (map_coverage: how much of
    the world's free space the saved map knows as free) and returns its JSON
    object; {"error": why} when it cannot be measured. With `cells_path`, the
    map's occupied cells at the scan height go to that file (--cells)."""
    if not tool or not os.access(tool, os.X_OK):
        return {"error": f"{tool} is not built"}
    if not world_path:
        return {"error": "no --world was given (the empty field has no free space to map)"}
    if not isinstance(map_file, str) or not os.path.isfile(map_file):
        return {"error": f"the map file {map_file!r} does not exist"}
    argv = [tool, "--world", world_path, "--map", map_file, "--json"]
    if cells_path:
        argv += ["--cells", cells_path]
    try:
        result = subprocess.run(argv, capture_output=True, text=True, timeout=timeout_s)
    except (OSError, subprocess.TimeoutExpired) as error:
        return {"error": f"{' '.join(argv)}: {error}"}
    if result.returncode != 0:
        return {"error": f"{' '.join(argv)} exited with code {result.returncode}: "
                         f"{(result.stderr or result.stdout).strip()[-500:]}"}
    try:
        measured = json.loads(result.stdout)
    except ValueError as error:
        return {"error": f"{' '.join(argv)} printed no JSON object ({error}): "
                         f"{result.stdout.strip()[-500:]}"}
    if not isinstance(measured, dict):
        return {"error": f"{' '.join(argv)} printed {type(measured).__name__}, not an object"}
    return measured


# --- metrics and /proc -----------------------------------------------------------

_SAMPLE = re.compile(r'^([a-zA-Z_:][a-zA-Z0-9_:]*)(?:\{(.*)\})?\s+(\S+)')
_LABEL = re.compile(r'([a-zA-Z_][a-zA-Z0-9_]*)="((?:[^"\\]|\\.)*)"')


def scrape(metrics_address, timeout_s=5.0):
    """The samples of a /metrics page: [(name, {labels}, value)]."""
    with urllib.request.urlopen(f"http://{metrics_address}/metrics", timeout=timeout_s) as page:
        text = page.read().decode()
    samples = []
    for line in text.splitlines():
        if not line or line.startswith("#"):
            continue
        match = _SAMPLE.match(line)
        if match:
            labels = dict(_LABEL.findall(match.group(2) or ""))
            samples.append((match.group(1), labels, float(match.group(3))))
    return samples


def behavior_figures(samples):
    """Per (system, behavior): the paper's a (activations), t1 (mean
    monitoring time per tick), t2 (accumulated monitoring time), t3 (mean
    activation time), and terminations by cause."""
    rows = {}

    def row(labels):
        key = (labels.get("system", ""), labels.get("behavior", ""))
        return rows.setdefault(key, {"system": key[0], "behavior": key[1], "robot":
                                     labels.get("robot", ""), "terminations": {}})

    for name, labels, value in samples:
        if "behavior" not in labels:
            continue
        if name == "behaviorlib_activations_total":
            row(labels)["activations"] = int(value)
        elif name == "behaviorlib_terminations_total" and value:
            row(labels)["terminations"][labels.get("cause", "?")] = int(value)
        elif name == "behaviorlib_monitoring_seconds_sum":
            row(labels)["monitoring_sum_s"] = value
        elif name == "behaviorlib_monitoring_seconds_count":
            row(labels)["monitoring_ticks"] = int(value)
        elif name == "behaviorlib_monitoring_cpu_seconds_sum":
            row(labels)["monitoring_cpu_sum_s"] = value
        elif name == "behaviorlib_activation_seconds_sum":
            row(labels)["activation_sum_s"] = value
        elif name == "behaviorlib_activation_seconds_count":
            row(labels)["activation_count"] = int(value)
        elif name == "behaviorlib_activate_call_seconds_sum":
            row(labels)["activate_call_sum_s"] = value
    figures = []
    for r in rows.values():
        ticks = r.get("monitoring_ticks", 0)
        starts = r.get("activation_count", 0)
        r["a"] = r.get("activations", 0)
        r["t1_us"] = r.get("monitoring_sum_s", 0.0) / ticks * 1e6 if ticks else None
        # The same on the thread's CPU clock: what the functions cost, without preemption.
        r["t1_cpu_us"] = (r["monitoring_cpu_sum_s"] / ticks * 1e6
                          if ticks and "monitoring_cpu_sum_s" in r else None)
        r["t2_ms"] = r.get("monitoring_sum_s", 0.0) * 1e3
        r["t3_ms"] = r.get("activation_sum_s", 0.0) / starts * 1e3 if starts else None
        # Of t3, the activate call itself (checkSituation, onActivate): the rest is the wait
        # for the first tick.
        r["t3_call_ms"] = (r["activate_call_sum_s"] / r["activations"] * 1e3
                           if r.get("activations") and "activate_call_sum_s" in r else None)
        figures.append(r)
    return sorted(figures, key=lambda r: (r["system"], r["behavior"]))


def collect_figures(stack, out):
    """Scrapes every behavior system's /metrics; reads /proc of every
    process. Returns (behavior rows, process rows)."""
    behaviors, processes = [], []
    for p in stack.processes:
        if p.role == "behavior_system" and p.metrics_port and p.running():
            try:
                behaviors.extend(behavior_figures(scrape(p.metrics_address)))
            except OSError as error:
                out(f"  cannot scrape {p.name} at {p.metrics_address}: {error}")
        processes.append({"name": p.name, "pid": p.pid, "grpc": p.address,
                          "metrics": p.metrics_address, "log": p.log_path,
                          **(p.proc_stats() or {})})
    return behaviors, processes
