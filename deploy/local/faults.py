"""Faults injected into the simulator at given simulated times of a mission
(Simulator.InjectFailure; the simulator needs --enable-fault-injection).

A fault is written [STEP+]T:KIND[:ARGS][@seeds=LIST]:
    T       simulated seconds after the mission's first activation (t = 0 of
            the report's timeline), e.g. 12.5; with STEP+, after the first
            attempt of the mission step STEP was activated, e.g.
            fly_square+4.5. The coordinator is not in the deterministic
            mode's barrier, so when a step starts after the mission's first
            activation varies from run to run (by up to 3 s on a loaded
            machine): a fault timed from its step hits the same moment of the
            step's flight in every run
    KIND    COMPONENT_TYPE, the proto's FailureComponent and FailureType in
            lower case: motor_off, motor_degraded, gps_stuck, imu_garbage,
            baro_noisy, battery_degraded, lidar_intermittent, wind_set, gps_ok
            (clears a fault), ... (KINDS lists every pair)
    ARGS    comma-separated key=value: robot=ID (default: the mission's),
            motor=0..3, intensity=0..1, delay=S (DELAYED), wind_x=, wind_y=,
            wind_z= (m/s), gust=S (m/s; wind_set)
    @seeds= only for these seeds: 3 or 3,7 or 1-10,15 (default: every seed)

    12:motor_off:motor=0            motor 0 stops 12 s into the mission
    fly_square+4.5:motor_off:motor=0@seeds=3
    5:wind_set:wind_x=6,gust=2@seeds=1-5

A schedule file (YAML or JSON) lists the same, as strings or as mappings:
    faults:
      - "12:motor_off:motor=0@seeds=3"
      - {at_s: 5, kind: wind_set, wind_x: 6, gust: 2, seeds: [1, 2]}
      - {step: fly_square, at_s: 4.5, kind: gps_stuck}

FaultInjector injects them during one mission, each at the simulator's first
time quantum (10 ms) at or after its time, so that the same seed and the same
schedule give the same run: in the deterministic mode (--time-scale max) it
follows the time grants (Simulator.FollowTime) as one more follower, which
the simulator waits for, and it injects while the simulator waits for it.
"""

import queue
import re
import threading

from google.protobuf import timestamp_pb2

SIMULATOR = "behaviorlib.v1.Simulator"
# The deterministic mode's time quantum (the simulator's --quantum-ms default).
QUANTUM_S = 0.01

SENSORS = ("gps", "imu", "baro", "lidar", "camera", "linear_speed", "battery")
SENSOR_TYPES = ("ok", "off", "stuck", "noisy", "garbage", "intermittent", "delayed")
# Every KIND (component_type) the simulator accepts.
KINDS = tuple([f"{s}_{t}" for s in SENSORS for t in SENSOR_TYPES]
              + ["battery_degraded", "motor_ok", "motor_off", "motor_degraded", "wind_set",
                 "wind_ok"])
ARG_KEYS = ("robot", "motor", "intensity", "delay", "wind_x", "wind_y", "wind_z", "gust")
# Types that need intensity > 0, and the delay.
NEEDS_INTENSITY = ("noisy", "intermittent", "degraded")


class FaultError(ValueError):
    """A fault or schedule that cannot be used (the message says why)."""


def parse_seeds(text):
    """'3', '3,7', '1-10,15' -> a frozenset of seeds (each >= 1)."""
    seeds = set()
    for part in str(text).split(","):
        part = part.strip()
        match = re.fullmatch(r"(\d+)(?:-(\d+))?", part)
        if not match:
            raise FaultError(f"'{text}' is not a seed list (e.g. 3 or 3,7 or 1-10,15)")
        first, last = int(match.group(1)), int(match.group(2) or match.group(1))
        if first < 1 or last < first:
            raise FaultError(f"'{part}' is not a range of seeds >= 1")
        seeds.update(range(first, last + 1))
    return frozenset(seeds)


def format_seeds(seeds):
    """The shortest LIST for a set of seeds (ranges joined with '-')."""
    ordered, parts = sorted(seeds), []
    i = 0
    while i < len(ordered):
        j = i
        while j + 1 < len(ordered) and ordered[j + 1] == ordered[j] + 1:
            j += 1
        parts.append(str(ordered[i]) if i == j else f"{ordered[i]}-{ordered[j]}")
        i = j + 1
    return ",".join(parts)


class Fault:
    """One fault of a schedule."""

    def __init__(self, at_s, kind, args=None, seeds=None, step=None):
        self.step = step or None  # None: from the mission's first activation
        if self.step is not None and not re.fullmatch(r"[^:@+]+", self.step):
            raise FaultError(f"'{step}' is not a step name (no ':', '@' or '+')")
        self.at_s = float(at_s)
        if not 0 <= self.at_s < 1e6:
            raise FaultError(f"fault time {at_s} is not within [0, 1e6) s")
        self.kind = str(kind).strip().lower()
        if self.kind not in KINDS:
            raise FaultError(f"no fault kind '{kind}': COMPONENT_TYPE, a sensor ("
                             f"{', '.join(SENSORS)}) with {', '.join(SENSOR_TYPES)}, or "
                             f"battery_degraded, motor_ok, motor_off, motor_degraded, wind_set, "
                             f"wind_ok")
        self.component, self.type = self.kind.rsplit("_", 1)
        self.args = {}
        for key, value in (args or {}).items():
            if key not in ARG_KEYS:
                raise FaultError(f"{self.kind}: no argument '{key}' (arguments: "
                                 f"{', '.join(ARG_KEYS)})")
            if key == "robot":
                if not re.fullmatch(r"[A-Za-z0-9_-]+", str(value)):
                    raise FaultError(f"{self.kind}: robot '{value}' is not a robot id")
                self.args[key] = str(value)
                continue
            try:
                self.args[key] = int(value) if key == "motor" else float(value)
            except (TypeError, ValueError):
                raise FaultError(f"{self.kind}: {key}={value} is not a number") from None
        if self.component == "motor" and not 0 <= self.args.get("motor", 0) <= 3:
            raise FaultError(f"{self.kind}: motor={self.args['motor']} is not within 0..3")
        if self.type in NEEDS_INTENSITY and not 0 < self.args.get("intensity", 0) <= 1:
            raise FaultError(f"{self.kind} needs intensity within (0, 1], e.g. "
                             f"{self.kind}:intensity=0.5")
        if self.type == "delayed" and not 0 < self.args.get("delay", 0) <= 10:
            raise FaultError(f"{self.kind} needs delay within (0, 10] s, e.g. "
                             f"{self.kind}:delay=0.2")
        self.seeds = frozenset(seeds) if seeds is not None else None

    @classmethod
    def parse(cls, text):
        """[STEP+]T:KIND[:ARGS][@seeds=LIST] (see the module's doc)."""
        spec, _, selector = str(text).strip().partition("@")
        seeds = None
        if selector:
            key, sep, value = selector.partition("=")
            if key.strip() != "seeds" or not sep:
                raise FaultError(f"fault '{text}': after '@' comes seeds=LIST")
            seeds = parse_seeds(value)
        parts = spec.split(":", 2)
        if len(parts) < 2:
            raise FaultError(f"fault '{text}' is not T:KIND[:ARGS][@seeds=LIST], e.g. "
                             f"12:motor_off:motor=0")
        step, plus, when = parts[0].rpartition("+")
        try:
            at_s = float(when)
        except ValueError:
            raise FaultError(f"fault '{text}': '{parts[0]}' is not [STEP+]T, a time in "
                             f"seconds") from None
        args = {}
        for item in (parts[2].split(",") if len(parts) == 3 and parts[2] else []):
            key, sep, value = item.partition("=")
            if not sep:
                raise FaultError(f"fault '{text}': argument '{item}' is not key=value")
            args[key.strip()] = value.strip()
        if plus and not step:
            raise FaultError(f"fault '{text}': '+' comes after a step name")
        return cls(at_s, parts[1], args, seeds, step)

    @classmethod
    def from_mapping(cls, item):
        """{at_s, kind, step?, seeds?, ARGS...} from a schedule file."""
        item = dict(item)
        if "at_s" not in item or "kind" not in item:
            raise FaultError(f"schedule entry {item}: needs at_s and kind")
        at_s, kind, seeds = item.pop("at_s"), item.pop("kind"), item.pop("seeds", None)
        step = item.pop("step", None)
        if isinstance(seeds, int):
            seeds = [seeds]
        if seeds is not None:
            seeds = (parse_seeds(",".join(str(s) for s in seeds)) if isinstance(seeds, list)
                     else parse_seeds(seeds))
        return cls(at_s, kind, item, seeds, None if step is None else str(step))

    def applies_to(self, seed):
        return self.seeds is None or seed in self.seeds

    def spec(self, with_seeds=True):
        """The fault as [STEP+]T:KIND[:ARGS][@seeds=LIST] (parse gives it
        back)."""
        text = (f"{self.step}+" if self.step else "") + f"{_number(self.at_s)}:{self.kind}"
        if self.args:
            text += ":" + ",".join(f"{k}={v}" if k == "robot" else f"{k}={_number(v)}"
                                   for k, v in self.args.items())
        if with_seeds and self.seeds is not None:
            text += "@seeds=" + format_seeds(self.seeds)
        return text

    def request(self, robot_id):
        """Its InjectFailureRequest (proto JSON)."""
        request = {"robot_id": self.args.get("robot", robot_id),
                   "component": "FAILURE_COMPONENT_" + self.component.upper(),
                   "type": "FAILURE_TYPE_" + self.type.upper()}
        if "motor" in self.args:
            request["motor_index"] = self.args["motor"]
        if "intensity" in self.args:
            request["intensity"] = self.args["intensity"]
        if "delay" in self.args:
            request["delay"] = f"{self.args['delay']:.9f}s"
        wind = {axis: self.args[f"wind_{axis}"] for axis in "xyz" if f"wind_{axis}" in self.args}
        if wind:
            request["wind_velocity_m_s"] = wind
        if "gust" in self.args:
            request["gust_stddev_m_s"] = self.args["gust"]
        return request


def load_schedule(path):
    """The faults of a schedule file (YAML or JSON; see the module's doc)."""
    try:
        import yaml  # Debian's python3-yaml; JSON is YAML too
        with open(path, encoding="utf-8") as f:
            data = yaml.safe_load(f)
    except (OSError, ImportError) as error:
        raise FaultError(f"cannot read the fault schedule {path}: {error}") from None
    except yaml.YAMLError as error:
        raise FaultError(f"fault schedule {path}: {error}") from None
    entries = data.get("faults") if isinstance(data, dict) else data
    if not isinstance(entries, list):
        raise FaultError(f"fault schedule {path}: expected a list of faults (or faults: [...])")
    faults = []
    for entry in entries:
        try:
            faults.append(Fault.parse(entry) if isinstance(entry, str)
                          else Fault.from_mapping(entry) if isinstance(entry, dict)
                          else None)
        except FaultError as error:
            raise FaultError(f"fault schedule {path}: {error}") from None
        if faults[-1] is None:
            raise FaultError(f"fault schedule {path}: entry {entry!r} is neither a string nor "
                             f"a mapping")
    return faults


def _number(value):
    """A number as a fault's text writes it: no exponent, no rounding to a
    few digits (3, 4.5, 0.125)."""
    if isinstance(value, int):
        return str(value)
    return f"{value:.9f}".rstrip("0").rstrip(".")


def _timestamp_json(ns):
    t = timestamp_pb2.Timestamp()
    t.FromNanoseconds(int(ns))
    return t.ToJsonString()


class FaultInjector:
    """Injects `faults` into one mission on `simulator` (an rpc.Client of
    the Simulator service) as the deterministic mode's time goes by. Their
    times count from anchors given with set_anchor: None, the simulated time
    of the mission's first activation, and each step's name, the time its
    first attempt was activated. start() before the mission, stop() after
    it; `results` then says, per fault, when it was injected.

    It follows the time grants as a busy follower until its last fault is
    in: the simulator waits for its report of every quantum, so however
    slowly this process runs, simulated time cannot pass a fault whose
    anchor it knows. An anchor it learns only after its fault's time (the
    coordinator's events arrive late) makes that fault late: its result
    says so, and the run does not follow the schedule."""

    PARTICIPANT = "campaign/faults"

    def __init__(self, simulator, robot_id, faults):
        self._simulator = simulator
        self._robot_id = robot_id
        self._pending = list(faults)
        self._lock = threading.Lock()
        self._requests = queue.SimpleQueue()
        self._anchors = {}  # None (the mission) or a step name -> simulated s
        self._call = None
        self._thread = threading.Thread(target=self._run, name="fault-injector", daemon=True)
        self.error = None
        # One per fault, in the order injected: fault (its spec), step (its
        # anchor, None for the mission's start), at_s, injected_at_s (from
        # its anchor) or None when never injected,
        # mission_s (from the mission's first activation), late (more than a
        # quantum after its time), error.
        self.results = []

    def start(self):
        self._thread.start()

    def anchors(self):
        with self._lock:
            return dict(self._anchors)

    def _target_s(self, fault):
        anchor = self._anchors.get(fault.step)
        return None if anchor is None else anchor + fault.at_s

    def set_anchor(self, step, t_s):
        """The mission's first activation (step None), or the first attempt
        of `step`, happened at simulated time t_s."""
        with self._lock:
            self._anchors.setdefault(step, t_s)

    def _requests_iter(self):
        while True:
            item = self._requests.get()
            if item is None:
                return
            yield item

    def _run(self):
        # Joins busy (caught up to time 0): the simulator waits for it from
        # its first grant on.
        self._requests.put({"participant": self.PARTICIPANT, "caught_up_to": _timestamp_json(0),
                            "idle": False})
        try:
            self._call = self._simulator.bidi(SIMULATOR, "FollowTime", self._requests_iter())
            for grant in self._call:
                t = grant.clock.time
                ns = t.seconds * 1_000_000_000 + t.nanos
                if not self._on_grant(ns * 1e-9, ns):
                    break
        except Exception as error:  # noqa: BLE001 - reported with the run
            code = getattr(error, "code", None)
            if not (callable(code) and code().name == "CANCELLED"):
                self.error = (f"{code().name}: {error.details()}" if callable(code)
                              else f"{type(error).__name__}: {error}")
        finally:
            self._requests.put(None)

    def _result(self, fault, grant_s=None, error=""):
        anchor = self._anchors.get(fault.step)
        mission = self._anchors.get(None)
        return {"fault": fault.spec(with_seeds=False), "step": fault.step, "at_s": fault.at_s,
                "injected_at_s": None if grant_s is None else round(grant_s - anchor, 6),
                "mission_s": (None if grant_s is None or mission is None
                              else round(grant_s - mission, 6)),
                "late": grant_s is not None and grant_s - anchor - fault.at_s > QUANTUM_S + 1e-6,
                "error": error}

    def _on_grant(self, grant_s, grant_ns):
        """Injects what is due at this grant, then reports it; False once
        nothing is left to inject (the stream then ends)."""
        with self._lock:
            due = [f for f in self._pending
                   if self._target_s(f) is not None and self._target_s(f) <= grant_s + 1e-9]
            due.sort(key=self._target_s)
            self._pending = [f for f in self._pending if f not in due]
        for fault in due:
            error = ""
            try:
                self._simulator.call(SIMULATOR, "InjectFailure", fault.request(self._robot_id))
            except Exception as failure:  # noqa: BLE001 - an rpc.grpc.RpcError
                code = getattr(failure, "code", None)
                error = f"{code().name}: {failure.details()}" if callable(code) else str(failure)
            with self._lock:
                self.results.append(self._result(fault, grant_s, error))
        with self._lock:
            if not self._pending:
                return False
        self._requests.put({"caught_up_to": _timestamp_json(grant_ns)})
        return True

    def stop(self):
        """Leaves the time grants; a fault not injected by now is listed
        with injected_at_s None (the mission ended before its time, or its
        step was never activated)."""
        self._requests.put(None)
        if self._call is not None:
            self._call.cancel()
        self._thread.join(timeout=5)
        with self._lock:
            for fault in self._pending:
                why = (self.error or ("its step was never activated"
                                      if fault.step not in self._anchors
                                      else "the mission ended before its time"))
                self.results.append(self._result(fault, None, why))
            self._pending = []
            return list(self.results)
