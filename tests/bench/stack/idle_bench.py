"""Idle cost of the whole local stack: the launcher (deploy/local/launch.py,
without --demo) starts every built process for one robot (or --vehicles),
the vehicles stay landed, and the CPU time and memory of each process are
read from /proc over a window of wall time, once per time scale.

    python3 tests/bench/stack/idle_bench.py --build-dir build \
        --time-scales 1,10 --window-s 20 --runs 3

prints one table per time scale: per process the CPU as % of one core
(median over the runs, and each run), the RSS, and the total; the channel
broker's delivered samples per second from its /metrics. Extra launcher
arguments go after `--` (e.g. `-- --clock-publish every-tick` for the
simulator's clock as it was, a sample every 5 ms of simulated time).
--smoke runs one short window at 1x and checks that the table is complete.
"""

import argparse
import json
import os
import re
import signal
import statistics
import subprocess
import sys
import tempfile
import time
import urllib.request

REPO = os.path.abspath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", ".."))
LAUNCHER = os.path.join(REPO, "deploy", "local", "launch.py")
CLOCK_TICKS = os.sysconf("SC_CLK_TCK")
PAGE_KIB = os.sysconf("SC_PAGE_SIZE") // 1024


def cpu_seconds(pid):
    """utime + stime of `pid` (children excluded), None once it is gone."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return (int(fields[11]) + int(fields[12])) / CLOCK_TICKS


def rss_kib(pid):
    try:
        with open(f"/proc/{pid}/statm") as f:
            return int(f.read().split()[1]) * PAGE_KIB
    except OSError:
        return 0


def samples_out(metrics_address):
    """Samples the broker handed out, summed over topics: writes to subscribers' streams
    (behaviorlib_channel_samples_out_total) plus writes into the shared-memory rings that the
    subscribers on its host read (behaviorlib_channel_shm_samples_total, one per sample)."""
    try:
        with urllib.request.urlopen(f"http://{metrics_address}/metrics", timeout=2) as r:
            text = r.read().decode()
    except OSError:
        return None
    return sum(float(m.group(1)) for m in
               re.finditer(r"^behaviorlib_channel_(?:samples_out|shm_samples)_total\{[^}]*\} (\S+)$",
                           text, re.M))


class Stack:
    """The launcher serving a stack until stopped."""

    def __init__(self, build_dir, time_scale, extra):
        self.run_dir = tempfile.mkdtemp(prefix="behaviorlib-idle-")
        argv = [sys.executable, LAUNCHER, "--build-dir", build_dir, "--run-dir", self.run_dir,
                "--time-scale", str(time_scale), *extra]
        self.log = open(os.path.join(self.run_dir, "launcher.log"), "w")
        self.process = subprocess.Popen(argv, stdout=self.log, stderr=subprocess.STDOUT,
                                        start_new_session=True)

    def wait_serving(self, timeout_s=120):
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise RuntimeError(f"the launcher exited with {self.process.returncode}; "
                                   f"see {self.log.name}")
            with open(self.log.name) as f:
                if "Ctrl-C stops everything." in f.read():
                    return
            time.sleep(0.2)
        raise RuntimeError(f"the stack was not serving within {timeout_s} s")

    def pids(self):
        with open(os.path.join(self.run_dir, "pids.json")) as f:
            return json.load(f)

    def metrics_address(self, name):
        path = os.path.join(self.run_dir, "ports", name + ".ports")
        with open(path) as f:
            ports = dict(line.strip().split("=", 1) for line in f if "=" in line)
        return f"127.0.0.1:{ports['metrics_port']}" if "metrics_port" in ports else ""

    def stop(self):
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGINT)
            try:
                self.process.wait(timeout=60)
            except subprocess.TimeoutExpired:
                os.killpg(self.process.pid, signal.SIGKILL)
                self.process.wait()
        self.log.close()


def measure(build_dir, time_scale, window_s, settle_s, extra):
    """One run: {process: (cpu %, rss KiB)} and the broker's deliveries/s."""
    stack = Stack(build_dir, time_scale, extra)
    try:
        stack.wait_serving()
        time.sleep(settle_s)
        pids = stack.pids()
        broker = stack.metrics_address("channel_broker")
        before = {name: cpu_seconds(pid) for name, pid in pids.items()}
        out_before = samples_out(broker)
        t0 = time.monotonic()
        time.sleep(window_s)
        elapsed = time.monotonic() - t0
        after = {name: cpu_seconds(pid) for name, pid in pids.items()}
        out_after = samples_out(broker)
        rows = {}
        for name, pid in pids.items():
            if before[name] is None or after[name] is None:
                raise RuntimeError(f"{name} exited during the window")
            rows[name] = (100.0 * (after[name] - before[name]) / elapsed, rss_kib(pid))
        rate = ((out_after - out_before) / elapsed
                if out_before is not None and out_after is not None else float("nan"))
        return rows, rate
    finally:
        stack.stop()


def window_arguments(description):
    """The options of an idle measurement (also container_idle_bench's)."""
    parser = argparse.ArgumentParser(description=description,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--build-dir", default=os.path.join(REPO, "build"))
    parser.add_argument("--time-scales", default="1,10")
    parser.add_argument("--window-s", type=float, default=20.0)
    parser.add_argument("--settle-s", type=float, default=5.0)
    parser.add_argument("--runs", type=int, default=3)
    return parser


def main():
    parser = window_arguments(__doc__)
    parser.add_argument("--smoke", action="store_true")
    parser.add_argument("extra", nargs="*", help="launcher arguments (after --)")
    args = parser.parse_args()
    if args.smoke:
        args.time_scales, args.window_s, args.settle_s, args.runs = "1", 2.0, 1.0, 1
    build_dir = os.path.abspath(args.build_dir)
    print(f"# idle_bench: {os.cpu_count()} CPUs, "
          f"window {args.window_s} s, {args.runs} run(s), launcher args {args.extra or '-'}")
    for scale in [float(s) for s in args.time_scales.split(",") if s]:
        runs = [measure(build_dir, scale, args.window_s, args.settle_s, args.extra)
                for _ in range(args.runs)]
        names = list(runs[0][0])
        print(f"\n## time scale {scale:g}x\n")
        print("| process | CPU % of a core (median) | runs | RSS MiB |")
        print("|---|---:|---|---:|")
        totals = [sum(cpu for cpu, _ in rows.values()) for rows, _ in runs]
        for name in names:
            cpus = [rows[name][0] for rows, _ in runs if name in rows]
            rss = statistics.median(rows[name][1] for rows, _ in runs if name in rows) / 1024
            print(f"| {name} | {statistics.median(cpus):.2f} | "
                  f"{', '.join(f'{c:.2f}' for c in cpus)} | {rss:.1f} |")
        rss_total = statistics.median(sum(r for _, r in rows.values()) for rows, _ in runs) / 1024
        print(f"| **total** | **{statistics.median(totals):.2f}** | "
              f"{', '.join(f'{t:.2f}' for t in totals)} | {rss_total:.1f} |")
        rates = [rate for _, rate in runs]
        print(f"\nbroker deliveries (stream writes + ring writes): "
              f"{statistics.median(rates):.0f} samples/s "
              f"(runs: {', '.join(f'{r:.0f}' for r in rates)})")
        if args.smoke:
            missing = {"channel_broker", "simulator", "coordinator"} - set(names)
            if missing or len(names) < 4:
                print(f"FAILED: the table lacks {sorted(missing)} or behavior systems")
                return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
