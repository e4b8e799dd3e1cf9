"""The console's live-update latency and its cost (issue 19: updates within
200 ms of the event), against the real coordinator, a behavior system, the
broker, the simulator and the console on loopback:

    /usr/bin/python3 tests/bench/stack/console_bench.py --build-dir build [--activations 100]

Latency: each behavior event's FleetEvent.wall_time (the coordinator's clock,
when it took the event) to its arrival (this host's clock) on two paths at
once, the coordinator's own WatchEvents over gRPC (the floor) and the
console's event feed (/api/events, Server-Sent Events). The console adds the
difference. WAIT activations of 10 ms are made one after another with
behaviorctl.

Cost: the console's CPU time and resident memory over an idle interval with
the simulator publishing (it follows each robot's pose and flight status).

Prints a table for docs/benchmarks.md; exits 1 if an event is missing on
either path. The smoke run (ctest console_bench_smoke) makes 3 activations.
"""

import argparse
import calendar
import json
import os
import statistics
import subprocess
import sys
import threading
import time

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.abspath(os.path.join(HERE, "..", "..", ".."))
sys.path.insert(0, os.path.join(REPO, "tests", "integration"))
sys.path.insert(0, os.path.join(REPO, "deploy", "local"))
import console_gateway_test as cg  # noqa: E402  (Process, EventFeed)
import demo  # noqa: E402
import rpc  # noqa: E402


def wall_s(stamp):
    """An RFC 3339 timestamp (FleetEvent.wall_time in JSON) in seconds."""
    clock, _, fraction = stamp.rstrip("Z").partition(".")
    seconds = calendar.timegm(time.strptime(clock, "%Y-%m-%dT%H:%M:%S"))
    return seconds + (float("0." + fraction) if fraction else 0.0)


def percentile(values, q):
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(round(q * (len(ordered) - 1))))]


def proc_cpu_s(pid):
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rpartition(")")[2].split()
    ticks = os.sysconf("SC_CLK_TCK")
    return (int(fields[11]) + int(fields[12])) / ticks


def proc_rss_mib(pid):
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return 0.0


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--build-dir", default=os.path.join(REPO, "build"))
    parser.add_argument("--activations", type=int, default=100)
    parser.add_argument("--idle-s", type=float, default=10.0)
    args = parser.parse_args()
    cg.BUILD_DIR = os.path.abspath(args.build_dir)
    run_dir = cg.tempfile.mkdtemp(prefix="console-bench-")
    listen = ["--listen", "127.0.0.1:0", "--metrics-listen", "127.0.0.1:0"]
    processes = []
    try:
        broker = cg.Process("channel_broker", listen, run_dir)
        processes.append(broker)
        broker_address = f"127.0.0.1:{broker.ports['grpc_port']}"
        processes.append(cg.Process("simulator", listen + ["--channel", broker_address,
                                                           "--vehicles", "robot-a"], run_dir))
        coordinator = cg.Process("coordinator", listen, run_dir)
        processes.append(coordinator)
        coordinator_address = f"127.0.0.1:{coordinator.ports['grpc_port']}"
        processes.append(cg.Process("basic_quadrotor_behaviors",
                                    listen + ["--robot-id", "robot-a", "--coordinator",
                                              coordinator_address], run_dir))
        console = cg.Process("console", ["--listen", "127.0.0.1:0", "--coordinator",
                                         coordinator_address, "--channel", broker_address],
                             run_dir)
        processes.append(console)
        port = int(console.ports["http_port"])

        # The floor: the coordinator's WatchEvents, directly.
        client = rpc.Client(coordinator_address, [demo.COORDINATOR])
        direct = demo.EventRecorder(client, "robot-a")
        direct.start()
        # The console's feed, read on a thread of its own.
        feed = cg.EventFeed(port)
        sse = {}
        stop = threading.Event()

        def read_feed():
            while not stop.is_set():
                try:
                    _, event, data = feed.next()
                except (EOFError, OSError, ValueError, AttributeError):  # closed
                    return
                if event == "fleet" and "behavior_event" in data:
                    sse[int(data["seq"])] = (time.time(), data)

        reader = threading.Thread(target=read_feed, daemon=True)
        reader.start()

        # Until the system is UP.
        deadline = time.monotonic() + 60
        while not any(s.get("state") == "SYSTEM_STATE_UP" for s in
                      client.call(demo.COORDINATOR, "ListSystems").get("systems", [])):
            if time.monotonic() > deadline:
                print("console_bench: the behavior system never came up")
                return 1
            time.sleep(0.1)
        started = time.monotonic()
        ctl = os.path.join(cg.BUILD_DIR, "bin", "behaviorctl")
        for _ in range(args.activations):
            subprocess.run([ctl, "--coordinator", coordinator_address, "--robot", "robot-a",
                            "activate", "WAIT", json.dumps({"duration_s": 0.01})], check=True,
                           stdout=subprocess.DEVNULL, timeout=60)
        expected = 2 * args.activations  # activated and finished each
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            have_direct = [e for e in direct.events if "behavior_event" in e]
            if len(have_direct) >= expected and len(sse) >= expected:
                break
            time.sleep(0.1)
        activations_s = time.monotonic() - started

        direct_ms, sse_ms = [], []
        for event in direct.events:
            if "behavior_event" not in event:
                continue
            stamp = wall_s(event["wall_time"])
            direct_ms.append((event["received_wall_s"] - stamp) * 1e3)
            seq = int(event["seq"])
            if seq in sse:
                sse_ms.append((sse[seq][0] - stamp) * 1e3)
        missing = expected - len(sse_ms)

        # Idle: no activations; the simulator publishes, the console follows.
        cpu0, t0 = proc_cpu_s(console.process.pid), time.monotonic()
        time.sleep(args.idle_s)
        cpu1, t1 = proc_cpu_s(console.process.pid), time.monotonic()
        rss = proc_rss_mib(console.process.pid)
        stop.set()
        feed.close()
        direct.stop()
        client.close()

        print(f"console_bench: {args.activations} WAIT activations in {activations_s:.1f} s; "
              f"{len(direct_ms)} events on WatchEvents, {len(sse_ms)} of them on the console's "
              f"feed")
        print("| path | events | median (ms) | p99 (ms) | max (ms) |")
        print("| --- | ---: | ---: | ---: | ---: |")
        for name, values in (("coordinator WatchEvents, gRPC (floor)", direct_ms),
                             ("console /api/events, SSE", sse_ms)):
            if values:
                print(f"| {name} | {len(values)} | {statistics.median(values):.2f} | "
                      f"{percentile(values, 0.99):.2f} | {max(values):.2f} |")
        print(f"console idle, simulator publishing: "
              f"{(cpu1 - cpu0) / (t1 - t0) * 100:.2f} % of a core over {t1 - t0:.1f} s, "
              f"RSS {rss:.1f} MiB")
        if missing or len(direct_ms) < expected:
            print(f"console_bench: {missing} events missing on the console's feed, "
                  f"{expected - len(direct_ms)} on WatchEvents")
            return 1
        return 0
    finally:
        for process in reversed(processes):
            process.stop()
        cg.shutil.rmtree(run_dir, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
