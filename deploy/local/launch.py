#!/usr/bin/python3
"""Starts the behaviorlib stack on this machine, without Docker.

Starts on loopback, with ports chosen free at run time, each one health
checked before the next: the data channel broker, the simulator, the
coordinator and every behavior system that is built. Writes one log file per
process, the ports, the pids and Prometheus file-based service discovery
targets into a run directory. Then either serves until Ctrl-C, or (--demo)
flies the demo mission (or the --mission files) through the coordinator,
prints its progress, and writes a mission report (report.md, report.json,
trajectory.png, timeline.png). Stops every process in reverse order (SIGTERM,
then SIGKILL after a time-out) on exit and on Ctrl-C.

Meanwhile it supervises the processes as compose's `restart:` does. With
--restart on-failure (the default) a process that crashes (a non-zero exit
code, or killed by a signal) is started again with the same arguments, on
the same ports (the others dial them; a behavior system registers again with
the coordinator), after 0.5 s doubling up to 5 s; its log goes on in the same
file and pids.json names its new pid. After 5 restarts of a process within
60 s the launcher gives up and stops the stack (--demo: once the missions
have ended). A process that exits with code 0 stays stopped. With --restart
no, a process that exits stops the stack (while serving).

    deploy/local/launch.py --build-dir build --demo
    deploy/local/launch.py --build-dir build          # serve until Ctrl-C

Behavior systems written in Python (behaviorlib.system.run_system, decision
47) start beside the C++ ones, per robot and with the same flags, from their
scripts: --python-systems examples/python_behavior/system.py. They run on
the interpreter that $BEHAVIORLIB_PYTHON names (default
<build-dir>/venv/bin/python, which the build installs the behaviorlib
package into); each process is named after its script (without .py), and
the system name it registers is asked of the process once it serves
(BehaviorSystem.ListBehaviors), so the launcher waits for the name the
script chose. They serve no TLS yet: --tls refuses them.

The paper's applications:

    # aircraft inspection: QR markers found, with their positions, in the report
    deploy/local/launch.py --demo --world aircraft \
        --sensor-config deploy/config/simulator_sensors_aircraft.yaml \
        --mission deploy/missions/aircraft_inspection.yaml
    # two vehicles sharing their positions: every behavior system once per
    # robot (process names suffixed with the robot), one fleet mission for both
    deploy/local/launch.py --demo --vehicles drone1,drone2 \
        --mission drone1=deploy/missions/swarm_two_vehicles.yaml
    # room exploration: the saved map's coverage of the building in the report
    deploy/local/launch.py --demo --world rooms --mission deploy/missions/room_exploration_slam.yaml

Before the missions start, belief {robot}/output_dir names the directory
where a mission may write its files (e.g. SAVE_OCCUPANCY_GRID's map):
<run-dir>/output, or <run-dir>/output/<robot> with several robots. It is the
behavior systems' --map-dir, the only place where they write. After the missions,
the report lists what the behaviors left in the coordinator's belief memory
for each robot: the QR markers found ({robot}/markers/...), the other
robots' positions ({robot}/swarm/...), and the map saved by
SAVE_OCCUPANCY_GRID ({robot}/map_file) with, when a world was given and
build/bin/map_coverage is built, the fraction of the world's
free space it covers.

Every behavior system started costs CPU even idle (on a two-core machine
the whole one-robot stack took about 1.4 cores at 3x, and two robots 1.1
cores at 1x): hence the 2x default; with a camera decoded, or with several
robots, start only the systems the missions need with --systems (the
applications' tests do, at 2-3x).

Run directory (--run-dir; default a new directory under /tmp):
    logs/<process>.log         what each process printed
    ports/<process>.ports      its bound ports (grpc_port=, metrics_port=)
    pids.json                  the pid of each process started
    prometheus_targets.json    file_sd targets, one per /metrics port, labelled
                               job (channel_broker, simulator, coordinator,
                               behavior_system), system (process name), robot;
                               scrape with honor_labels: true so that a
                               metric's own system/robot labels win
    coordinator/               the coordinator's --state-dir
    report.md, report.json, trajectory.png, timeline.png   (--demo)

Exit code 0 when every process started and stopped cleanly and, with --demo,
every mission SUCCEEDED; 128 + the signal's number when stopped by a signal.

Needs Debian's python3-grpcio, python3-protobuf and python3-yaml; calls the
servers through gRPC reflection (no generated code).
"""

import argparse
import hashlib
import json
import math
import os
import re
import secrets
import signal
import subprocess
import sys
import tempfile
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import demo  # noqa: E402
import report  # noqa: E402
import rpc  # noqa: E402
import screenshot  # noqa: E402
from stack import (HttpProcess, Process, RestartPolicy, Stack, StartError,  # noqa: E402
                   Supervisor, popen_with_launcher)

REPO = os.path.abspath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", ".."))
# The coordinator's catalog and the simulator's sensor configurations; each
# behavior system's configuration is in its own folder (SYSTEMS_DIR).
CONFIG_DIR = os.path.join(REPO, "deploy", "config")
SYSTEMS_DIR = os.path.join(REPO, "services", "systems")
WORLDS_DIR = os.path.join(REPO, "simulator", "worlds")
DEMO_MISSION = os.path.join(REPO, "deploy", "missions", "demo.yaml")
# Measures how much of a world's free space a saved map covers
# (simulator/tools).
MAP_COVERAGE = "bin/map_coverage"

# The behavior systems, started in this order when their binary is built
# (bin/<name>), each with services/systems/<name>/config.yaml when present.
BEHAVIOR_SYSTEMS = [
    "basic_quadrotor_behaviors",
    "quadrotor_motion_with_pid_control",
    "quadrotor_motion_with_mpc_control",
    "quadrotor_motion_with_platform_control",
    "multi_sensor_fusion",
    "navigation_with_lidar",
    "attention_to_visual_markers",
    "swarm_interaction",
    "operator_interaction",
]
REQUIRED_SYSTEMS = ["basic_quadrotor_behaviors"]
# The stack's other processes (their logs and port files are named so).
STACK_PROCESSES = ["channel_broker", "simulator", "coordinator", "console", "recorder"]
# The interpreter of the Python behavior systems (--python-systems): this
# variable, else the build's virtual environment, which has the behaviorlib
# package.
PYTHON_ENV = "BEHAVIORLIB_PYTHON"
BEHAVIOR_SYSTEM_SERVICE = "behaviorlib.v1.BehaviorSystem"


class Interrupted(Exception):
    """SIGINT, SIGTERM or SIGHUP reached the launcher."""

    def __init__(self, signum):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


# The coordinator's --grace-period-s in the deterministic mode (its default
# is 1 s): supervision is in wall time, and this mode is meant for loaded
# machines (tests run beside each other and a CPU hog).
DETERMINISTIC_GRACE_S = 5.0

def _on_signal(signum, _frame):
    raise Interrupted(signum)


def say(text=""):
    print(text, flush=True)


def binary(build_dir, relative, required=True):
    path = os.path.join(build_dir, relative)
    if os.access(path, os.X_OK):
        return path
    if required:
        raise StartError(f"{path} not found; build first (scripts/build.sh, or cmake --build "
                         f"{build_dir})")
    return None


def world_file(world):
    """The YAML file of --world (a path, or the name of a shipped world, as
    the simulator resolves it); "" for the default empty field."""
    if not world:
        return ""
    is_name = "/" not in world and not world.endswith(".yaml")
    return os.path.join(WORLDS_DIR, world + ".yaml") if is_name else os.path.abspath(world)


def world_markers(path):
    """Marker text -> centre [x, y, z] of a world file (to compare the
    markers found with); {} when it has none or cannot be read."""
    if not path:
        return {}
    try:
        import yaml  # Debian's python3-yaml
        with open(path) as f:
            world = yaml.safe_load(f) or {}
        return {m["text"]: [float(v) for v in m["center_m"]]
                for m in world.get("markers") or [] if "text" in m and "center_m" in m}
    except (ImportError, OSError, ValueError, TypeError, KeyError, AttributeError) as error:
        say(f"  note: cannot read the markers of {path}: {error}")
        return {}


def world_walls(path):
    """The walls of a world file as plan-view segments ((x0, y0), (x1, y1)),
    their doors left out (for the report's plot); [] when it has none or
    cannot be read."""
    if not path:
        return []
    try:
        import yaml  # Debian's python3-yaml
        with open(path) as f:
            world = yaml.safe_load(f) or {}
        segments = []
        for wall in world.get("walls") or []:
            (x0, y0), (x1, y1) = [float(v) for v in wall["from_m"]], [float(v) for v in wall["to_m"]]
            length = math.hypot(x1 - x0, y1 - y0)
            if length <= 0:
                continue
            # Along the wall, the spans between its doors.
            gaps = sorted((float(d["offset_m"]) - float(d["width_m"]) / 2,
                           float(d["offset_m"]) + float(d["width_m"]) / 2)
                          for d in wall.get("doors") or [])
            start = 0.0
            for lo, hi in gaps + [(length, length)]:
                if lo > start:
                    a, b = start / length, lo / length
                    segments.append(((x0 + (x1 - x0) * a, y0 + (y1 - y0) * a),
                                     (x0 + (x1 - x0) * b, y0 + (y1 - y0) * b)))
                start = max(start, hi)
        return segments
    except (ImportError, OSError, ValueError, TypeError, KeyError, AttributeError) as error:
        say(f"  note: cannot read the walls of {path}: {error}")
        return []


def simulator_vehicles(simulator, timeout_s=3.0):
    """The robot ids the simulator says it flies (its log's "vehicles [...]"
    line), or None when it has not said so yet."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            with open(simulator.log_path, errors="replace") as f:
                match = re.search(r"vehicles \[([^\]]*)\]", f.read())
            if match:
                return [v for v in match.group(1).split(",") if v]
        except OSError:
            pass
        if time.monotonic() > deadline:
            return None
        time.sleep(0.05)


def system_binaries(args, build_dir):
    """The behavior systems to start: [(name, binary)]."""
    found = []
    for name in BEHAVIOR_SYSTEMS:
        if args.systems and name not in args.systems and name not in REQUIRED_SYSTEMS:
            continue
        path = binary(build_dir, f"bin/{name}",
                      required=name in REQUIRED_SYSTEMS or name in args.systems)
        if path is None:
            say(f"  note: {name} is not built ({build_dir}/bin/{name}); "
                f"its behaviors are unavailable")
            continue
        found.append((name, path))
    return found


def python_interpreter(build_dir):
    """The interpreter of the Python behavior systems ($BEHAVIORLIB_PYTHON,
    else <build-dir>/venv/bin/python)."""
    path = os.environ.get(PYTHON_ENV) or os.path.join(build_dir, "venv", "bin", "python")
    if not os.access(path, os.X_OK):
        raise StartError(f"{path} not found: the Python behavior systems need an interpreter "
                         f"with the behaviorlib package (the build's venv, or ${PYTHON_ENV})")
    return path


def python_system_name(process):
    """The system name a Python behavior system registers, as it says it
    (ListBehaviors' `system`): run_system's `system` argument, which need
    not be its script's name."""
    client = rpc.Client(process.address, [BEHAVIOR_SYSTEM_SERVICE])
    try:
        reply = client.call(BEHAVIOR_SYSTEM_SERVICE, "ListBehaviors", {"page_size": 1})
    finally:
        client.close()
    if not reply.get("system"):
        raise StartError(f"{process.name} does not say which system it is (ListBehaviors)")
    return reply["system"]


def output_root(run_dir):
    """Where behaviors may write files (maps): --map-dir of the systems.
    Apart from the coordinator's journal, which it must not reach."""
    return os.path.join(run_dir, "output")


def recordings_dir(run_dir):
    """Where the flight recorder writes (--record), which the console may
    open (--recordings-dir): nothing else of the run is in it."""
    return os.path.join(run_dir, "recordings")


def make_certs(run_dir, names, systems):
    """--tls: a CA and a certificate per process (scripts/make-dev-certs.sh)
    in <run-dir>/certs, and the access policy that gives each its roles
    (certs/policy.yaml; deploy/config/access_policy.yaml is the compose
    deployment's); this launcher's own clients use "operator". `systems`
    maps a system process's name to (robot, system)."""
    certs = os.path.join(run_dir, "certs")
    result = subprocess.run([os.path.join(REPO, "scripts", "make-dev-certs.sh"), "--out", certs,
                             "operator", *names], capture_output=True, text=True)
    if result.returncode != 0:
        raise StartError(f"cannot make the TLS certificates: {result.stderr.strip()}")
    # The console's own identity only views: its controls act with the
    # browser's bearer token (decision 35), this run's in certs/console-token,
    # which the console's URL carries (console_url).
    roles = {"operator": "[viewer, operator, safety]", "coordinator": "[viewer, operator, safety]",
             "console": "[viewer]",
             "simulator": "[viewer, operator]", "channel_broker": "[viewer]"}
    lines = ["# Made by deploy/local/launch.py --tls for this run.", "identities:"]
    for name, role_list in roles.items():
        lines += [f"  - certificate: behaviorlib:{name}", f"    roles: {role_list}"]
    token = secrets.token_urlsafe(24)
    token_file = os.path.join(certs, "console-token")
    with open(os.open(token_file, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600), "w") as f:
        f.write(token + "\n")
    lines += [f"  - token_sha256: {hashlib.sha256(token.encode()).hexdigest()}",
              "    name: console-operator",
              "    roles: [viewer, operator, safety]"]
    for process, (robot, system) in systems.items():
        lines += [f"  - certificate: behaviorlib:{process}",
                  "    roles: [viewer, operator, system]",
                  f"    system: {{robot: {robot}, name: {system}}}"]
    with open(os.path.join(certs, "policy.yaml"), "w") as f:
        f.write("\n".join(lines) + "\n")
    rpc.rc.use_tls(os.path.join(certs, "operator.pem"), os.path.join(certs, "operator.key"),
                   os.path.join(certs, "ca.pem"))
    return certs


def console_url(console, run_dir):
    """The console's address for a person: with --tls, with the run's
    operator token (certs/console-token) for the page's controls."""
    token_file = os.path.join(run_dir, "certs", "console-token")
    if not console.url.startswith("https:") or not os.path.exists(token_file):
        return console.url
    with open(token_file) as f:
        return console.url + "?token=" + f.read().strip()


def start_stack(args, build_dir, stack):
    robots = args.vehicles
    several = len(robots) > 1
    deterministic = args.time_scale == "max"
    binaries = system_binaries(args, build_dir)
    python = python_interpreter(build_dir) if args.python_systems else None
    system_processes = {(f"{name}-{robot}" if several else name): (robot, name)
                        for name, _ in binaries for robot in robots}
    certs = (make_certs(stack.run_dir,
                        ["channel_broker", "simulator", "coordinator", "console",
                         *system_processes],
                        system_processes)
             if args.tls else None)

    def listen_as(process):
        argv = ["--listen", "127.0.0.1:0", "--metrics-listen", "127.0.0.1:0"]
        if certs:
            argv += ["--tls-cert", os.path.join(certs, f"{process}.pem"),
                     "--tls-key", os.path.join(certs, f"{process}.key"),
                     "--tls-ca", os.path.join(certs, "ca.pem"),
                     "--access-policy", os.path.join(certs, "policy.yaml")]
        return argv

    broker = stack.start(Process("channel_broker",
                                 [binary(build_dir, "bin/channel_broker"),
                                  *listen_as("channel_broker")],
                                 stack.run_dir, "channel_broker"))

    simulator_argv = [binary(build_dir, "bin/simulator"), *listen_as("simulator"),
                      "--channel", broker.address, "--vehicles", ",".join(robots),
                      "--worlds-dir", WORLDS_DIR,
                      "--time-scale", str(args.time_scale), "--seed", str(args.seed)]
    if args.world:
        simulator_argv += ["--world", args.world]
    if args.sensor_config:
        simulator_argv += ["--sensor-config", os.path.abspath(args.sensor_config)]
    if args.enable_fault_injection:
        simulator_argv.append("--enable-fault-injection")
    if deterministic:
        # Time starts once every behavior system follows the grants.
        followers = (len(binaries) + len(args.python_systems)) * len(robots)
        simulator_argv += ["--min-followers", str(followers)]
    if args.clock_publish != "line":
        simulator_argv += ["--clock-publish", args.clock_publish]
    simulator_argv += args.simulator_arg or []
    simulator = stack.start(Process("simulator", simulator_argv, stack.run_dir, "simulator"))
    # A world with start poses has its own vehicles, whatever --vehicles says.
    flown = simulator_vehicles(simulator)
    if flown is not None and not set(robots) <= set(flown):
        missing = ", ".join(sorted(set(robots) - set(flown)))
        raise StartError(f"the simulator has no vehicle {missing} (its vehicles: "
                         f"{', '.join(flown)}; a world's start poses name them)")

    coordinator_bin = binary(build_dir, "bin/coordinator")
    coordinator_argv = [coordinator_bin, *listen_as("coordinator"),
                        "--state-dir", os.path.join(stack.run_dir, "coordinator"),
                        # The files StartMission's file_path may name (the
                        # console's form).
                        "--mission-dir", os.path.abspath(args.mission_dir)]
    # One --flight-controller flag lists every robot (a repeated flag would
    # replace the previous one).
    coordinator_argv += ["--catalog", os.path.join(CONFIG_DIR, "catalog.yaml"),
                         "--flight-controller",
                         ",".join(f"{robot}={simulator.address}" for robot in robots),
                         # The safety rules' hover before landing lasts the
                         # vehicle's (simulated) time.
                         "--channel", broker.address, "--clock", "sim"]
    if deterministic:
        # Supervision stays in wall time: a system starved for over a second
        # on a loaded machine, which this mode tolerates, is not a dead one.
        coordinator_argv += ["--grace-period-s", str(DETERMINISTIC_GRACE_S)]
    coordinator_argv += args.coordinator_arg or []
    coordinator = stack.start(Process("coordinator", coordinator_argv, stack.run_dir,
                                      "coordinator"))

    console = None
    if args.console:
        console_argv = [binary(build_dir, "bin/console"), "--listen", args.console_listen,
                        "--coordinator", coordinator.address, "--channel", broker.address,
                        "--web-dir", os.path.join(REPO, "console", "web"),
                        "--recordings-dir", recordings_dir(stack.run_dir)]
        os.makedirs(recordings_dir(stack.run_dir), exist_ok=True)
        if args.world:
            console_argv += ["--world", world_file(args.world)]
        if certs:
            console_argv += ["--tls-cert", os.path.join(certs, "console.pem"),
                             "--tls-key", os.path.join(certs, "console.key"),
                             "--tls-ca", os.path.join(certs, "ca.pem")]
        console = stack.start(HttpProcess("console", console_argv, stack.run_dir, "console",
                                          os.path.join(certs, "ca.pem") if certs else None))

    systems = []
    for name, path in binaries:
        config = os.path.join(SYSTEMS_DIR, name, "config.yaml")
        for robot in robots:
            process_name = f"{name}-{robot}" if several else name
            argv = [path, *listen_as(process_name), "--robot-id", robot,
                    "--channel", broker.address,
                    "--clock", "sim", "--flight-controller", simulator.address,
                    "--coordinator", coordinator.address]
            if deterministic:
                argv += ["--follow-time", simulator.address]
            if os.path.exists(config):
                argv += ["--config", config]
            if name == "navigation_with_lidar":
                argv += ["--map-dir", output_root(stack.run_dir)]
            systems.append(stack.start(Process(process_name, argv, stack.run_dir,
                                               "behavior_system", robot, system=name)))
    for name, script in args.python_systems:
        for robot in robots:
            process_name = f"{name}-{robot}" if several else name
            argv = [python, script, *listen_as(process_name), "--robot-id", robot,
                    "--channel", broker.address,
                    "--clock", "sim", "--flight-controller", simulator.address,
                    "--coordinator", coordinator.address]
            if deterministic:
                argv += ["--follow-time", simulator.address]
            process = stack.start(Process(process_name, argv, stack.run_dir, "behavior_system",
                                          robot))
            process.system = python_system_name(process)
            systems.append(process)
    return simulator, coordinator, systems, console


def wait_until_up(coordinator, systems, robots):
    """Serving: waits until the coordinator has every behavior system UP (a
    system registers, then the coordinator opens its event stream), so that
    a mission started once the stack says it serves finds its behaviors. A
    system not UP within the wait is told, and the stack serves anyway."""
    client = rpc.Client(coordinator.address, [demo.COORDINATOR])
    try:
        for robot in robots:
            demo.wait_for_systems(client, robot,
                                  [s.system for s in systems if s.robot_id == robot])
    except RuntimeError as error:
        say(f"  warning: {error}")
    finally:
        client.close()


def run_demo(args, run_dir, simulator, coordinator, systems, state):
    """Flies the missions (every robot's at once); fills `state` with what
    the report needs as it goes (each mission's status, the event and
    trajectory recorders of each robot)."""
    coordinator_client = rpc.Client(coordinator.address, [demo.COORDINATOR])
    state["clients"].append(coordinator_client)
    state["coordinator"] = coordinator_client
    simulator_client = rpc.Client(simulator.address, [demo.SIMULATOR])
    state["clients"].append(simulator_client)
    for robot in args.vehicles:
        state["events"][robot] = demo.EventRecorder(coordinator_client, robot)
        state["trajectories"][robot] = demo.TrajectoryRecorder(simulator_client, robot)
        # The other robots' positions as they arrive (the report keeps the
        # last one and how every one matched the ground truth).
        state["swarm"][robot] = demo.BeliefRecorder(coordinator_client, f"{robot}/swarm/")
        for recorder in (state["events"][robot], state["trajectories"][robot],
                         state["swarm"][robot]):
            recorder.start()
    for robot in args.vehicles:
        demo.wait_for_systems(coordinator_client, robot,
                              [s.system for s in systems if s.robot_id == robot])

    for robot in args.missions:
        output_dir = output_root(run_dir) if len(args.vehicles) == 1 else os.path.join(
            output_root(run_dir), robot)
        os.makedirs(output_dir, exist_ok=True)
        demo.write_belief(coordinator_client, f"{robot}/output_dir", output_dir)

    stamp = f"{time.strftime('%Y%m%d-%H%M%S')}-{os.getpid()}"
    if len(args.vehicles) == 1:
        robot = args.vehicles[0]
        mission_path = args.missions[robot]
        say(f"\n== mission {os.path.relpath(mission_path, REPO)} on {robot} "
            f"(simulator at {args.time_scale}x) ==")

        def on_status(status):
            state["missions"][robot] = status

        demo.run_mission(coordinator_client, mission_path, robot, f"demo-{stamp}",
                         args.mission_timeout_s, say, on_status)
    else:
        missions = [(robot, args.missions[robot], f"demo-{stamp}-{robot}")
                    for robot in args.vehicles if robot in args.missions]
        say(f"\n== missions (simulator at {args.time_scale}x): "
            + ", ".join(f"{os.path.relpath(path, REPO)} on {robot}"
                        for robot, path, _ in missions) + " ==")

        def on_status(robot, status):
            # A fleet mission commands several robots: each one's report
            # shows it.
            for commanded in status.get("robot_ids") or [robot]:
                state["missions"][commanded] = status

        demo.run_missions(coordinator_client, missions, args.mission_timeout_s, say, on_status)
    for robot, events in state["events"].items():
        if not events.wait_settled(3.0):
            say(f"  note: some activations{'' if len(args.vehicles) == 1 else ' of ' + robot} "
                f"had no finished event 3 s after the mission ended")


class FlightRecorder:
    """`behaviorctl record` beside the stack (--record, on for --demo): the
    fleet's events, missions, beliefs and vehicle topics into
    <run-dir>/recordings/flight.mcap (clients/recorder, decision 36). It ends with the
    launcher (SIGTERM at the stop, and the parent-death signal if the
    launcher dies), writing the file's summary."""

    FILE = "flight.mcap"

    def __init__(self, build_dir, run_dir, coordinator, broker, topics, certs):
        self.path = os.path.join(recordings_dir(run_dir), self.FILE)
        self.log_path = os.path.join(run_dir, "logs", "recorder.log")
        self.result = {}
        argv = [binary(build_dir, "bin/behaviorctl"), "--coordinator", coordinator,
                "--channel", broker]
        if topics:
            argv += ["--topics", topics]
        if certs:
            argv += ["--tls-cert", os.path.join(certs, "operator.pem"),
                     "--tls-key", os.path.join(certs, "operator.key"),
                     "--tls-ca", os.path.join(certs, "ca.pem")]
        argv += ["record", self.path]
        os.makedirs(os.path.dirname(self.path), exist_ok=True)
        os.makedirs(os.path.dirname(self.log_path), exist_ok=True)
        self._stdout = tempfile.TemporaryFile(mode="w+")
        with open(self.log_path, "a") as log:
            self.process = popen_with_launcher(argv, stdout=self._stdout, stderr=log,
                                               stdin=subprocess.DEVNULL)

    def stop(self, timeout_s):
        """Ends the recording; what it wrote ({file, bytes, messages})."""
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        self._stdout.seek(0)
        for line in self._stdout.read().splitlines():
            try:
                self.result = json.loads(line)
            except ValueError:
                pass
        self._stdout.close()
        return self.result


# The console has drawn the finished demo: every robot's vehicle on the map,
# the systems, the missions ended and their events.
CONSOLE_READY = """(() => {
  const robots = %s;
  const ended = [...document.querySelectorAll("#missions tbody tr .state")]
    .filter((cell) => ["SUCCEEDED", "FAILED", "ABORTED"].includes(cell.textContent));
  return robots.every((r) => document.querySelector(`#map circle.vehicle[data-robot="${r}"]`))
    && document.querySelectorAll("#systems tbody tr").length > 0
    && ended.length > 0 && document.querySelectorAll("#events tbody tr").length > 0;
})()"""


def save_console(console, run_dir, robots):
    """A screenshot of the console at the end of the demo, beside the report
    (console.png); its name, or "" when there is none (the reason is said)."""
    path = os.path.join(run_dir, "console.png")
    problem = screenshot.take(console.url, path, CONSOLE_READY % json.dumps(robots))
    if problem:
        say(f"  console screenshot: {problem}")
    if not os.path.exists(path):
        return ""
    say(f"  console screenshot: {path}")
    return "console.png"


def parse_python_systems(parser, args):
    """args.python_systems: [(process name, absolute script path)] from
    --python-systems (paths relative to the repository root); a name is
    its script's file name without .py, and must be new."""
    found = []
    for value in [v for v in args.python_systems.split(",") if v]:
        path = value if os.path.isabs(value) else os.path.join(REPO, value)
        if not os.path.isfile(path):
            parser.error(f"--python-systems: {path} is not a file")
        name = os.path.splitext(os.path.basename(path))[0]
        if name in STACK_PROCESSES + BEHAVIOR_SYSTEMS + [n for n, _ in found]:
            parser.error(f"--python-systems {value}: a process is named {name} already (one "
                         "is named after its script's file)")
        found.append((name, path))
    if found and args.tls:
        parser.error("--python-systems: Python behavior systems serve no TLS yet (--tls)")
    return found


def parse_missions(parser, args):
    """args.missions: robot -> absolute mission file, from the --mission
    values (FILE for the first robot, or ROBOT=FILE); the demo mission on
    the first robot when there is none."""
    missions = {}
    for value in args.mission or []:
        robot, sep, path = value.partition("=")
        if not (sep and re.fullmatch(r"[A-Za-z0-9_.-]+", robot) and not os.path.exists(value)):
            robot, path = args.vehicles[0], value
        if robot not in args.vehicles:
            parser.error(f"--mission {value}: {robot} is not one of the vehicles "
                         f"({','.join(args.vehicles)})")
        if robot in missions:
            parser.error(f"--mission {value}: {robot} has a mission already "
                         f"({missions[robot]})")
        missions[robot] = os.path.abspath(path)
    if not missions:
        missions[args.vehicles[0]] = DEMO_MISSION
    if args.demo:
        for robot, path in missions.items():
            if not os.path.isfile(path):
                parser.error(f"--mission: {path} (for {robot}) is not a file")
    return missions


def robot_reports(args, build_dir, state, run_dir):
    """Per robot what report.write needs; measures the coverage of each map
    saved (map_coverage), printing it, and keeps its occupied cells in
    run_dir (map_cells_<robot>.json, for the plot)."""
    world_path = world_file(args.world)
    tool = os.path.join(build_dir, MAP_COVERAGE)
    robots = []
    for robot in args.vehicles:
        findings = dict(state["findings"].get(robot, {}))
        if "map_file" in findings:
            cells = os.path.join(run_dir, f"map_cells_{robot}.json")
            coverage = demo.measure_map_coverage(tool, world_path, findings["map_file"],
                                                 cells_path=cells)
            if os.path.isfile(cells):
                findings["map_cells_file"] = cells
            findings["map_coverage"] = coverage
            who = "" if len(args.vehicles) == 1 else f" of {robot}"
            if "mapped_fraction" in coverage:
                say(f"map{who}: {coverage['mapped_fraction'] * 100:.0f} % of the world's free "
                    f"space mapped ({findings['map_file']})")
            else:
                say(f"map{who}: coverage not measured: {coverage.get('error')}")
        swarm = state["swarm"].get(robot)
        tracks = demo.swarm_tracks(swarm.snapshot(), robot) if swarm else {}
        if tracks:
            findings["swarm_tracks"] = tracks
        path = args.missions.get(robot)
        if path is None:
            # A fleet mission started for another robot commands this one.
            path = next((args.missions[r] for r in args.missions
                         if robot in state["missions"].get(r, {}).get("robot_ids", [])), None)
        events = state["events"].get(robot)
        trajectory = state["trajectories"].get(robot)
        robots.append({"robot_id": robot,
                       "mission_file": os.path.relpath(path, REPO) if path else "",
                       "mission": state["missions"].get(robot, {}),
                       "behavior_events": events.behavior_events() if events else [],
                       "samples": trajectory.snapshot() if trajectory else [],
                       "findings": findings})
    return robots


def time_scale_arg(text):
    """--time-scale: a number of simulated seconds per wall second, or 'max'."""
    if text == "max":
        return text
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is neither a number nor 'max'") from None


def main():
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--build-dir", default="build", help="where the binaries are built")
    parser.add_argument("--run-dir", default="",
                        help="directory for logs, ports, state and the report (default: a new "
                             "directory under /tmp)")
    parser.add_argument("--robot-id", default="drone1",
                        help="the robot, when --vehicles is not given")
    parser.add_argument("--vehicles", default="",
                        help="comma-separated robot ids (e.g. drone1,drone2): the simulator flies "
                             "them all (in a world with start poses, they must be among them; "
                             "in the empty field vehicle i starts at x = 2 i m) and every "
                             "behavior system runs once per robot, named <system>-<robot>; "
                             "default: --robot-id's one robot")
    parser.add_argument("--time-scale", type=time_scale_arg, default=2.0,
                        help="simulated seconds per wall second. Idle, the stack costs about 6 "
                             "%% of a core at 1x and 10 %% at 10x; flying, the controllers run in "
                             "scaled wall time and can starve on a loaded machine: 2x leaves a "
                             "margin. With --systems (a lighter stack) 3-5x is fine. 'max': "
                             "the deterministic mode, time advanced in 10 ms quanta as fast as "
                             "every busy behavior system has its data and ran its ticks (a "
                             "starved process slows the simulation; the demo runs about 5-6x "
                             "with the whole stack, 9-10x with the light one; the coordinator "
                             f"then waits {DETERMINISTIC_GRACE_S:g} wall seconds, not 1, before "
                             "it declares a silent system down)")
    parser.add_argument("--world", default="",
                        help="simulator world (file or shipped name); default an empty field")
    parser.add_argument("--seed", type=int, default=1, help="the simulator's noise seed")
    parser.add_argument("--systems", default="",
                        help="comma-separated behavior systems to start (each must be built; "
                             "basic_quadrotor_behaviors always is), e.g. "
                             "quadrotor_motion_with_pid_control,swarm_interaction: a lighter "
                             "stack; default: every behavior system that is built")
    parser.add_argument("--python-systems", default="", metavar="PATH[,PATH...]",
                        help="behavior systems written in Python to start too, after the C++ "
                             "ones: scripts that call behaviorlib.system.run_system (paths "
                             "relative to the repository root, or absolute), each per robot "
                             "with a C++ system's flags, named after its file (without .py), "
                             f"run by ${PYTHON_ENV} (default <build-dir>/venv/bin/python)")
    parser.add_argument("--sensor-config", default="",
                        help="the simulator's sensor configuration (YAML; e.g. "
                             "deploy/config/simulator_sensors_aircraft.yaml); default: the "
                             "built-in defaults (deploy/config/simulator_sensors.yaml)")
    parser.add_argument("--clock-publish", choices=("line", "every-tick"), default="line",
                        help="how the simulator publishes simulated time: its pace line when it "
                             "changes and once a wall second (default; readers extrapolate), or "
                             "a sample every 5 ms of simulated time (as before decision 16)")
    parser.add_argument("--simulator-arg", action="append", metavar="ARG",
                        help="an extra argument for the simulator (repeatable), e.g. "
                             "--simulator-arg=--gate-topics=false to publish every sample as "
                             "before decision 17 (benchmarks)")
    parser.add_argument("--coordinator-arg", action="append", metavar="ARG",
                        help="an extra argument for the coordinator (repeatable), e.g. "
                             "--coordinator-arg=--max-ended-missions=100 (what it retains; "
                             "`coordinator --help` lists them)")
    parser.add_argument("--enable-fault-injection", action="store_true",
                        help="let Simulator.InjectFailure inject faults")
    parser.add_argument("--tls", action="store_true",
                        help="mutual TLS and roles between every process: a CA, a certificate "
                             "per process and an access policy are made in <run-dir>/certs "
                             "(scripts/make-dev-certs.sh); gRPC then needs a client certificate "
                             "from that CA (certs/operator.pem for grpcurl and behaviorctl)")
    parser.add_argument("--demo", action="store_true",
                        help="fly the demo mission (or the --mission files), write the report, "
                             "then stop everything")
    parser.add_argument("--mission", action="append", metavar="[ROBOT=]FILE",
                        help="mission file flown by --demo: FILE for the first (or only) robot, "
                             "or ROBOT=FILE, repeated for several robots (each started through "
                             "StartMission with its robot id, all at once); default "
                             "deploy/missions/demo.yaml on the first robot")
    parser.add_argument("--mission-timeout-s", type=float, default=300.0,
                        help="wall seconds after which the demo aborts the missions")
    parser.add_argument("--stop-timeout-s", type=float, default=10.0,
                        help="wall seconds a process has after SIGTERM before SIGKILL")
    parser.add_argument("--mission-dir", default=os.path.join(REPO, "deploy", "missions"),
                        help="the coordinator's --mission-dir: the mission files a client "
                             "(the console's form) may start by name (default: %(default)s)")
    parser.add_argument("--no-console", dest="console", action="store_false",
                        help="do not start the operator's console (console/, decision 35)")
    parser.add_argument("--console-listen", default="127.0.0.1:0", metavar="HOST:PORT",
                        help="the console's HTTP address (port 0: any free port; the URL is "
                             "printed; default: %(default)s)")
    parser.add_argument("--record", action=argparse.BooleanOptionalAction, default=None,
                        help="record the flight into <run-dir>/recordings/flight.mcap with "
                             "behaviorctl record: events, missions, beliefs and the vehicle "
                             "topics (MCAP, decision 36); on by default with --demo")
    parser.add_argument("--record-topics", default="", metavar="A,B@HZ",
                        help="the vehicle topics recorded under robots/{id}/, each NAME (every "
                             "sample) or NAME@HZ (at most HZ samples a wall second); default: "
                             "poses and twist @30, flight state, marker detections, the map's "
                             "occupied cells; add camera/image@5 or lidar/scan here")
    parser.add_argument("--restart", choices=RestartPolicy.MODES, default="on-failure",
                        help="on-failure: a process that crashes (non-zero exit code, or a "
                             "signal) is started again on its ports, at most 5 times in 60 s "
                             "(then the launcher gives up and stops the stack); no: a process "
                             "that exits stops the stack (default: %(default)s)")
    args = parser.parse_args()
    args.vehicles = [v for v in args.vehicles.split(",") if v] or [args.robot_id]
    if len(set(args.vehicles)) != len(args.vehicles):
        parser.error(f"--vehicles {','.join(args.vehicles)}: a robot is named twice")
    for robot in args.vehicles:
        if not re.fullmatch(r"[A-Za-z0-9_-]+", robot):
            parser.error(f"--vehicles: '{robot}' is not a robot id (letters, digits, _ and -)")
    args.systems = [s for s in args.systems.split(",") if s]
    for name in args.systems:
        if name not in BEHAVIOR_SYSTEMS:
            parser.error(f"--systems: no behavior system {name} (known: "
                         f"{', '.join(BEHAVIOR_SYSTEMS)})")
    args.python_systems = parse_python_systems(parser, args)
    args.missions = parse_missions(parser, args)
    if args.record is None:
        args.record = args.demo
    if args.sensor_config and not os.path.isfile(args.sensor_config):
        parser.error(f"--sensor-config: {args.sensor_config} is not a file")
    build_dir = os.path.abspath(args.build_dir)
    run_dir = os.path.abspath(args.run_dir) if args.run_dir else tempfile.mkdtemp(
        prefix="behaviorlib-run-")
    os.makedirs(run_dir, exist_ok=True)
    for signum in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(signum, _on_signal)

    started = time.monotonic()
    stack = Stack(run_dir)
    supervisor = Supervisor(stack, RestartPolicy(args.restart), say)
    status = 0
    demo_state = {"missions": {}, "events": {}, "trajectories": {}, "swarm": {}, "findings": {},
                  "coordinator": None, "clients": []}
    figures = ([], [])
    interrupted = ""
    console = None
    flight_recorder = None
    recording = {}
    console_png = ""
    say(f"run directory: {run_dir}")
    try:
        say("\n== starting ==")
        simulator, coordinator, systems, console = start_stack(args, build_dir, stack)
        supervisor.start()
        targets = stack.write_prometheus_targets()
        say("\n== running ==")
        for p in stack.processes:
            if p is console:
                continue
            metrics = f"http://{p.metrics_address}/metrics" if p.metrics_port else "-"
            say(f"  {p.name:<40} gRPC {p.address:<17} metrics {metrics}")
        say(f"  Prometheus targets: {targets}")
        if console is not None:
            say(f"  console: {console_url(console, run_dir)}")
        if args.record:
            flight_recorder = FlightRecorder(
                build_dir, run_dir, coordinator.address, stack.find("channel_broker").address,
                args.record_topics, os.path.join(run_dir, "certs") if args.tls else None)
            say(f"  recording: {flight_recorder.path}")
        if args.demo:
            run_demo(args, run_dir, simulator, coordinator, systems, demo_state)
            supervisor.check()
            if console is not None:
                console_png = save_console(console, run_dir, args.vehicles)
            if any(demo_state["missions"].get(robot, {}).get("state") != "MISSION_STATE_SUCCEEDED"
                   for robot in args.missions):
                status = 1
        else:
            wait_until_up(coordinator, systems, args.vehicles)
            say("Ctrl-C stops everything.")
            while True:
                supervisor.check()
                time.sleep(0.5)
    except Interrupted as signal_received:
        interrupted = str(signal_received)
        say(f"\n{interrupted}: stopping")
        status = 128 + signal_received.signum
    except (StartError, RuntimeError, rpc.grpc.RpcError, OSError) as error:
        text = (f"{error.code().name}: {error.details()}" if isinstance(error, rpc.grpc.RpcError)
                else str(error))
        print(f"launch.py: {text}", file=sys.stderr, flush=True)
        status = 1
    finally:
        # Signals during the shutdown would leave processes behind.
        for signum in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
            signal.signal(signum, signal.SIG_IGN)
        # No restart from here on: the processes are stopped on purpose.
        supervisor.stop()
        recorders = (list(demo_state["events"].values())
                     + list(demo_state["trajectories"].values())
                     + list(demo_state["swarm"].values()))
        for recorder in recorders:
            recorder.stop()
        if recorders:
            figures = demo.collect_figures(stack, say)
        if demo_state["coordinator"] is not None:
            for robot in args.vehicles:
                try:
                    demo_state["findings"][robot] = demo.robot_findings(
                        demo_state["coordinator"], robot)
                except rpc.grpc.RpcError as error:
                    say(f"  cannot read the beliefs of {robot}: {error.code().name}: "
                        f"{error.details()}")
        for client in demo_state["clients"]:
            client.close()
        say("\n== stopping ==")
        if flight_recorder is not None:
            recording = flight_recorder.stop(args.stop_timeout_s)
            code = flight_recorder.process.returncode
            if code == 0 and recording:
                say(f"  recording {flight_recorder.path}: {recording.get('bytes', 0):.0f} bytes, "
                    f"{sum(recording.get('messages', {}).values()):.0f} messages"
                    + ("" if recording.get("drained") else
                       " (it did not catch up with the coordinator before closing)"))
            else:
                say(f"  the recorder ended with {code}: {flight_recorder.log_path}")
        clean = stack.stop(args.stop_timeout_s, say)
        if not clean:
            status = status or 1
    if demo_state["events"] and demo_state["trajectories"]:
        behaviors, processes = figures
        for row in processes:
            process = stack.find(row["name"])
            row["exit_code"] = process.exit_code
            row["restarts"] = process.restarts
        first = args.vehicles[0]
        settings = {"mission": os.path.relpath(args.missions.get(first, ""), REPO)
                    if first in args.missions else "",
                    "robot_id": first, "time_scale": args.time_scale,
                    "world": args.world, "world_file": world_file(args.world),
                    "seed": args.seed, "run_dir": run_dir,
                    "wall_s": time.monotonic() - started, "interrupted": interrupted,
                    "vehicles": args.vehicles,
                    "missions": {robot: os.path.relpath(path, REPO)
                                 for robot, path in args.missions.items()},
                    "sensor_config": os.path.relpath(os.path.abspath(args.sensor_config), REPO)
                    if args.sensor_config else "",
                    "console_url": console_url(console, run_dir) if console is not None else "",
                    "recording": flight_recorder.path if recording else "",
                    "console_screenshot": console_png,
                    "recording_messages": recording.get("messages", {})}
        robots = robot_reports(args, build_dir, demo_state, run_dir)
        report.write(run_dir, settings, robots, behaviors, processes, clean,
                     world_markers(world_file(args.world)), world_walls(world_file(args.world)))
        say("")
        for robot in args.vehicles:
            if robot not in args.missions:
                continue
            mission = demo_state["missions"].get(robot, {})
            state = mission.get("state", "MISSION_STATE_UNSPECIFIED").replace("MISSION_STATE_",
                                                                              "")
            where = "" if len(args.vehicles) == 1 else f" on {robot}"
            say(f"mission {mission.get('name', '')}{where}: {state}")
        say(f"report: {os.path.join(run_dir, 'report.md')} (also report.json, trajectory.png, timeline.png)")
    return status


if __name__ == "__main__":
    sys.exit(main())
