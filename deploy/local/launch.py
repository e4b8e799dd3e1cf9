#!/usr/bin/python3
"""Starts the behaviorlib stack on this machine, without Docker.

Starts on loopback, with ports chosen free at run time, each one health
checked before the next: the data channel broker, the simulator, the
coordinator and every behavior system that is built. Writes one log file per
process, the ports, the pids and Prometheus file-based service discovery
targets into a run directory. Then either serves until Ctrl-C, or (--demo)
flies the demo mission through the coordinator, prints its progress, and
writes a mission report (report.md, report.json, trajectory.png). Stops
every process in reverse order (SIGTERM, then SIGKILL after a time-out) on
exit and on Ctrl-C.

    deploy/local/launch.py --build-dir build --demo
    deploy/local/launch.py --build-dir build          # serve until Ctrl-C

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
    report.md, report.json, trajectory.png   (--demo)

Exit code 0 when every process started and stopped cleanly and, with --demo,
the mission SUCCEEDED; 128 + the signal's number when stopped by a signal.

Needs Debian's python3-grpcio, python3-protobuf and python3-yaml; calls the
servers through gRPC reflection (no generated code).
"""

import argparse
import os
import signal
import subprocess
import sys
import tempfile
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import demo  # noqa: E402
import report  # noqa: E402
import rpc  # noqa: E402
from stack import Process, Stack, StartError  # noqa: E402

REPO = os.path.abspath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", ".."))
CONFIG_DIR = os.path.join(REPO, "deploy", "config")

# The behavior systems, started in this order when their binary is built
# (services/<name>/<name>), each with deploy/config/<name>.yaml when present.
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


class Interrupted(Exception):
    """SIGINT, SIGTERM or SIGHUP reached the launcher."""

    def __init__(self, signum):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


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


def start_stack(args, build_dir, stack):
    robot = args.robot_id
    listen = ["--listen", "127.0.0.1:0", "--metrics-listen", "127.0.0.1:0"]
    broker = stack.start(Process("channel_broker",
                                 [binary(build_dir, "services/channel/channel_broker"), *listen],
                                 stack.run_dir, "channel_broker"))

    simulator_argv = [binary(build_dir, "simulator/service/simulator"), *listen,
                      "--channel", broker.address, "--vehicles", robot,
                      "--worlds-dir", os.path.join(REPO, "simulator", "worlds"),
                      "--time-scale", str(args.time_scale), "--seed", str(args.seed)]
    if args.world:
        simulator_argv += ["--world", args.world]
    if args.enable_fault_injection:
        simulator_argv.append("--enable-fault-injection")
    simulator = stack.start(Process("simulator", simulator_argv, stack.run_dir, "simulator"))

    coordinator_bin = binary(build_dir, "coordinator/coordinator")
    coordinator_argv = [coordinator_bin, *listen,
                        "--state-dir", os.path.join(stack.run_dir, "coordinator")]
    coordinator_argv += ["--catalog", os.path.join(CONFIG_DIR, "catalog.yaml"),
                         "--flight-controller", f"{robot}={simulator.address}",
                         "--channel", broker.address]
    coordinator = stack.start(Process("coordinator", coordinator_argv, stack.run_dir,
                                      "coordinator"))

    systems = []
    for name in BEHAVIOR_SYSTEMS:
        path = binary(build_dir, f"services/{name}/{name}", required=name in REQUIRED_SYSTEMS)
        if path is None:
            say(f"  note: {name} is not built ({build_dir}/services/{name}/{name}); "
                f"its behaviors are unavailable")
            continue
        argv = [path, *listen, "--robot-id", robot, "--channel", broker.address,
                "--clock", "sim", "--flight-controller", simulator.address,
                "--coordinator", coordinator.address]
        config = os.path.join(CONFIG_DIR, name + ".yaml")
        if os.path.exists(config):
            argv += ["--config", config]
        systems.append(stack.start(Process(name, argv, stack.run_dir, "behavior_system", robot)))
    return simulator, coordinator, systems


def run_demo(args, simulator, coordinator, systems, state):
    """Flies the mission; fills `state` with what the report needs as it
    goes (the mission's status, the event and trajectory recorders)."""
    robot = args.robot_id
    coordinator_client = rpc.Client(coordinator.address, [demo.COORDINATOR])
    state["clients"].append(coordinator_client)
    simulator_client = rpc.Client(simulator.address, [demo.SIMULATOR])
    state["clients"].append(simulator_client)
    events = state["events"] = demo.EventRecorder(coordinator_client, robot)
    trajectory = state["trajectory"] = demo.TrajectoryRecorder(simulator_client, robot)
    events.start()
    trajectory.start()
    demo.wait_for_systems(coordinator_client, robot, [s.name for s in systems])

    mission_path = os.path.abspath(args.mission)
    mission_id = f"demo-{time.strftime('%Y%m%d-%H%M%S')}-{os.getpid()}"
    say(f"\n== mission {os.path.relpath(mission_path, REPO)} on {robot} "
        f"(simulator at {args.time_scale}x) ==")

    def on_status(status):
        state["mission"] = status

    demo.run_mission(coordinator_client, mission_path, robot, mission_id,
                     args.mission_timeout_s, say, on_status)
    if not events.wait_settled(3.0):
        say("  note: some activations had no finished event 3 s after the mission ended")


def main():
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--build-dir", default="build", help="where the binaries are built")
    parser.add_argument("--run-dir", default="",
                        help="directory for logs, ports, state and the report (default: a new "
                             "directory under /tmp)")
    parser.add_argument("--robot-id", default="drone1")
    parser.add_argument("--time-scale", type=float, default=5.0,
                        help="simulated seconds per wall second. The whole stack takes about "
                             "0.2-0.3 s of CPU per simulated second: at 10x it saturates two "
                             "cores and the controllers fall behind; 5x leaves a margin")
    parser.add_argument("--world", default="",
                        help="simulator world (file or shipped name); default an empty field")
    parser.add_argument("--seed", type=int, default=1, help="the simulator's noise seed")
    parser.add_argument("--enable-fault-injection", action="store_true",
                        help="let Simulator.InjectFailure inject faults")
    parser.add_argument("--demo", action="store_true",
                        help="fly the demo mission, write the report, then stop everything")
    parser.add_argument("--mission", default=os.path.join(REPO, "deploy", "missions", "demo.yaml"),
                        help="mission file flown by --demo")
    parser.add_argument("--mission-timeout-s", type=float, default=300.0,
                        help="wall seconds after which the demo aborts the mission")
    parser.add_argument("--stop-timeout-s", type=float, default=10.0,
                        help="wall seconds a process has after SIGTERM before SIGKILL")
    args = parser.parse_args()
    build_dir = os.path.abspath(args.build_dir)
    run_dir = os.path.abspath(args.run_dir) if args.run_dir else tempfile.mkdtemp(
        prefix="behaviorlib-run-")
    os.makedirs(run_dir, exist_ok=True)
    for signum in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(signum, _on_signal)

    started = time.monotonic()
    stack = Stack(run_dir)
    status = 0
    demo_state = {"mission": {}, "events": None, "trajectory": None, "clients": []}
    figures = ([], [])
    interrupted = ""
    say(f"run directory: {run_dir}")
    try:
        say("\n== starting ==")
        simulator, coordinator, systems = start_stack(args, build_dir, stack)
        targets = stack.write_prometheus_targets()
        say("\n== running ==")
        for p in stack.processes:
            metrics = f"http://{p.metrics_address}/metrics" if p.metrics_port else "-"
            say(f"  {p.name:<40} gRPC {p.address:<17} metrics {metrics}")
        say(f"  Prometheus targets: {targets}")
        if args.demo:
            run_demo(args, simulator, coordinator, systems, demo_state)
            if demo_state["mission"].get("state") != "MISSION_STATE_SUCCEEDED":
                status = 1
        else:
            say("Ctrl-C stops everything.")
            while True:
                for p in stack.processes:
                    if not p.running():
                        raise StartError(f"{p.name} exited with code {p.process.returncode}; "
                                         f"log {p.log_path}")
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
        recorders = [demo_state[k] for k in ("events", "trajectory") if demo_state[k]]
        for recorder in recorders:
            recorder.stop()
        if recorders:
            figures = demo.collect_figures(stack, say)
        for client in demo_state["clients"]:
            client.close()
        say("\n== stopping ==")
        clean = stack.stop(args.stop_timeout_s, say)
        if not clean:
            status = status or 1
    if demo_state["events"] and demo_state["trajectory"]:
        behaviors, processes = figures
        for row in processes:
            row["exit_code"] = stack.find(row["name"]).exit_code
        mission = demo_state["mission"]
        settings = {"mission": os.path.relpath(os.path.abspath(args.mission), REPO),
                    "robot_id": args.robot_id, "time_scale": args.time_scale,
                    "world": args.world, "seed": args.seed, "run_dir": run_dir,
                    "wall_s": time.monotonic() - started, "interrupted": interrupted}
        report.write(run_dir, settings, mission, demo_state["events"].behavior_events(),
                     behaviors, processes, demo_state["trajectory"].snapshot(), clean)
        state = mission.get("state", "MISSION_STATE_UNSPECIFIED").replace("MISSION_STATE_", "")
        say(f"\nmission {mission.get('name', '')}: {state}")
        say(f"report: {os.path.join(run_dir, 'report.md')} (also report.json, trajectory.png)")
    return status


if __name__ == "__main__":
    sys.exit(main())
