"""What a behavior written in Python costs (issue 40 goal 5), each figure beside the C++ one
measured in the same run:

    BEHAVIORLIB_BUILD_DIR=build build/venv/bin/python tests/bench/stack/python_system_bench.py

1. The library's overhead per tick: the engine's tick (the four checks, the time-out, then
   on_execute) of an active behavior whose functions do nothing, called directly while its
   worker sleeps on a fake clock, as build/tests/bench/tick_bench does for the C++ engine
   (BM_TickNoWorkNoObserver, run here too). Per-tick median and p99 over 20000 ticks.
2. Activation latency: BehaviorSystem.ActivateBehavior of a WAIT-like behavior through the
   generic service on loopback, from the call to its answer (the activation decided: the
   situation checked, on_activate run), then its Deactivate; 200 each, on a Python system
   hosting a WAIT (TEST_WAIT's parameters) and on the C++ basic_quadrotor_behaviors (WAIT).
3. An idle system: CPU (percent of a core) and RSS over a window, with nothing active, both
   registered with a coordinator and sending heartbeats.
"""

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time

import grpc
from google.protobuf import struct_pb2

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.abspath(os.path.join(HERE, "..", "..", ".."))
sys.path.insert(0, os.path.join(REPO, "clients", "python", "tests"))

from behaviorlib.system import (Behavior, BehaviorContext, EventLog, ExecutionManager,  # noqa
                                FakeClock)
from behaviorlib.v1 import behavior_pb2, behavior_pb2_grpc  # noqa: E402
from deterministic_wait_system import TestWaitParameters  # noqa: E402


# The Python system measured: TEST_WAIT's parameters, and a WAIT's goal.
SYSTEM_SCRIPT = """
import sys
sys.path.insert(0, {tests!r})
from behaviorlib.system import Behavior, Verdict, run_system, seconds
from deterministic_wait_system import TestWaitParameters


class Wait(Behavior):
    Parameters = TestWaitParameters

    def check_goal(self):
        if self.active_time() >= seconds(self.parameters.duration_s):
            return Verdict.finish("waited")
        return Verdict.keep_going()


raise SystemExit(run_system([Wait()], system="python_bench"))
"""


def percentile(values, q):
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(round(q * (len(ordered) - 1))))]


class NoWork(Behavior):
    """Active until deactivated; every function does nothing."""
    Parameters = TestWaitParameters


def python_tick_ns(ticks):
    clock = FakeClock()
    engine = ExecutionManager(NoWork())
    engine.start(BehaviorContext(clock=clock, events=EventLog("drone1", "bench"),
                                 robot_id="drone1"))
    try:
        engine.activate_and_wait(TestWaitParameters(duration_s=3600))
        times = []
        for _ in range(ticks):
            begin = time.perf_counter_ns()
            engine._execute()
            times.append(time.perf_counter_ns() - begin)
        return times
    finally:
        engine.stop()


def cpp_tick_ns(build_dir):
    out = subprocess.run([os.path.join(build_dir, "tests", "bench", "tick_bench"),
                          "--benchmark_filter=BM_TickNoWorkNoObserver$",
                          "--benchmark_repetitions=5"], capture_output=True, text=True,
                         check=True).stdout
    for line in out.splitlines():
        if line.startswith("BM_TickNoWorkNoObserver_median"):
            return float(line.split()[1])
    raise RuntimeError(f"no median in tick_bench's output:\n{out}")


def start(argv, directory, name):
    port_file = os.path.join(directory, name + ".ports")
    process = subprocess.Popen(argv + ["--port-file", port_file], stdout=subprocess.DEVNULL,
                               stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        if os.path.exists(port_file):
            with open(port_file) as f:
                fields = dict(line.strip().split("=") for line in f if "=" in line)
            if "grpc_port" in fields:
                return process, f"127.0.0.1:{fields['grpc_port']}"
        time.sleep(0.05)
    process.kill()
    raise RuntimeError(f"{name} did not start")


def activation_ns(address, behavior, count):
    stub = behavior_pb2_grpc.BehaviorSystemStub(grpc.insecure_channel(address))
    parameters = struct_pb2.Struct()
    parameters.update({"duration_s": 3600})
    times = []
    for _ in range(count):
        begin = time.perf_counter_ns()
        reply = stub.ActivateBehavior(behavior_pb2.ActivateBehaviorRequest(
            behavior=behavior, parameters=parameters), timeout=10)
        times.append(time.perf_counter_ns() - begin)
        stub.DeactivateBehavior(behavior_pb2.DeactivateBehaviorRequest(
            behavior=behavior, activation_id=reply.activation_id), timeout=10)
    return times


def cpu_s(pid):
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rpartition(")")[2].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def rss_mib(pid):
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return 0.0


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ticks", type=int, default=20000)
    parser.add_argument("--activations", type=int, default=200)
    parser.add_argument("--window-s", type=float, default=20.0)
    args = parser.parse_args()
    build_dir = os.path.abspath(os.environ.get("BEHAVIORLIB_BUILD_DIR",
                                               os.path.join(REPO, "build")))
    ticks = python_tick_ns(args.ticks)
    cpp = cpp_tick_ns(build_dir)
    print("| tick of a behavior that does nothing | median µs | p99 µs |")
    print("|---|---:|---:|")
    print(f"| Python engine (`ExecutionManager._execute`) | {statistics.median(ticks) / 1e3:.1f} "
          f"| {percentile(ticks, 0.99) / 1e3:.1f} |")
    print(f"| C++ engine (tick_bench BM_TickNoWorkNoObserver, median of 5) | {cpp / 1e3:.2f} "
          "| |")
    with tempfile.TemporaryDirectory(prefix="behaviorlib-python-bench-") as directory:
        processes = []
        try:
            coordinator, coordinator_address = start(
                [os.path.join(build_dir, "bin", "coordinator"), "--listen", "127.0.0.1:0",
                 "--metrics-listen", "127.0.0.1:0"], directory, "coordinator")
            processes.append(coordinator)
            common = ["--robot-id", "drone1", "--listen", "127.0.0.1:0", "--metrics-listen",
                      "127.0.0.1:0", "--coordinator", coordinator_address]
            script = os.path.join(directory, "bench_system.py")
            with open(script, "w") as f:
                f.write(SYSTEM_SCRIPT.format(tests=os.path.join(REPO, "clients", "python",
                                                                "tests")))
            python, python_address = start([sys.executable, script, *common], directory,
                                           "python")
            processes.append(python)
            cpp_system, cpp_address = start(
                [os.path.join(build_dir, "bin", "basic_quadrotor_behaviors"), *common],
                directory, "cpp")
            processes.append(cpp_system)
            time.sleep(2)  # registered, heartbeats going
            rows = []
            for name, address, behavior in (("Python (TEST_WAIT)", python_address, "TEST_WAIT"),
                                            ("C++ (WAIT)", cpp_address, "WAIT")):
                activation_ns(address, behavior, 10)  # warm
                times = activation_ns(address, behavior, args.activations)
                rows.append((name, statistics.median(times) / 1e3, percentile(times, 0.99) / 1e3))
            print()
            print("| ActivateBehavior (generic service, loopback) | median µs | p99 µs |")
            print("|---|---:|---:|")
            for name, median, p99 in rows:
                print(f"| {name} | {median:.0f} | {p99:.0f} |")
            time.sleep(2)
            before = {p.pid: cpu_s(p.pid) for p in (python, cpp_system)}
            begin = time.monotonic()
            time.sleep(args.window_s)
            elapsed = time.monotonic() - begin
            print()
            print(f"| idle system over {args.window_s:.0f} s | CPU % of a core | RSS MiB |")
            print("|---|---:|---:|")
            for name, process in (("Python", python), ("C++ basic_quadrotor_behaviors",
                                                       cpp_system)):
                cpu = 100 * (cpu_s(process.pid) - before[process.pid]) / elapsed
                print(f"| {name} | {cpu:.2f} | {rss_mib(process.pid):.1f} |")
            # Active: a WAIT ticking at its rate (100 Hz for both), the whole process's CPU
            # per tick (the worker's wake-ups and waits included).
            stubs = {}
            for name, address, behavior, process in (
                    ("Python", python_address, "TEST_WAIT", python),
                    ("C++ basic_quadrotor_behaviors", cpp_address, "WAIT", cpp_system)):
                stub = behavior_pb2_grpc.BehaviorSystemStub(grpc.insecure_channel(address))
                parameters = struct_pb2.Struct()
                parameters.update({"duration_s": 3600})
                stub.ActivateBehavior(behavior_pb2.ActivateBehaviorRequest(
                    behavior=behavior, parameters=parameters), timeout=10)
                stubs[name] = (stub, behavior, process)
            time.sleep(1)
            before = {p.pid: cpu_s(p.pid) for p in (python, cpp_system)}
            begin = time.monotonic()
            time.sleep(args.window_s)
            elapsed = time.monotonic() - begin
            print()
            print(f"| a WAIT active at 100 Hz over {args.window_s:.0f} s | CPU % of a core | "
                  "CPU µs per tick |")
            print("|---|---:|---:|")
            for name, (stub, behavior, process) in stubs.items():
                spent = cpu_s(process.pid) - before[process.pid]
                print(f"| {name} | {100 * spent / elapsed:.2f} | "
                      f"{1e6 * spent / (100 * elapsed):.0f} |")
        finally:
            for process in processes:
                process.kill()
                process.wait()


if __name__ == "__main__":
    main()
