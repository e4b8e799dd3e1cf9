"""What reading the vehicle through the coordinator costs (issue 40 goal 1,
decision 47): GetVehicleSample against two floors measured in the same run,
and what open WatchVehicle streams cost the coordinator.

    BEHAVIORLIB_BUILD_DIR=build build/venv/bin/python tests/bench/stack/telemetry_bench.py \\
        [--reads 500] [--time-scale 1]

The stack is the local launcher's (deploy/local/launch.py: broker, simulator
with drone1, the behavior systems, the coordinator with --channel and --clock
sim) on loopback. Three unary calls, interleaved round by round so that the
machine's drift falls on all three alike:
  - ListSystems to the coordinator: one hop to it, no channel (floor 1);
  - GetLatest of robots/drone1/ground_truth/pose to the broker, from this
    process (floor 2: the channel's own read);
  - GetVehicleSample of the same topic through the coordinator, which is
    both hops (the client's drone.sample("ground_truth_pose")).
Then the coordinator's CPU over a window with no watch open, and with 16
watches of the ground-truth pose at 10 Hz each.

Prints medians and p99 in microseconds, and the CPU, for docs/benchmarks.md.
"""

import argparse
import json
import os
import re
import shutil
import statistics
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.abspath(os.path.join(HERE, "..", "..", ".."))
sys.path[:0] = [os.path.join(REPO, "deploy", "local"), os.path.join(REPO, "tests", "deploy"),
                os.path.join(REPO, "tests", "e2e")]
import grpc  # noqa: E402
from local_demo_test import kill_launched  # noqa: E402
from local_restart_test import Launcher  # noqa: E402
from stack import read_ports  # noqa: E402

from behaviorlib import Fleet  # noqa: E402
from behaviorlib.v1 import channel_pb2, channel_pb2_grpc, coordinator_pb2  # noqa: E402

TOPIC = "robots/drone1/ground_truth/pose"


def percentile(values, q):
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(round(q * (len(ordered) - 1))))]


def cpu_s(pid):
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rpartition(")")[2].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def coordinator_pid(run_dir):
    with open(os.path.join(run_dir, "pids.json")) as f:
        return json.load(f)["coordinator"]


def cpu_percent(pid, window_s):
    start, begin = cpu_s(pid), time.monotonic()
    time.sleep(window_s)
    return 100.0 * (cpu_s(pid) - start) / (time.monotonic() - begin)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reads", type=int, default=500)
    parser.add_argument("--time-scale", default="1")
    parser.add_argument("--window-s", type=float, default=10.0)
    args = parser.parse_args()
    build_dir = os.path.abspath(os.environ.get("BEHAVIORLIB_BUILD_DIR",
                                               os.path.join(REPO, "build")))
    run_dir = tempfile.mkdtemp(prefix="behaviorlib-telemetry-bench-")
    launcher = Launcher(["/usr/bin/python3", os.path.join(REPO, "deploy", "local", "launch.py"),
                         "--build-dir", build_dir, "--run-dir", run_dir, "--time-scale",
                         args.time_scale, "--vehicles", "drone1"])
    try:
        launcher.wait_for(re.escape("Ctrl-C stops everything."), 120, "the launcher serving")
        def address(name):
            ports = read_ports(os.path.join(run_dir, "ports", name + ".ports"))
            return f"127.0.0.1:{ports['grpc_port']}"
        coordinator, broker = address("coordinator"), address("channel_broker")
        with Fleet(coordinator) as fleet, grpc.insecure_channel(broker) as channel:
            drone = fleet.robot("drone1")
            stub = channel_pb2_grpc.DataChannelStub(channel)
            calls = {
                "ListSystems (coordinator, floor 1)": lambda: fleet._stub.ListSystems(
                    coordinator_pb2.ListSystemsRequest(), timeout=10),
                "GetLatest (broker, floor 2)": lambda: stub.GetLatest(
                    channel_pb2.GetLatestRequest(topic=TOPIC), timeout=10),
                "GetVehicleSample (both)": lambda: drone.sample("ground_truth_pose"),
            }
            for call in calls.values():  # warm: connections, the topic wanted
                for _ in range(20):
                    call()
            times = {name: [] for name in calls}
            for _ in range(args.reads):
                for name, call in calls.items():
                    begin = time.perf_counter()
                    call()
                    times[name].append((time.perf_counter() - begin) * 1e6)
            print(f"reads: {args.reads} rounds, time scale {args.time_scale}")
            print("| call | median µs | p99 µs |")
            print("|---|---:|---:|")
            for name, values in times.items():
                print(f"| {name} | {statistics.median(values):.0f} | "
                      f"{percentile(values, 0.99):.0f} |")
            pid = coordinator_pid(run_dir)
            idle = cpu_percent(pid, args.window_s)
            watches = [drone.subscribe("ground_truth_pose", max_rate_hz=10) for _ in range(16)]
            for watch in watches:
                next(watch)
            watched = cpu_percent(pid, args.window_s)
            for watch in watches:
                watch.close()
            print(f"coordinator CPU over {args.window_s:.0f} s: no watch {idle:.2f} % of a core, "
                  f"16 watches at 10 Hz {watched:.2f} %")
    finally:
        try:
            launcher.interrupt(timeout_s=60)
        finally:
            launcher.kill()
            kill_launched(run_dir)
            shutil.rmtree(run_dir, ignore_errors=True)


if __name__ == "__main__":
    main()
