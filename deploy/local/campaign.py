#!/usr/bin/python3
"""A campaign: one mission flown over many seeds, and fault schedules, in the
deterministic mode (--time-scale max), and a report of how it went.

    deploy/local/campaign.py --build-dir build --seeds 50
    deploy/local/campaign.py --seed-list 1,2,7 --fault take_off+3:motor_off:motor=0@seeds=7
    deploy/local/campaign.py --seeds 20 --fault-schedule faults.yaml --check-determinism
    deploy/local/campaign.py --seeds 50 --mission deploy/missions/demo.yaml -- \\
        --systems quadrotor_motion_with_pid_control,multi_sensor_fusion

Every run flies the mission (default deploy/missions/demo.yaml) once, with
one seed and the faults of that seed; the same seed and faults give the same
result: the steps end with the same causes (and, but for the variations the
mission itself shows, see --check-determinism, after the same active times).

Faults (--fault, repeatable, and --fault-schedule FILE) are written
[STEP+]T:KIND[:ARGS][@seeds=LIST] and injected with Simulator.InjectFailure
at the simulator's first 10 ms quantum at or after their time:
  T       simulated seconds from the mission's first activation (t = 0 of a
          run's timeline), or with STEP+ from the activation of the first
          attempt of that step of the mission. Prefer STEP+T: the
          coordinator is not in the deterministic mode's barrier, so when a
          step starts after the mission's start varies from run to run (by
          up to 3 s on a loaded machine), and a fault timed from the
          mission's start then hits different moments of the flight;
  KIND    the proto's component and type in lower case: motor_off,
          motor_degraded, gps_stuck, imu_garbage, baro_noisy,
          battery_degraded, lidar_intermittent, wind_set, gps_ok (clears),
          ... (deploy/local/faults.py lists them);
  ARGS    comma-separated key=value: robot= (default the mission's),
          motor=0..3, intensity=0..1 (noisy, intermittent, degraded),
          delay=S (delayed), wind_x=, wind_y=, wind_z= (m/s), gust= (m/s);
  @seeds= only for these seeds: 3, 3,7 or 1-10,15 (default every seed).

    --fault take_off+3:motor_off:motor=0           motor 0 stops 3 s into the take-off
    --fault fly_square+4.5:motor_degraded:motor=2,intensity=0.5@seeds=3
    --fault 5:wind_set:wind_x=6,gust=2@seeds=1-5   from 5 s after the mission's start

A schedule file (YAML or JSON) lists the same, as strings or mappings:
    faults:
      - "take_off+3:motor_off:motor=0@seeds=3"
      - {step: fly_square, at_s: 4.5, kind: gps_stuck}
      - {at_s: 5, kind: wind_set, wind_x: 6, gust: 2, seeds: [1, 2]}

The campaign follows the simulator's time grants while a fault is to come
(the simulator waits for it every quantum), so a fault is never late for a
reason of this process; but it learns when a step started from the
coordinator's events, which on a loaded machine may come after the fault's
time: such a run is flown again (at most three flights), and the report
marks a fault that was still late.

How it runs: --jobs stacks at once (default: the number of cores), each
started by launch.py for one run (serving, --time-scale max --seed N
--enable-fault-injection --no-console; extra launcher arguments go after
`--`): the flight recorder (behaviorctl record), the mission through the
coordinator, the faults; then the stack is stopped. With
--missions-per-stack N a stack flies up to N missions one after the other,
each after Simulator.Reset with its seed (time back to 0, the vehicle at its
start, faults cleared, every random process reseeded) and a situation check
of each behavior system, which makes it follow the new time at once (see
LaunchedStack.reset); it is replaced after a mission that did not succeed
and after a process restart. That is not the default: it saves nothing
with the whole stack (50 demo runs, two stacks at once: 272 s against
275 s, the same CPU time) and about 18 % with the light one (--systems
quadrotor_motion_with_pid_control), but a Reset leaves state behind, and
one reused run of fifty failed in a way the same seed on a new stack does
not (TAKE_OFF: "the velocity estimate is 1.01 s old"): docs/benchmarks.md.

The report (--out DIR; default a new directory under /tmp), report.md and
report.json:
- the success rate with its 95 % Wilson score interval;
- per step (and recurrent behavior), how its attempts ended: termination
  causes, counted; "not reached" when the mission ended before the step;
- per step, its active time in simulated seconds: min, median, p90, max;
- the worst runs, failed ones first, then the longest (simulated time from
  the first activation to the end of the last step): seed, faults, the step
  that failed and its cause, the run directory (runs/seed-N:
  recordings/flight.mcap, report.md with trajectory.png and timeline.png,
  logs/ with every process's lines of that run) and the command line that
  flies it again. Only the --keep-worst K worst runs keep their
  directories; the others are deleted as the campaign goes. With
  --missions-per-stack, a kept run that followed other missions on its
  stack is flown again on a new stack, so that its recording holds only its
  own flight (behaviorctl record replays the coordinator's earlier events),
  and the report says whether that gave the same result;
- with --check-determinism[=SEED], that seed (default the first) flown again
  on a new stack after the campaign, and whether both runs give the same
  result (deploy/local/determinism.py: the same causes, step active times
  within --duration-tolerance-s, flown paths within --path-tolerance-m).
  The demo mission itself varies now and then: FOLLOW_PATH ends 4.4 s later
  in about one run in twelve, LAND up to 1.2 s later; the check reports it;
- one row per run.

Exit code: 0 when the campaign ran, whether or not its missions succeeded;
1 when the success rate is below --min-success-rate, or --check-determinism
found different results; 2 for bad arguments; 3 when the tooling failed (a
stack did not start, a mission could not be started or followed); 128 + the
signal's number when stopped by a signal.
"""

import argparse
import json
import math
import os
import queue
import shlex
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import traceback

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import demo  # noqa: E402
import determinism  # noqa: E402
import faults as faultlib  # noqa: E402
import report  # noqa: E402
import rpc  # noqa: E402
from launch import DEMO_MISSION, REPO, FlightRecorder, world_file  # noqa: E402
from stack import popen_with_launcher, read_ports  # noqa: E402

LAUNCHER = os.path.join(os.path.dirname(os.path.abspath(__file__)), "launch.py")
# The launcher prints this once every process is up and the coordinator has its
# behavior systems UP (launch.py wait_until_up).
SERVING_LINE = "Ctrl-C stops everything."
# Launcher options the campaign sets itself (or that it cannot follow).
OWN_LAUNCHER_OPTIONS = ("--demo", "--time-scale", "--seed", "--run-dir", "--build-dir",
                        "--mission", "--vehicles", "--robot-id", "--tls", "--record",
                        "--no-record", "--record-topics", "--enable-fault-injection",
                        "--console-listen")
BEHAVIOR_SYSTEM = "behaviorlib.v1.BehaviorSystem"
SUCCEEDED = "MISSION_STATE_SUCCEEDED"
NOT_REACHED = "not reached"
# A run whose fault came late (its anchor reached the campaign after the
# fault's time) is flown again, up to this many flights in all.
LATE_FLIGHTS = 3
EXIT_CHECK_FAILED = 1
EXIT_TOOLING = 3


class Interrupted(Exception):
    """SIGINT, SIGTERM or SIGHUP reached the campaign."""

    def __init__(self, signum):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


class ToolingError(RuntimeError):
    """The campaign could not do its job (not a mission that failed)."""


def _on_signal(signum, _frame):
    raise Interrupted(signum)


_print_lock = threading.Lock()


def say(text=""):
    with _print_lock:
        print(text, flush=True)


def wilson_interval(successes, n, z=1.959964):
    """The Wilson score interval of a proportion (95 % by default)."""
    if n == 0:
        return 0.0, 1.0
    p = successes / n
    denominator = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / denominator
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denominator
    return max(0.0, centre - half), min(1.0, centre + half)


def percentile(values, q):
    """The q-th percentile (0..100) by linear interpolation between ranks."""
    ordered = sorted(values)
    if not ordered:
        return None
    rank = (len(ordered) - 1) * q / 100.0
    low, high = math.floor(rank), math.ceil(rank)
    return ordered[low] + (ordered[high] - ordered[low]) * (rank - low)


def relative(path):
    """A path as a command line shows it: relative to the repository's root
    when inside it."""
    path = os.path.abspath(path)
    inside = os.path.commonpath([path, REPO]) == REPO
    return os.path.relpath(path, REPO) if inside else path


# --- the mission file ----------------------------------------------------------

def mission_outline(path):
    """(name, robot, [(step name, behavior)], [recurrent behavior]) of a
    mission file: the steps in order, each fallback's after its step."""
    import yaml  # Debian's python3-yaml
    with open(path, encoding="utf-8") as f:
        mission = yaml.safe_load(f) or {}
    steps = []

    def walk(items, prefix):
        for i, step in enumerate(items or []):
            if not isinstance(step, dict):
                continue
            steps.append((step.get("name") or f"{prefix}step {i}", step.get("behavior", "")))
            walk(step.get("fallback"), f"{step.get('name') or f'step {i}'}/")

    walk(mission.get("steps"), "")
    recurrent = [r.get("behavior", "") for r in mission.get("recurrent") or []
                 if isinstance(r, dict)]
    return mission.get("name", ""), mission.get("robot", ""), steps, recurrent


# --- a stack -------------------------------------------------------------------

class StackEvents(demo.EventRecorder):
    """The coordinator's events of the robot for the stack's whole life; a
    mission's are those after mark(), which also hands every activation
    after it to `on_activated(behavior event, simulated time)`."""

    def __init__(self, coordinator, robot_id):
        super().__init__(coordinator, robot_id)
        self._watch = None  # (index, callback)

    def mark(self, on_activated=None):
        with self._cv:
            self._watch = (len(self.events), on_activated) if on_activated else None
            return len(self.events)

    def _handle(self, reply):
        with self._cv:
            before = len(self.events)
        super()._handle(reply)
        with self._cv:
            watch = self._watch
            event = (self.events[-1].get("behavior_event", {}) if len(self.events) > before
                     else {})
        t = demo.timestamp_s(event.get("time"))
        if watch is not None and "activated" in event and t is not None:
            watch[1](event, t)

    def since(self, index):
        with self._cv:
            return [e["behavior_event"] for e in self.events[index:] if "behavior_event" in e]


class Anchors:
    """Tells a FaultInjector when the mission started (its first activation)
    and when each step's first attempt was activated, in simulated time,
    from the activations as they arrive (StackEvents): a step whose behavior
    n steps before it also activate is that behavior's activation n + 1 (the
    coordinator's event stream is faster than its mission statuses).
    wrong(status) then names the steps for which the mission's final status
    (its step records name their activations) says otherwise."""

    def __init__(self, injector, outline):
        self._injector = injector
        self._lock = threading.Lock()
        self._occurrence = {}  # step name -> (behavior, how many steps before run it)
        counts = {}
        for name, behavior in outline:
            self._occurrence[name] = (behavior, counts.get(behavior, 0))
            counts[behavior] = counts.get(behavior, 0) + 1
        self._activations = {}  # behavior -> [activation ids, in order]
        self._used = {}  # step name -> the activation id taken as its first attempt
        self._started = False

    def on_activated(self, event, t_s):
        behavior, activation = event.get("behavior", ""), event.get("activation_id", "")
        with self._lock:
            first = not self._started
            self._started = True
            seen = self._activations.setdefault(behavior, [])
            seen.append(activation)
            steps = [name for name, (b, n) in self._occurrence.items()
                     if b == behavior and n == len(seen) - 1]
            for name in steps:
                self._used[name] = activation
        if first:
            self._injector.set_anchor(None, t_s)
        for name in steps:
            self._injector.set_anchor(name, t_s)

    def wrong(self, status):
        """The steps whose anchor was not their first attempt's activation."""
        first = {}
        for record in status.get("steps", []):
            if int(record.get("attempt", 1)) == 1 and record.get("activation_id"):
                first.setdefault(record.get("name", ""), record["activation_id"])
        with self._lock:
            return sorted(name for name, activation in self._used.items()
                          if name in first and first[name] != activation)


class LaunchedStack:
    """One stack started by launch.py in the deterministic mode with fault
    injection, serving until stop(); its run directory holds its processes'
    logs (and the launcher's output, launcher.log)."""

    def __init__(self, args, number):
        self.args = args
        self.number = number
        self.run_dir = os.path.join(args.out, "stacks", f"stack-{number}")
        self.process = None
        self.simulator = None
        self.coordinator = None
        self.broker = ""
        self.events = None
        self.pids = {}
        self.missions = 0
        self.seed = None
        self.systems = []

    def start(self, seed, timeout_s=60.0):
        """Starts the stack with the simulator's --seed `seed`."""
        os.makedirs(self.run_dir, exist_ok=True)
        self.seed = seed
        argv = self.launcher_argv(seed)
        self.log_path = os.path.join(self.run_dir, "launcher.log")
        with open(self.log_path, "w") as log:
            self.process = popen_with_launcher(argv, stdout=log, stderr=subprocess.STDOUT,
                                               stdin=subprocess.DEVNULL)
        deadline = time.monotonic() + timeout_s
        while True:
            text = self._log()
            if SERVING_LINE in text:
                break
            if self.process.poll() is not None or time.monotonic() > deadline:
                self.stop()
                raise ToolingError(f"stack {self.number} did not start (launcher exit "
                                   f"{self.process.returncode}); {self.log_path}:\n"
                                   + "\n".join(text.splitlines()[-15:]))
            time.sleep(0.05)
        self.simulator = rpc.Client(self._address("simulator"), [demo.SIMULATOR])
        self.coordinator = rpc.Client(self._address("coordinator"), [demo.COORDINATOR])
        self.broker = self._address("channel_broker")
        self.events = StackEvents(self.coordinator, self.args.robot)
        self.events.start()
        self.pids = self._read_pids()
        with open(os.path.join(self.run_dir, "prometheus_targets.json")) as f:
            names = [t["labels"]["system"] for t in json.load(f)
                     if t["labels"].get("job") == "behavior_system"]
        self.systems = [rpc.Client(self._address(name), [BEHAVIOR_SYSTEM]) for name in names]
        self._probes = {}  # client -> a behavior of it

    def launcher_argv(self, seed):
        """launch.py's command line: serving, in the deterministic mode, with
        fault injection and the simulator's --seed `seed`, without the
        console (tests/bench/stack/soak_bench.py starts its stack otherwise)."""
        return [sys.executable, LAUNCHER, "--build-dir", self.args.build_dir,
                "--run-dir", self.run_dir, "--time-scale", "max", "--enable-fault-injection",
                "--seed", str(seed), "--no-console", "--robot-id", self.args.robot,
                *self.args.launcher_args]

    def reset(self, seed):
        """Simulator.Reset with `seed` (time back to 0, the vehicle at its
        start, faults cleared, every random process reseeded), then each
        behavior system made to follow the new time at once: a situation
        check wakes it (FollowTimeRequest.wake), and it reports a time of
        the new run. The simulator's time grants do not start over with a
        Reset: each follower keeps the time it last reported, which is
        ahead of the new time, so until it reports again the simulator does
        not wait for it, and an idle one is not granted time until the old
        time plus a second. Without this, the first command of the next
        mission woke a system whose report came only after simulated time
        had run on without it (seen: 7.7 s in 0.2 s of wall time, and
        SELF_LOCALIZE_WITH_GROUND_TRUTH failing on "no ground truth")."""
        self.simulator.call(demo.SIMULATOR, "Reset", {"seed": seed})
        self.seed = seed
        for client in self.systems:
            if client not in self._probes:
                listed = client.call(BEHAVIOR_SYSTEM, "ListBehaviors", {})
                self._probes[client] = listed["behaviors"][0]["name"]
            client.call(BEHAVIOR_SYSTEM, "CheckBehaviorSituation",
                        {"behavior": self._probes[client]})

    def _log(self):
        try:
            with open(self.log_path, errors="replace") as f:
                return f.read()
        except OSError:
            return ""

    def _address(self, process):
        ports = read_ports(os.path.join(self.run_dir, "ports", process + ".ports"))
        return f"127.0.0.1:{ports['grpc_port']}"

    def _read_pids(self):
        try:
            with open(os.path.join(self.run_dir, "pids.json")) as f:
                return json.load(f)
        except (OSError, ValueError):
            return {}

    def intact(self):
        """Whether the launcher runs and no process was started again."""
        return (self.process is not None and self.process.poll() is None
                and self._read_pids() == self.pids)

    def log_sizes(self):
        logs = os.path.join(self.run_dir, "logs")
        return {name: os.path.getsize(os.path.join(logs, name)) for name in os.listdir(logs)
                if name.endswith(".log")}

    def copy_logs(self, since, run_dir):
        """Each process's lines written since `since` (log_sizes) into
        run_dir/logs/."""
        target = os.path.join(run_dir, "logs")
        os.makedirs(target, exist_ok=True)
        for name in sorted(self.log_sizes()):
            with open(os.path.join(self.run_dir, "logs", name), "rb") as source:
                source.seek(since.get(name, 0))
                with open(os.path.join(target, name), "wb") as copy:
                    shutil.copyfileobj(source, copy)

    def stop(self, timeout_s=30.0):
        if self.events is not None:
            self.events.stop()
        for client in (self.simulator, self.coordinator, *self.systems):
            if client is not None:
                client.close()
        if self.process is not None and self.process.poll() is None:
            self.process.send_signal(signal.SIGINT)
            try:
                self.process.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()


# --- one run -------------------------------------------------------------------

def step_rows(status, events, recurrent):
    """Every step attempt of a mission (its safety steps are not among them:
    the mission's message tells how they ended), then every activation of
    its recurrent behaviors: name, behavior, attempt, kind ("step" or
    "recurrent"), cause, message, duration_s (its active time in simulated
    seconds; None while active), end_s (when it ended, simulated time)."""
    finished = {e.get("activation_id"): e for e in events if "finished" in e}

    def ended(activation, fallback_cause="", fallback_message=""):
        event = finished.get(activation, {})
        f = event.get("finished", {})
        duration = demo.duration_s(f.get("active_duration"))
        return {"cause": demo.short_cause(f.get("cause")) or fallback_cause or "?",
                "message": f.get("message", "") or fallback_message,
                "duration_s": None if duration is None else round(duration, 6),
                "end_s": demo.timestamp_s(event.get("time"))}

    rows = []
    for record in status.get("steps", []):
        state = record.get("state", "").replace("MISSION_STEP_STATE_", "")
        rows.append({"name": record.get("name", ""), "behavior": record.get("behavior", ""),
                     "attempt": int(record.get("attempt", 1)), "kind": "step",
                     **ended(record.get("activation_id", ""),
                             demo.short_cause(record.get("cause")) or state,
                             record.get("message", ""))})
    attempts = {}
    for e in events:
        if "activated" in e and e.get("behavior") in recurrent:
            behavior = e["behavior"]
            attempts[behavior] = attempts.get(behavior, 0) + 1
            rows.append({"name": behavior, "behavior": behavior,
                         "attempt": attempts[behavior], "kind": "recurrent",
                         **ended(e.get("activation_id"), "ACTIVE")})
    return rows


def row_label(row):
    """A step row's name in the report's tables."""
    return row["name"] if row["kind"] == "step" else f"{row['kind']}: {row['name']}"


def failing_step(run):
    """What failed the mission: the last step attempt that ended neither
    GOAL_ACHIEVED nor INTERRUPTED, else a recurrent behavior that so ended,
    else the last step attempt; None for a success."""
    if run["state"] == SUCCEEDED:
        return None
    ok = ("GOAL_ACHIEVED", "INTERRUPTED")
    for kind in ("step", "recurrent"):
        candidates = [s for s in run["steps"] if s["kind"] == kind and s["cause"] not in ok]
        if candidates:
            return candidates[-1]
    steps = [s for s in run["steps"] if s["kind"] == "step"]
    return steps[-1] if steps else None


def fly(args, stack, seed, faults, run_dir):
    """One run on `stack`: the result dict (see report.json's runs)."""
    os.makedirs(run_dir, exist_ok=True)
    logs_before = stack.log_sizes()
    if stack.missions or stack.seed != seed:
        stack.reset(seed)  # a stack's next mission (--missions-per-stack)
    recorder = (FlightRecorder(args.build_dir, run_dir, stack.coordinator.address, stack.broker,
                               "", None) if args.record else None)
    trajectory = demo.TrajectoryRecorder(stack.simulator, args.robot)
    trajectory.start()
    injector = faultlib.FaultInjector(stack.simulator, args.robot, faults) if faults else None
    anchors = Anchors(injector, args.outline) if injector is not None else None
    if injector is not None:
        injector.start()
    first_event = stack.events.mark(anchors.on_activated if anchors else None)
    mission_id = f"campaign-{args.stamp}-seed{seed}-{stack.number}-{stack.missions}"
    stack.missions += 1
    try:
        wall_start = time.monotonic()
        status = demo.run_mission(stack.coordinator, args.mission, args.robot, mission_id,
                                  args.mission_timeout_s, lambda text: None,
                                  lambda status: None)
        mission_wall_s = time.monotonic() - wall_start
        settled = stack.events.wait_settled(5.0)
    finally:
        stack.events.mark()  # no more anchors
        injected = injector.stop() if injector is not None else []
        trajectory.stop()
        recording = recorder.stop(10.0) if recorder is not None else {}
    wrong = anchors.wrong(status) if anchors is not None else []
    for result in injected:
        if result["step"] in wrong:
            result["error"] = (f"timed from another activation than the first attempt of "
                               f"{result['step']}")
    events = stack.events.since(first_event)
    stack.copy_logs(logs_before, run_dir)
    times = [t for t in (demo.timestamp_s(e.get("time")) for e in events) if t is not None]
    t0 = min(times) if times else None
    steps = step_rows(status, events, args.recurrent)
    # The mission's own time: until its last step ended (what the
    # coordinator does after a failure, outside the barrier, is not timed).
    ends = [s.pop("end_s") for s in steps]
    ends = [t for t, s in zip(ends, steps) if t is not None and s["kind"] != "recurrent"]
    run = {"seed": seed, "faults": [f.spec(with_seeds=False) for f in faults],
           "state": status.get("state", "?"), "message": status.get("message", ""),
           "steps": steps, "sim_s": round(max(ends) - t0, 3) if ends else None,
           "t0_s": t0, "wall_s": round(mission_wall_s, 3), "injected": injected,
           "settled": settled, "stack": stack.number, "mission_on_stack": stack.missions,
           "run_dir": run_dir, "mission_id": mission_id,
           "recording": recorder.path if recorder is not None and recording else ""}
    failed = failing_step(run)
    run["failed_step"] = ({"name": row_label(failed), "behavior": failed["behavior"],
                           "attempt": failed["attempt"], "cause": failed["cause"],
                           "message": failed["message"]} if failed else None)
    # What a run's own report needs (kept runs only; not in report.json).
    run["_raw"] = {"status": status, "events": events, "samples": trajectory.snapshot()}
    return run


def describe(run):
    failed = run["failed_step"]
    state = run["state"].replace("MISSION_STATE_", "")
    where = (f" at {failed['name']} ({failed['behavior']}): {failed['cause']}" if failed
             else "")
    sim = f"{run['sim_s']:.1f} s simulated" if run["sim_s"] is not None else "no events"
    notes = [f"{i['fault']} " + (f"not injected: {i['error']}" if i["injected_at_s"] is None
                                 else f"{i['injected_at_s'] - i['at_s']:.2f} s late" if i["late"]
                                 else i["error"])
             for i in run["injected"] if i["late"] or i["error"]]
    note = "".join(f"; {n}" for n in notes)
    return f"{state}{where} ({sim}, {run['wall_s']:.1f} s wall{note})"


def reproduce_command(args, seed, faults):
    """The command line that flies this seed (with its faults) again."""
    argv = ["deploy/local/campaign.py", "--build-dir", relative(args.build_dir),
            "--mission", relative(args.mission), "--seed-list", str(seed)]
    for fault in faults:
        argv += ["--fault", fault.spec(with_seeds=False)]
    argv += ["--jobs", "1", "--out", f"/tmp/campaign-seed-{seed}"]
    if args.launcher_args:
        argv += ["--", *args.launcher_args]
    return " ".join(shlex.quote(a) for a in argv)


# --- the campaign --------------------------------------------------------------

def worst_order(run):
    """Sort key: failed runs first, then the longest (simulated, from the
    first activation to the end of the last step), then by seed."""
    return (run["state"] == SUCCEEDED, -(run["sim_s"] or 0.0), run["seed"], run.get("label", ""))


class Campaign:
    """The runs, flown by --jobs workers, each with its stack."""

    def __init__(self, args, items, first_stack=0):
        self.args = args
        self.items = queue.SimpleQueue()
        for item in items:
            self.items.put(item)
        self.runs = []
        self.lock = threading.Lock()
        self.error = None
        self.stop = threading.Event()
        self.stacks = []
        self.failed_stacks = []
        self.started_stacks = first_stack
        self.done = 0
        self.total = len(items)

    def _new_stack(self, seed):
        with self.lock:
            self.started_stacks += 1
            number = self.started_stacks
        stack = LaunchedStack(self.args, number)
        with self.lock:
            self.stacks.append(stack)
        try:
            stack.start(seed)
        except ToolingError:
            with self.lock:
                self.failed_stacks.append(stack.run_dir)
            raise
        return stack

    def _retire(self, stack):
        """Stops the stack and deletes its directory: its runs have their
        lines of its logs already (one that did not start keeps it)."""
        stack.stop()
        with self.lock:
            if stack in self.stacks:
                self.stacks.remove(stack)
            failed = stack.run_dir in self.failed_stacks
        if not failed:
            shutil.rmtree(stack.run_dir, ignore_errors=True)

    def _fly(self, item, stack):
        """Flies one item, on `stack` or (when None, or when it broke) a new
        one: (run, the stack it leaves running or None)."""
        for attempt in (1, 2):
            try:
                if stack is None:
                    stack = self._new_stack(item["seed"])
                run = fly(self.args, stack, item["seed"], item["faults"], item["run_dir"])
            except (ToolingError, rpc.grpc.RpcError) as error:
                text = (f"{error.code().name}: {error.details()}"
                        if isinstance(error, rpc.grpc.RpcError) else str(error))
                if stack is not None:
                    self._retire(stack)
                    stack = None
                if attempt == 2 or self.stop.is_set():
                    raise ToolingError(f"seed {item['seed']}: {text}") from None
                say(f"  seed {item['seed']}: {text.splitlines()[0]}; again on a new stack")
                continue
            limit = self.args.missions_per_stack
            if (run["state"] != SUCCEEDED or not stack.intact()
                    or (limit and stack.missions >= limit)):
                self._retire(stack)
                stack = None
            return run, stack
        raise AssertionError("unreachable")

    def worker(self):
        stack = None
        try:
            while not self.stop.is_set():
                try:
                    item = self.items.get_nowait()
                except queue.Empty:
                    break
                if stack is not None and item.get("fresh"):
                    self._retire(stack)
                    stack = None
                for flight in range(1, LATE_FLIGHTS + 1):
                    run, stack = self._fly(item, stack)
                    late = [i for i in run["injected"] if i["late"]]
                    if not late or flight == LATE_FLIGHTS or self.stop.is_set():
                        break
                    # Its anchor reached the campaign after the fault's time:
                    # the run did not follow the schedule.
                    say(f"  seed {item['seed']}: " + ", ".join(
                        f"{i['fault']} came {i['injected_at_s'] - i['at_s']:.2f} s late"
                        for i in late) + "; flown again")
                    shutil.rmtree(item["run_dir"], ignore_errors=True)
                run["label"] = item.get("label", "")
                run["flights"] = flight
                self._finished(run)
        except Exception as error:  # noqa: BLE001 - the campaign's own failure: exit 3
            if self.stop.is_set():
                return  # stopping (a signal, or another worker failed): not this one's fault
            if not isinstance(error, ToolingError):
                traceback.print_exc()
            with self.lock:
                self.error = self.error or f"{error}"
            self.stop.set()
        finally:
            if stack is not None:
                self._retire(stack)

    def _finished(self, run):
        with self.lock:
            self.runs.append(run)
            self.done += 1
            done = self.done
            # Only the worst --keep-worst campaign runs keep their directories
            # (a determinism recheck's is kept if it differs: decided later).
            ranked = sorted((r for r in self.runs if not r["label"]), key=worst_order)
            keep = {id(r) for r in ranked[:self.args.keep_worst]}
            doomed = [r for r in ranked if id(r) not in keep and r.get("run_dir")]
            for r in doomed:
                shutil.rmtree(r["run_dir"], ignore_errors=True)
                r["run_dir"] = ""
                r["recording"] = ""
                # The determinism check compares the flown paths.
                if r["seed"] != self.args.check_determinism:
                    r.pop("_raw", None)
        label = f" ({run['label']})" if run["label"] else ""
        say(f"[{done:>3}/{self.total}] seed {run['seed']}{label}: {describe(run)}")

    def run(self):
        workers = [threading.Thread(target=self.worker, name=f"worker-{i + 1}", daemon=True)
                   for i in range(max(1, min(self.args.jobs, self.total)))]
        for w in workers:
            w.start()
        try:
            for w in workers:
                while w.is_alive():  # signals reach the main thread meanwhile
                    w.join(0.2)
        finally:
            self.stop.set()
            with self.lock:
                stacks = list(self.stacks)
            for stack in stacks:
                stack.stop()
            for w in workers:
                w.join(35.0)


# --- the report ----------------------------------------------------------------

def cause_counts(args, runs):
    """Per step of the mission file, then per recurrent behavior and any
    other name seen: {cause: attempts}, with NOT_REACHED for the runs that
    ended before the step."""
    names = [name for name, _ in args.outline] + [f"recurrent: {b}" for b in args.recurrent]
    behaviors = dict(args.outline)
    behaviors.update({f"recurrent: {b}": b for b in args.recurrent})
    counts = {name: {} for name in names}
    for run in runs:
        seen = set()
        for step in run["steps"]:
            name = row_label(step)
            if name not in counts:
                counts[name] = {}
                names.append(name)
                behaviors[name] = step["behavior"]
            counts[name][step["cause"]] = counts[name].get(step["cause"], 0) + 1
            seen.add(name)
        for name in names[:len(args.outline) + len(args.recurrent)]:
            if name not in seen:
                counts[name][NOT_REACHED] = counts[name].get(NOT_REACHED, 0) + 1
    return [{"step": name, "behavior": behaviors.get(name, ""), "causes": counts[name]}
            for name in names]


def duration_stats(runs, steps):
    """Per entry of cause_counts: how many attempts have an active time, and
    its min, median, p90 and max (simulated seconds)."""
    rows = []
    for entry in steps:
        values = [s["duration_s"] for run in runs for s in run["steps"]
                  if s["duration_s"] is not None and row_label(s) == entry["step"]]
        if not values:
            rows.append({"step": entry["step"], "attempts": 0})
            continue
        rows.append({"step": entry["step"], "attempts": len(values),
                     "min_s": round(min(values), 3),
                     "median_s": round(statistics.median(values), 3),
                     "p90_s": round(percentile(values, 90), 3), "max_s": round(max(values), 3)})
    return rows


def write_run_report(args, run):
    """A kept run's own report (report.md, report.json, trajectory.png,
    timeline.png) in its directory, as the launcher's --demo writes it."""
    raw = run.pop("_raw", None)
    if raw is None or not run.get("run_dir"):
        return
    settings = {"mission": relative(args.mission), "robot_id": args.robot, "time_scale": "max",
                "world": args.world, "world_file": world_file(args.world), "seed": run["seed"],
                "run_dir": run["run_dir"], "wall_s": run["wall_s"], "interrupted": "",
                "vehicles": [args.robot], "missions": {args.robot: relative(args.mission)},
                "sensor_config": "", "console_url": "", "recording": run["recording"],
                "console_screenshot": "", "recording_messages": {}}
    robots = [{"robot_id": args.robot, "mission_file": relative(args.mission),
               "mission": raw["status"], "behavior_events": raw["events"],
               "samples": raw["samples"], "findings": {}}]
    try:
        report.write(run["run_dir"], settings, robots, [], [], True)
    except Exception as error:  # noqa: BLE001 - the campaign's report still goes out
        say(f"  seed {run['seed']}: its own report failed: {type(error).__name__}: {error}")


def public(run):
    """A run as report.json holds it."""
    return {k: v for k, v in run.items() if not k.startswith("_")}


def confirm_kept_runs(args, campaign):
    """Flies each kept run that was not its stack's first mission once more,
    on a new stack (behaviorctl record replays the coordinator's retained
    events, so a reused stack's recording begins with its earlier missions).
    The same result: the run's directory then holds the new flight, and
    run["new_stack"]["same"] is True. Another: both directories stay, and
    the new flight (returned, for its own report) is named there."""
    kept = [r for r in campaign.runs if not r["label"] and r.get("run_dir")
            and r["mission_on_stack"] > 1]
    if campaign.error or not kept:
        return []
    items = [{"seed": r["seed"], "faults": [f for f in args.faults if f.applies_to(r["seed"])],
              "run_dir": r["run_dir"] + "-new-stack", "label": "new stack", "fresh": True}
             for r in kept]
    say(f"the {len(items)} kept runs that followed other missions on their stacks, again on "
        f"new stacks:")
    second = Campaign(args, items, first_stack=campaign.started_stacks)
    second.run()
    campaign.failed_stacks += second.failed_stacks
    campaign.error = campaign.error or second.error
    by_seed = {r["seed"]: r for r in second.runs}
    different = []
    for run in kept:
        again = by_seed.get(run["seed"])
        if again is None:
            continue
        result = determinism.compare(comparable(run), comparable(again),
                                     args.duration_tolerance_s, args.path_tolerance_m)
        run["new_stack"] = {"same": result["same"], "differences": result["differences"],
                            "run_dir": ""}
        if not result["same"]:
            run["new_stack"]["run_dir"] = again["run_dir"]
            different.append(again)
            continue
        shutil.rmtree(run["run_dir"], ignore_errors=True)
        os.rename(again["run_dir"], run["run_dir"])
        run["_raw"] = again.pop("_raw", None)
        run["stack"], run["mission_on_stack"] = again["stack"], again["mission_on_stack"]
        if again["recording"]:
            run["recording"] = os.path.join(run["run_dir"], "recordings",
                                            os.path.basename(again["recording"]))
    return different


def comparable(run):
    """A run as determinism.compare takes it: its steps, and the ground truth
    from its first activation until its first fault, or else the end of its
    last step. After a fault the flight may be chaotic (a vehicle tumbling
    on three motors), so that a quantum's difference in when a step started
    grows to a metre; and what comes after a failure, the coordinator's
    safety actions, is outside the deterministic mode's barrier."""
    raw = run.get("_raw") or {}
    start, span = run.get("t0_s"), run.get("sim_s")
    if start is None or span is None:
        return {"steps": run["steps"], "samples": []}
    faults = [i["mission_s"] for i in run["injected"] if i.get("mission_s") is not None]
    end = start + min([span] + faults)
    samples = [s for s in raw.get("samples", []) if start <= s[0] <= end]
    return {"steps": run["steps"], "samples": samples}


def build_report(args, runs, recheck, wall_s, error, interrupted):
    campaign_runs = sorted(runs, key=lambda r: r["seed"])
    n = len(campaign_runs)
    successes = sum(r["state"] == SUCCEEDED for r in campaign_runs)
    low, high = wilson_interval(successes, n)
    causes = cause_counts(args, campaign_runs)
    worst = sorted(campaign_runs, key=worst_order)[:max(args.keep_worst, 0)]
    failed = [r for r in campaign_runs if r["state"] != SUCCEEDED]
    worst_entries = []
    for rank, run in enumerate(sorted(failed + [r for r in worst if r not in failed],
                                      key=worst_order), 1):
        faults = [f for f in args.faults if f.applies_to(run["seed"])]
        worst_entries.append({"rank": rank, "seed": run["seed"], "state": run["state"],
                              "failed_step": run["failed_step"], "sim_s": run["sim_s"],
                              "faults": run["faults"], "message": run["message"],
                              "run_dir": run["run_dir"], "recording": run["recording"],
                              "new_stack": run.get("new_stack"),
                              "reproduce": reproduce_command(args, run["seed"], faults)})
    return {
        "mission": relative(args.mission), "mission_name": args.mission_name,
        "robot_id": args.robot, "seeds": [r["seed"] for r in campaign_runs],
        "faults": [f.spec() for f in args.faults], "launcher_args": args.launcher_args,
        "build_dir": args.build_dir, "jobs": args.jobs,
        "missions_per_stack": args.missions_per_stack, "wall_s": round(wall_s, 1),
        "runs_done": n, "runs_planned": len(args.seeds), "error": error or "",
        "interrupted": interrupted,
        "success": {"succeeded": successes, "runs": n,
                    "rate": round(successes / n, 4) if n else None,
                    "wilson95": [round(low, 4), round(high, 4)]},
        "step_causes": causes, "step_durations_s": duration_stats(campaign_runs, causes),
        "worst": worst_entries, "determinism": recheck,
        "runs": [public(r) for r in campaign_runs],
    }


def _fmt(value, digits=2):
    return "-" if value is None else f"{value:.{digits}f}"


def new_stack_note(new_stack):
    """What flying a kept run again on a new stack gave, for report.md."""
    if not new_stack:
        return ""
    if new_stack["same"]:
        return " (flown again on a new stack, for its recording: the same result)"
    return (f" (flown again on a new stack: **a different result**: "
            f"{'; '.join(new_stack['differences'])}; that flight: `{new_stack['run_dir']}`)")


def write_markdown(path, data):
    s = data["success"]
    lines = [f"# Campaign: {data['mission_name'] or data['mission']}", "",
             f"- mission `{data['mission']}` on {data['robot_id']}, deterministic mode "
             f"(`--time-scale max`); launcher arguments: "
             f"`{' '.join(data['launcher_args']) or '-'}`",
             f"- {data['runs_done']} of {data['runs_planned']} runs, seeds "
             f"{faultlib.format_seeds(data['seeds']) or '-'}",
             f"- faults: {', '.join(f'`{f}`' for f in data['faults']) or 'none'}",
             f"- {data['wall_s']:.0f} s of wall time, {data['jobs']} stacks at once, "
             + {1: "a new stack for every run",
                0: "a stack reused (Simulator.Reset) while its missions succeed"}.get(
                    data["missions_per_stack"],
                    f"a new stack every {data['missions_per_stack']} missions")]
    if data["error"]:
        lines.append(f"- **the campaign stopped**: {data['error']}")
    if data["interrupted"]:
        lines.append(f"- **interrupted** by {data['interrupted']}")
    lines += ["", "## Success rate", ""]
    if s["runs"]:
        lines.append(f"**{s['succeeded']} of {s['runs']}** succeeded: {s['rate'] * 100:.1f} % "
                     f"(95 % Wilson score interval {s['wilson95'][0] * 100:.1f} - "
                     f"{s['wilson95'][1] * 100:.1f} %).")
    else:
        lines.append("No run finished.")

    all_causes = []
    for row in data["step_causes"]:
        for cause in row["causes"]:
            if cause not in all_causes and cause != NOT_REACHED:
                all_causes.append(cause)
    all_causes.append(NOT_REACHED)
    lines += ["", "## Termination causes per step", "",
              "Every attempt of every step (a retried step counts each attempt).", "",
              "| step | behavior | " + " | ".join(all_causes) + " |",
              "|---|---|" + "---:|" * len(all_causes)]
    for row in data["step_causes"]:
        lines.append(f"| {row['step']} | {row['behavior']} | "
                     + " | ".join(str(row["causes"].get(c, "")) for c in all_causes) + " |")
    lines += ["", "## Step active time (simulated seconds)", "",
              "| step | attempts | min | median | p90 | max |", "|---|---:|---:|---:|---:|---:|"]
    for row in data["step_durations_s"]:
        lines.append(f"| {row['step']} | {row['attempts']} | {_fmt(row.get('min_s'))} | "
                     f"{_fmt(row.get('median_s'))} | {_fmt(row.get('p90_s'))} | "
                     f"{_fmt(row.get('max_s'))} |")

    lines += ["", "## Worst runs", "",
              "Failed runs first, then the longest (simulated time from the first activation "
              "to the end of the last step). A run directory holds `report.md` (trajectory, "
              "timeline), `recordings/flight.mcap` and `logs/`. Each command flies the run "
              "again, from the repository's root.", ""]
    if not data["worst"]:
        lines.append("None.")
    for entry in data["worst"]:
        failed = entry["failed_step"]
        result = entry["state"].replace("MISSION_STATE_", "")
        if failed:
            result += (f" at step `{failed['name']}` ({failed['behavior']}, attempt "
                       f"{failed['attempt']}): **{failed['cause']}**"
                       + (f" - {failed['message']}" if failed["message"] else ""))
        lines += [f"{entry['rank']}. seed **{entry['seed']}**: {result}; "
                  f"{_fmt(entry['sim_s'], 1)} s simulated"
                  + (f"; faults {', '.join(f'`{f}`' for f in entry['faults'])}"
                     if entry["faults"] else "")
                  + (f"; run directory `{entry['run_dir']}`" if entry["run_dir"]
                     else "; run directory not kept (--keep-worst)")
                  + new_stack_note(entry.get("new_stack")), "",
                  "   ```sh", f"   {entry['reproduce']}", "   ```", ""]

    d = data["determinism"]
    if d:
        lines += ["## Determinism check", "",
                  f"Seed {d['seed']} flown again on a new stack: "
                  + ("**the same result**" if d["same"] else "**a different result**")
                  + f" (same causes: {'yes' if d['same_causes'] else 'no'}; step active times "
                  f"differ by at most {_fmt(d['duration_diff_s'], 3)} s, tolerance "
                  f"{d['duration_tolerance_s']} s; flown paths by "
                  f"{_fmt(d['path_deviation_m'], 4)} m, tolerance {d['path_tolerance_m']} m).",
                  ""]
        lines += [f"- {text}" for text in d["differences"]]
        if d.get("run_dir"):
            lines.append(f"- the second run's directory: `{d['run_dir']}`")
        lines.append("")

    lines += ["## Every run", "",
              "| seed | result | failed step: cause | simulated s | wall s | faults injected "
              "at (s) | stack/mission |", "|---:|---|---|---:|---:|---|---|"]
    for run in data["runs"]:
        failed = run["failed_step"]
        injected = ", ".join(
            f"`{i['fault']}` " + ("never" if i["injected_at_s"] is None else
                                  f"{i['injected_at_s']:.2f}"
                                  + (f" (mission {i['mission_s']:.2f})"
                                     if i["fault"][0].isalpha() and i["mission_s"] is not None
                                     else ""))
            + (" (late)" if i["late"] else "") + (f" ({i['error']})" if i["error"] else "")
            for i in run["injected"]) or "-"
        lines.append(f"| {run['seed']} | {run['state'].replace('MISSION_STATE_', '')} | "
                     f"{failed['name'] + ': ' + failed['cause'] if failed else '-'} | "
                     f"{_fmt(run['sim_s'], 2)} | {run['wall_s']:.1f} | {injected} | "
                     f"{run['stack']}/{run['mission_on_stack']} |")
    with open(path, "w") as f:
        f.write("\n".join(lines) + "\n")


# --- main ----------------------------------------------------------------------

def parse_args():
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--build-dir", default="build", help="where the binaries are built")
    parser.add_argument("--mission", default=DEMO_MISSION,
                        help="the mission file (default: deploy/missions/demo.yaml)")
    seeds = parser.add_mutually_exclusive_group()
    seeds.add_argument("--seeds", type=int, default=10, metavar="N",
                       help="fly seeds --first-seed .. --first-seed + N - 1 (default: 10)")
    seeds.add_argument("--seed-list", default="", metavar="LIST",
                       help="fly these seeds: 1,2,7 or 1-20,30")
    parser.add_argument("--first-seed", type=int, default=1, help="see --seeds (default: 1)")
    parser.add_argument("--fault", action="append", default=[],
                        metavar="[STEP+]T:KIND[:ARGS][@seeds=L]",
                        help="inject a fault T simulated seconds after the mission's first "
                             "activation, or after step STEP's, in every run or only for the "
                             "seeds listed (repeatable; see above)")
    parser.add_argument("--fault-schedule", default="", metavar="FILE",
                        help="faults from a YAML or JSON file (see above)")
    parser.add_argument("--jobs", type=int, default=os.cpu_count() or 1,
                        help="stacks flying at once (default: the number of cores, %(default)s)")
    parser.add_argument("--missions-per-stack", type=int, default=1, metavar="N",
                        help="fly up to N missions on a stack, with Simulator.Reset between "
                             "them (0: no limit; a stack is replaced after a mission that did "
                             "not succeed); default 1: a new stack for every run (see above)")
    parser.add_argument("--out", default="",
                        help="directory for the report and the kept runs (default: a new "
                             "directory under /tmp)")
    parser.add_argument("--keep-worst", type=int, default=3, metavar="K",
                        help="keep the run directories of the K worst runs (default: 3)")
    parser.add_argument("--check-determinism", nargs="?", const=-1, type=int, default=None,
                        metavar="SEED",
                        help="fly SEED (default: the first seed) once more on a new stack "
                             "after the campaign, and check that both runs give the same result")
    parser.add_argument("--duration-tolerance-s", type=float,
                        default=determinism.DURATION_TOLERANCE_S,
                        help="--check-determinism: step active times may differ by this "
                             "(default: %(default)s s)")
    parser.add_argument("--path-tolerance-m", type=float, default=determinism.PATH_TOLERANCE_M,
                        help="--check-determinism: flown paths may differ by this "
                             "(default: %(default)s m)")
    parser.add_argument("--min-success-rate", type=float, default=None, metavar="X",
                        help="exit 1 when fewer than X (0..1) of the runs succeed")
    parser.add_argument("--mission-timeout-s", type=float, default=120.0,
                        help="wall seconds after which a mission is aborted (default: "
                             "%(default)s)")
    parser.add_argument("--no-record", dest="record", action="store_false",
                        help="no flight recording (recordings/flight.mcap) per run")
    parser.add_argument("launcher_args", nargs="*", metavar="-- LAUNCHER_ARG",
                        help="extra launch.py arguments after --, e.g. -- --systems "
                             "quadrotor_motion_with_pid_control")
    args = parser.parse_args()

    if args.seed_list:
        try:
            args.seeds = sorted(faultlib.parse_seeds(args.seed_list))
        except faultlib.FaultError as error:
            parser.error(f"--seed-list: {error}")
    else:
        if args.seeds < 1 or args.first_seed < 1:
            parser.error("--seeds and --first-seed must be at least 1")
        args.seeds = list(range(args.first_seed, args.first_seed + args.seeds))
    try:
        args.faults = [faultlib.Fault.parse(text) for text in args.fault]
        if args.fault_schedule:
            args.faults += faultlib.load_schedule(args.fault_schedule)
    except faultlib.FaultError as error:
        parser.error(str(error))
    if args.jobs < 1:
        parser.error("--jobs must be at least 1")
    if args.keep_worst < 0 or args.missions_per_stack < 0:
        parser.error("--keep-worst and --missions-per-stack must not be negative")
    if args.min_success_rate is not None and not 0 <= args.min_success_rate <= 1:
        parser.error("--min-success-rate must be within [0, 1]")
    if args.check_determinism == -1:
        args.check_determinism = args.seeds[0]
    if args.check_determinism is not None and args.check_determinism not in args.seeds:
        parser.error(f"--check-determinism: seed {args.check_determinism} is not one of the "
                     f"campaign's seeds")
    for arg in args.launcher_args:
        if arg.split("=", 1)[0] in OWN_LAUNCHER_OPTIONS:
            parser.error(f"launcher argument {arg}: the campaign sets it itself, or cannot "
                         f"follow it")
    if not os.path.isfile(args.mission):
        parser.error(f"--mission: {args.mission} is not a file")
    args.mission = os.path.abspath(args.mission)
    args.build_dir = os.path.abspath(args.build_dir)
    try:
        args.mission_name, robot, args.outline, args.recurrent = mission_outline(args.mission)
    except Exception as error:  # noqa: BLE001 - any YAML problem
        parser.error(f"--mission {args.mission}: {error}")
    args.robot = robot or "drone1"
    step_names = [name for name, _ in args.outline]
    for fault in args.faults:
        if fault.step is not None and fault.step not in step_names:
            parser.error(f"fault {fault.spec()}: the mission has no step {fault.step} (its "
                         f"steps: {', '.join(step_names)})")
    world = argparse.ArgumentParser(add_help=False)
    world.add_argument("--world", default="")
    args.world = world.parse_known_args(args.launcher_args)[0].world
    args.stamp = f"{time.strftime('%Y%m%d-%H%M%S')}-{os.getpid()}"
    return args


def main():
    args = parse_args()
    args.out = (os.path.abspath(args.out) if args.out
                else tempfile.mkdtemp(prefix="behaviorlib-campaign-"))
    runs_dir = os.path.join(args.out, "runs")
    os.makedirs(runs_dir, exist_ok=True)
    items = [{"seed": seed, "faults": [f for f in args.faults if f.applies_to(seed)],
              "run_dir": os.path.join(runs_dir, f"seed-{seed}")} for seed in args.seeds]
    if args.check_determinism is not None:
        seed = args.check_determinism
        items.append({"seed": seed, "faults": [f for f in args.faults if f.applies_to(seed)],
                      "run_dir": os.path.join(runs_dir, f"seed-{seed}-again"),
                      "label": "determinism check", "fresh": True})
    for signum in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(signum, _on_signal)

    stacks = min(args.jobs, len(items))
    say(f"campaign: {relative(args.mission)}, {len(args.seeds)} seed"
        f"{'s' * (len(args.seeds) != 1)}, {len(args.faults)} fault"
        f"{'s' * (len(args.faults) != 1)}, {stacks} stack{'s' * (stacks != 1)} at once; "
        f"report in {args.out}")
    started = time.monotonic()
    campaign = Campaign(args, items)
    interrupted = ""
    status = 0
    confirmations = []
    try:
        campaign.run()
        confirmations = confirm_kept_runs(args, campaign)
    except Interrupted as signal_received:
        interrupted = str(signal_received)
        say(f"\n{interrupted}: stopping")
        status = 128 + signal_received.signum
    finally:
        for signum in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
            signal.signal(signum, signal.SIG_IGN)
    wall_s = time.monotonic() - started

    runs = [r for r in campaign.runs if not r["label"]]
    recheck = None
    again = next((r for r in campaign.runs if r["label"]), None)
    if again is not None:
        first = next((r for r in runs if r["seed"] == again["seed"]), None)
        recheck = {"seed": again["seed"], "same": False, "same_causes": False,
                   "duration_diff_s": None, "path_deviation_m": None, "runs": [],
                   "differences": ["the seed has no campaign run to compare with"],
                   "run_dir": again["run_dir"]}
        if first is not None:
            result = determinism.compare(comparable(first), comparable(again),
                                         args.duration_tolerance_s, args.path_tolerance_m)
            recheck.update(result, runs=[public(r) for r in (first, again)],
                           run_dir=again["run_dir"] if not result["same"] else "")
            if result["same"]:
                shutil.rmtree(again["run_dir"], ignore_errors=True)
                again.pop("_raw", None)
        recheck.update(duration_tolerance_s=args.duration_tolerance_s,
                       path_tolerance_m=args.path_tolerance_m)
    for run in campaign.runs + confirmations:
        if run.get("run_dir") and os.path.isdir(run["run_dir"]):
            write_run_report(args, run)
    data = build_report(args, runs, recheck, wall_s, campaign.error, interrupted)
    with open(os.path.join(args.out, "report.json"), "w") as f:
        json.dump(data, f, indent=2)
        f.write("\n")
    write_markdown(os.path.join(args.out, "report.md"), data)
    if campaign.failed_stacks:
        say("stacks that did not start (their directories are kept): "
            + ", ".join(campaign.failed_stacks))
    else:
        shutil.rmtree(os.path.join(args.out, "stacks"), ignore_errors=True)
    # What a run stopped half-way (a signal, a tooling failure) left.
    named = {r.get("run_dir") for r in campaign.runs + confirmations}
    named.add((recheck or {}).get("run_dir"))
    for name in os.listdir(runs_dir):
        if os.path.join(runs_dir, name) not in named:
            shutil.rmtree(os.path.join(runs_dir, name), ignore_errors=True)

    s = data["success"]
    say("")
    if s["runs"]:
        say(f"{s['succeeded']} of {s['runs']} runs succeeded ({s['rate'] * 100:.1f} %, 95 % "
            f"interval {s['wilson95'][0] * 100:.1f}-{s['wilson95'][1] * 100:.1f} %) in "
            f"{wall_s:.0f} s")
    for entry in data["worst"]:
        if entry["state"] != SUCCEEDED:
            failed = entry["failed_step"] or {}
            say(f"  failed: seed {entry['seed']} at {failed.get('name', '?')}: "
                f"{failed.get('cause', '?')}; again: {entry['reproduce']}")
    if recheck is not None:
        say(f"determinism (seed {recheck['seed']} twice): "
            + ("the same result" if recheck["same"] else "DIFFERENT: "
               + "; ".join(recheck["differences"])))
    say(f"report: {os.path.join(args.out, 'report.md')} (also report.json)")
    if status:
        return status
    if campaign.error:
        print(f"campaign.py: {campaign.error}", file=sys.stderr, flush=True)
        return EXIT_TOOLING
    if (args.min_success_rate is not None and s["runs"]
            and s["rate"] < args.min_success_rate):
        say(f"success rate below --min-success-rate {args.min_success_rate}")
        return EXIT_CHECK_FAILED
    if recheck is not None and not recheck["same"]:
        return EXIT_CHECK_FAILED
    return 0


if __name__ == "__main__":
    sys.exit(main())
