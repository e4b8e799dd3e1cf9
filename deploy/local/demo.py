"""The demo mission through the coordinator, and what the report is made of:
the coordinator's event stream (timeline), the simulator's ground truth
(trajectory), the behavior systems' /metrics (the paper's a, t1, t2, t3) and
/proc (memory, CPU).
"""

import re
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
    """One line per mission step change (and per mission state change)."""

    def __init__(self, out):
        self._out = out
        self._start = time.monotonic()
        self._seen = []  # (state, cause) per step record index
        self._state = None

    def _line(self, text):
        self._out(f"  [{time.monotonic() - self._start:6.1f} s] {text}")

    def update(self, status):
        for i, record in enumerate(status.get("steps", [])):
            key = (record.get("state"), record.get("cause"))
            if i < len(self._seen) and self._seen[i] == key:
                continue
            if i >= len(self._seen):
                self._seen.append(key)
            else:
                self._seen[i] = key
            label = f"{record.get('name', '?')} ({record.get('behavior', '-')})"
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

def run_mission(coordinator, mission_path, robot_id, mission_id, timeout_s, out, on_status):
    """StartMission with the file, then WatchMission until it ends; returns
    the final MissionStatus (dict), also handing each status to on_status.
    On a wall-clock time-out the mission is aborted."""
    progress = ProgressPrinter(out)
    started = coordinator.call(COORDINATOR, "StartMission",
                               {"file_path": mission_path, "robot_id": robot_id,
                                "mission_id": mission_id})
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
        elif name == "behaviorlib_activation_seconds_sum":
            row(labels)["activation_sum_s"] = value
        elif name == "behaviorlib_activation_seconds_count":
            row(labels)["activation_count"] = int(value)
    figures = []
    for r in rows.values():
        ticks = r.get("monitoring_ticks", 0)
        starts = r.get("activation_count", 0)
        r["a"] = r.get("activations", 0)
        r["t1_us"] = r.get("monitoring_sum_s", 0.0) / ticks * 1e6 if ticks else None
        r["t2_ms"] = r.get("monitoring_sum_s", 0.0) * 1e3
        r["t3_ms"] = r.get("activation_sum_s", 0.0) / starts * 1e3 if starts else None
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
