"""Memory soak of the main job: ONE stack started as the launcher starts it by
default (deploy/local/launch.py serving, not --demo: every behavior system
that is built, the console, --time-scale 2, no flight recorder), the demo
mission (deploy/missions/demo.yaml) flown through the coordinator back to
back, with Simulator.Reset and a new seed every --reset-every missions (and
after a mission that did not succeed), as deploy/local/campaign.py does with
--missions-per-stack. After every mission, every process of the stack (by
name, the launcher too) is read from /proc: VmRSS, VmHWM, RssAnon, open file
descriptors (/proc/PID/fd), threads and CPU time; and every server process's
/metrics for its allocator's count (behaviorlib_process_heap_in_use_bytes and
_free_bytes), which tells a growing heap from a fragmented one.

    python3 tests/bench/stack/soak_bench.py --build-dir build --missions 0 \
        --duration-s 7200 --plot soak.png --check        # the 2-hour soak
    python3 tests/bench/stack/soak_bench.py --missions 126 --reset-every 20
    python3 tests/bench/stack/soak_bench.py --smoke      # ctest's soak_bench_smoke

It stops after --missions N or once --duration-s S of wall time have passed,
whichever comes first (a mission started before the time is up is flown to
its end). Extra launcher arguments go after `--` (e.g. `-- --no-console`,
`-- --time-scale max`).

Writes into --out DIR (default a new directory under /tmp, printed):
  samples.csv    one row per mission per process: the mission's number (0 is
                 the stack after start-up, before the first mission), wall
                 seconds since then, the seed of a Reset before it, its
                 outcome and wall duration, then the process's pid, VmRSS,
                 VmHWM, RssAnon (MiB), fds, threads, CPU seconds, heap in
                 use and heap held free (MiB; empty for the launcher);
  summary.json   the settings, the machine, every mission, and per process
                 the figures of the table below;
  stack/         the launcher's output (launcher.log) and every process's log.

Prints the machine (CPU model, cores), the exact command, and a markdown
table ready for docs/benchmarks.md: per process the RSS after the warm-up
(mission W = --warmup-missions, default 10 % of the run, at most 10), at the
middle and at the end of the run, the growth over the second half (MiB) and
its least-squares slope against wall time (MiB/h), the heap in use after the
warm-up and at the end, and the heap held free at the end (MiB), the peak (VmHWM), fds and
threads min-max, and whether it plateaued: a second-half slope below
--plateau-mib-per-h (default 2 MiB/h; "-" with fewer than 3 samples in the
second half, and mind that over a short run a single 1 MiB step is a steep
slope). Then the missions: succeeded / total, wall duration min / median /
max and whether it trends (second half's median against the first's).
--plot FILE.png draws each process's RSS over the missions, the Resets
marked; it needs matplotlib and is skipped, with a note, when matplotlib is
not installed.

Exit code 0; 1 when a mission did not succeed, a process exited or was
restarted (its series ends there and so does the soak), or with --check a
process did not plateau; 2 for bad arguments; 3 when the tooling failed (the
stack did not start, a call to it failed); 128 + the signal's number when
stopped by a signal. The stack is stopped in every case.
"""

import argparse
import csv
import json
import os
import re
import shlex
import signal
import statistics
import sys
import tempfile
import time

REPO = os.path.abspath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", ".."))
sys.path.insert(0, os.path.join(REPO, "deploy", "local"))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import campaign  # noqa: E402
import demo  # noqa: E402
import idle_bench  # noqa: E402
import main_job_bench  # noqa: E402
import rpc  # noqa: E402
from stack import read_ports  # noqa: E402

SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
# Options the soak sets itself (or cannot follow: one robot, one stack, serving).
OWN_LAUNCHER_OPTIONS = ("--demo", "--run-dir", "--build-dir", "--robot-id", "--vehicles",
                        "--seed", "--mission")
LAUNCHER_NAME = "launcher"
MIB = 1024.0
FIELDS = ("mission", "elapsed_s", "reset_seed", "mission_state", "mission_wall_s", "process",
          "pid", "rss_mib", "hwm_mib", "anon_mib", "fds", "threads", "cpu_s", "heap_mib",
          "heap_free_mib")
HEAP_METRICS = {"behaviorlib_process_heap_in_use_bytes": "heap_kib",
                "behaviorlib_process_heap_free_bytes": "heap_free_kib"}


def _on_signal(signum, _frame):
    raise campaign.Interrupted(signum)


class SoakStack(campaign.LaunchedStack):
    """The campaign's stack (its start, Reset, event stream and stop), started
    as the launcher serves by default instead of the campaign's deterministic
    mode without the console."""

    def __init__(self, args):
        super().__init__(args, 1)
        self.run_dir = os.path.join(args.out, "stack")

    def launcher_argv(self, seed):
        return [sys.executable, campaign.LAUNCHER, "--build-dir", self.args.build_dir,
                "--run-dir", self.run_dir, "--seed", str(seed), "--robot-id", self.args.robot,
                *self.args.launcher_args]

    def processes(self):
        """{name: pid} of every process of the stack, the launcher last."""
        return {**self.pids, LAUNCHER_NAME: self.process.pid}

    def heap(self, name):
        """{heap_kib, heap_free_kib} from `name`'s /metrics; {} when it serves
        none (the launcher, the console) and None when it does not answer."""
        try:
            ports = read_ports(os.path.join(self.run_dir, "ports", name + ".ports"))
        except OSError:
            return {}
        if "metrics_port" not in ports:
            return {}
        try:
            samples = demo.scrape(f"127.0.0.1:{ports['metrics_port']}")
        except (OSError, ValueError):
            return None
        return {HEAP_METRICS[metric]: value / 1024.0 for metric, _labels, value in samples
                if metric in HEAP_METRICS}


def proc_sample(pid):
    """What /proc says of `pid` (memory in KiB), or None once it is gone."""
    try:
        with open(f"/proc/{pid}/status") as f:
            status = {key: value.split() for key, _, value in
                      (line.partition(":") for line in f)}
        fds = len(os.listdir(f"/proc/{pid}/fd"))
    except OSError:
        return None
    cpu_s = idle_bench.cpu_seconds(pid)
    if cpu_s is None:
        return None
    return {"rss_kib": int(status["VmRSS"][0]), "hwm_kib": int(status["VmHWM"][0]),
            "anon_kib": int(status["RssAnon"][0]), "threads": int(status["Threads"][0]),
            "fds": fds, "cpu_s": cpu_s}


def fly_demo(args, stack, number):
    """One mission on `stack`: {state, failed (step: cause, or ""), wall_s, sim_s,
    steps: [[step, cause, active simulated s]]}."""
    first_event = stack.events.mark()
    mission_id = f"soak-{args.stamp}-{number}"
    started = time.monotonic()
    status = demo.run_mission(stack.coordinator, args.mission, args.robot, mission_id,
                              args.mission_timeout_s, lambda text: None, lambda status: None)
    wall_s = time.monotonic() - started
    stack.events.wait_settled(5.0)
    events = stack.events.since(first_event)
    steps = campaign.step_rows(status, events, args.recurrent)
    state = status.get("state", "?")
    failed = campaign.failing_step({"state": state, "steps": steps})
    times = [demo.timestamp_s(e.get("time")) for e in events]
    times = [t for t in times if t is not None]
    ends = [s["end_s"] for s in steps if s["kind"] == "step" and s["end_s"] is not None]
    return {"mission": number, "state": state.replace("MISSION_STATE_", ""),
            "failed": f"{campaign.row_label(failed)}: {failed['cause']}" if failed else "",
            "wall_s": round(wall_s, 3),
            "sim_s": round(max(ends) - min(times), 3) if ends and times else None,
            "steps": [[campaign.row_label(s), s["cause"], s["duration_s"]] for s in steps]}


def unclean_stops(log_path):
    """The processes whose exit code at the launcher's stop was not 0 (its
    "== stopping ==" lines in launcher.log)."""
    try:
        with open(log_path, errors="replace") as f:
            text = f.read().partition("\n== stopping ==\n")[2]
    except OSError:
        return []
    return [f"{name} {how} with code {code} at the stop" for name, how, code in
            re.findall(r"(?m)^  (\S+) +(exited|had already exited) with code (-?\d+)", text)
            if code != "0"]


def slope_per_h(points):
    """Least-squares slope of [(elapsed s, MiB)] in MiB per hour; None
    with fewer than 3 points."""
    if len(points) < 3 or len({t for t, _ in points}) < 2:
        return None
    fit = statistics.linear_regression([t / 3600.0 for t, _ in points], [v for _, v in points])
    return fit.slope


def marks(n, warmup):
    """(warm-up mission, middle mission, first mission of the second half)."""
    warm = min(warmup if warmup is not None else max(1, min(10, n // 10)), n)
    middle = max(warm, (n + 1) // 2)
    return warm, middle, max(1, (n + 1) // 2)


def summarize_process(rows, n, args):
    """The table's figures of one process from its samples [(mission, elapsed s, sample)]."""
    warm, middle, half = marks(n, args.warmup_missions)
    by_mission = {m: s for m, _, s in rows}

    def rss_at(mission, key="rss_kib"):
        sample = by_mission.get(mission)
        return round(sample[key] / MIB, 1) if sample and key in sample else None

    second = [(t, s["rss_kib"] / MIB) for m, t, s in rows if m >= half]
    slope = slope_per_h(second)
    growth = round(second[-1][1] - second[0][1], 2) if len(second) >= 2 else None
    samples = [s for _, _, s in rows]
    return {"rss_start_mib": rss_at(warm), "rss_mid_mib": rss_at(middle),
            "rss_end_mib": rss_at(n), "rss_after_startup_mib": rss_at(0),
            "second_half_growth_mib": growth,
            "heap_start_mib": rss_at(warm, "heap_kib"), "heap_end_mib": rss_at(n, "heap_kib"),
            "heap_free_end_mib": rss_at(n, "heap_free_kib"),
            "second_half_slope_mib_per_h": None if slope is None else round(slope, 2),
            "hwm_mib": round(max(s["hwm_kib"] for s in samples) / MIB, 1),
            "fds": [min(s["fds"] for s in samples), max(s["fds"] for s in samples)],
            "threads": [min(s["threads"] for s in samples), max(s["threads"] for s in samples)],
            "cpu_s": round(samples[-1]["cpu_s"] - samples[0]["cpu_s"], 2),
            "plateaued": None if slope is None else slope < args.plateau_mib_per_h}


def summarize_missions(missions):
    """Succeeded / total, wall durations and their trend."""
    walls = [m["wall_s"] for m in missions]
    summary = {"succeeded": sum(m["state"] == "SUCCEEDED" for m in missions),
               "total": len(missions)}
    if not walls:
        return summary
    summary.update(wall_min_s=min(walls), wall_median_s=round(statistics.median(walls), 2),
                   wall_max_s=max(walls), trend="-")
    sims = [m["sim_s"] for m in missions if m["sim_s"] is not None]
    summary["sim_median_s"] = round(statistics.median(sims), 2) if sims else None
    if len(walls) >= 4:
        half = len(walls) // 2
        first, second = statistics.median(walls[:half]), statistics.median(walls[half:])
        change = (second - first) / first if first else 0.0
        fit = statistics.linear_regression(range(len(walls)), walls)
        summary.update(first_half_median_s=round(first, 2), second_half_median_s=round(second, 2),
                       slope_s_per_100_missions=round(100 * fit.slope, 3),
                       trend="rising" if change > 0.1 else "falling" if change < -0.1
                       else "flat")
    return summary


def fmt(value, digits=1):
    return "-" if value is None else f"{value:.{digits}f}"


def print_table(summary):
    """The markdown table for docs/benchmarks.md."""
    warm, middle, _half = summary["marks"]
    n = summary["missions_done"]
    print(f"\n| process | RSS MiB after mission {warm} | mission {middle} | mission {n} "
          f"| 2nd half growth MiB | 2nd half slope MiB/h | heap in use MiB | heap free MiB "
          f"| VmHWM MiB | fds | threads | plateau? |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|")
    for name, p in summary["processes"].items():
        plateau = {None: "-", True: "yes", False: "**no**"}[p["plateaued"]]
        print(f"| {name} | {fmt(p['rss_start_mib'])} | {fmt(p['rss_mid_mib'])} "
              f"| {fmt(p['rss_end_mib'])} | {fmt(p['second_half_growth_mib'])} "
              f"| {fmt(p['second_half_slope_mib_per_h'])} "
              f"| {fmt(p['heap_start_mib'])} → {fmt(p['heap_end_mib'])} "
              f"| {fmt(p['heap_free_end_mib'])} | {fmt(p['hwm_mib'])} "
              f"| {p['fds'][0]}–{p['fds'][1]} | {p['threads'][0]}–{p['threads'][1]} "
              f"| {plateau} |")
    totals = [sum(p[key] or 0.0 for p in summary["processes"].values())
              for key in ("rss_start_mib", "rss_mid_mib", "rss_end_mib")]
    print(f"| **total** | {totals[0]:.1f} | {totals[1]:.1f} | {totals[2]:.1f} | | | | | | | "
          f"| |")
    m = summary["mission_summary"]
    print(f"\nmissions: {m['succeeded']} of {m['total']} succeeded", end="")
    if m.get("wall_median_s") is not None:
        print(f"; wall duration min / median / max {m['wall_min_s']:.1f} / "
              f"{m['wall_median_s']:.1f} / {m['wall_max_s']:.1f} s (simulated median "
              f"{fmt(m['sim_median_s'])} s); trend: {m['trend']}", end="")
        if "first_half_median_s" in m:
            print(f" (median {m['first_half_median_s']:.1f} s in the first half, "
                  f"{m['second_half_median_s']:.1f} s in the second; least-squares "
                  f"{m['slope_s_per_100_missions']:+.2f} s per 100 missions)", end="")
    print(f"\n{summary['resets']} Simulator.Reset; {summary['wall_s'] / 60:.1f} min of wall time; "
          f"plateau: second-half slope < {summary['plateau_mib_per_h']:g} MiB/h")


def plot(path, series, resets):
    """RSS per process over the missions; False when matplotlib is missing."""
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        import matplotlib.ticker
    except ImportError:
        return False
    figure, axes = plt.subplots(figsize=(10, 6))
    axes.set_prop_cycle(color=plt.get_cmap("tab20").colors)
    for name, rows in series.items():
        axes.plot([m for m, _, _ in rows], [s["rss_kib"] / MIB for _, _, s in rows], label=name)
    for mission in resets:
        axes.axvline(mission - 0.5, color="grey", linewidth=0.5, linestyle=":")
    axes.xaxis.set_major_locator(matplotlib.ticker.MaxNLocator(integer=True))
    axes.set_xlabel("missions flown (dotted: Simulator.Reset before the next)")
    axes.set_ylabel("VmRSS (MiB)")
    axes.set_title("soak_bench: RSS per process after each demo mission")
    axes.legend(fontsize="small", loc="center left", bbox_to_anchor=(1.0, 0.5))
    figure.tight_layout()
    figure.savefig(path, dpi=100)
    plt.close(figure)
    return True


def parse_args():
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--build-dir", default=os.path.join(REPO, "build"))
    parser.add_argument("--mission", default=os.path.join(REPO, "deploy", "missions", "demo.yaml"))
    parser.add_argument("--missions", type=int, default=126, metavar="N",
                        help="fly at most N missions (0: no limit; default %(default)s)")
    parser.add_argument("--duration-s", type=float, default=0.0, metavar="S",
                        help="start no mission after S wall seconds (0: no limit; default)")
    parser.add_argument("--reset-every", type=int, default=20, metavar="K",
                        help="Simulator.Reset (seed --seed + 1, + 2, ...) after every K missions "
                             "(0: never, but after a failure; default %(default)s)")
    parser.add_argument("--seed", type=int, default=1,
                        help="the launcher's --seed (default %(default)s)")
    parser.add_argument("--warmup-missions", type=int, default=None, metavar="W",
                        help="the table's first RSS column is after mission W (default: 10 %% "
                             "of the missions flown, at least 1, at most 10)")
    parser.add_argument("--plateau-mib-per-h", type=float, default=2.0,
                        help="plateaued: a second-half RSS slope below this (default "
                             "%(default)s MiB/h)")
    parser.add_argument("--check", action="store_true",
                        help="exit 1 when a process did not plateau")
    parser.add_argument("--mission-timeout-s", type=float, default=120.0,
                        help="wall seconds after which a mission is aborted (default "
                             "%(default)s)")
    parser.add_argument("--out", default="", help="output directory (default: a new one in /tmp)")
    parser.add_argument("--plot", default="", metavar="FILE.png",
                        help="RSS per process over the missions (needs matplotlib; skipped when "
                             "it is not installed)")
    parser.add_argument("--smoke", action="store_true",
                        help="2 missions, a Reset between them; fails unless both succeed and "
                             "every process was sampled after each, its heap included")
    parser.add_argument("launcher_args", nargs="*", metavar="-- LAUNCHER_ARG",
                        help="extra launch.py arguments after --")
    args = parser.parse_args()
    if args.smoke:
        args.missions, args.duration_s, args.reset_every = 2, 0.0, 1
    if args.missions < 0 or args.duration_s < 0 or args.reset_every < 0:
        parser.error("--missions, --duration-s and --reset-every must not be negative")
    if not args.missions and not args.duration_s:
        parser.error("give --missions or --duration-s a limit")
    if args.warmup_missions is not None and args.warmup_missions < 1:
        parser.error("--warmup-missions must be at least 1")
    for arg in args.launcher_args:
        if arg.split("=", 1)[0] in OWN_LAUNCHER_OPTIONS:
            parser.error(f"launcher argument {arg}: the soak sets it itself")
    args.build_dir = os.path.abspath(args.build_dir)
    args.mission = os.path.abspath(args.mission)
    _name, robot, _steps, args.recurrent = campaign.mission_outline(args.mission)
    args.robot = robot or "drone1"
    args.stamp = f"{time.strftime('%Y%m%d-%H%M%S')}-{os.getpid()}"
    args.out = os.path.abspath(args.out) if args.out else tempfile.mkdtemp(
        prefix="behaviorlib-soak-")
    os.makedirs(args.out, exist_ok=True)
    return args


def main():
    args = parse_args()
    command = " ".join(shlex.quote(a) for a in
                       ["python3", os.path.relpath(os.path.abspath(sys.argv[0]), REPO),
                        *sys.argv[1:]])
    print(f"# soak_bench: {command}\n# machine: {main_job_bench.machine()}\n# out: {args.out}",
          flush=True)
    others = main_job_bench.other_launchers()
    if others:
        print(f"WARNING: other launchers run (pids {', '.join(map(str, others))}): "
              f"the figures are not comparable", flush=True)
    for signum in SIGNALS:
        signal.signal(signum, _on_signal)

    stack = SoakStack(args)
    series = {}  # process -> [(mission, elapsed s, sample)]
    heap_readers = set()  # the processes that serve /metrics
    heap_unread = set()  # those whose /metrics did not answer once
    missions, resets, problems = [], [], []
    status, interrupted, mission_row = 0, "", {}
    samples_file = open(os.path.join(args.out, "samples.csv"), "w", newline="")
    writer = csv.DictWriter(samples_file, FIELDS)
    writer.writeheader()

    def sample(number, elapsed_s):
        for name, pid in stack.processes().items():
            taken = proc_sample(pid)
            if taken is None:
                problems.append(f"{name} (pid {pid}) was gone after mission {number}")
                continue
            if name != LAUNCHER_NAME:
                heap = stack.heap(name)
                if heap is None:
                    heap_unread.add(name)
                elif heap:
                    heap_readers.add(name)
                    taken.update(heap)
            series.setdefault(name, []).append((number, elapsed_s, taken))
            writer.writerow({**mission_row, "mission": number, "elapsed_s": round(elapsed_s, 2),
                             "process": name, "pid": pid,
                             "rss_mib": round(taken["rss_kib"] / MIB, 2),
                             "hwm_mib": round(taken["hwm_kib"] / MIB, 2),
                             "anon_mib": round(taken["anon_kib"] / MIB, 2),
                             "fds": taken["fds"], "threads": taken["threads"],
                             "cpu_s": round(taken["cpu_s"], 2),
                             **{key[:-4] + "_mib": round(taken[key] / MIB, 2)
                                for key in HEAP_METRICS.values() if key in taken}})
        samples_file.flush()

    started = time.monotonic()
    try:
        stack.start(args.seed, timeout_s=120.0)
        started = time.monotonic()
        sample(0, 0.0)
        last_failed = False
        while ((not args.missions or len(missions) < args.missions)
               and (not args.duration_s or time.monotonic() - started < args.duration_s)):
            number = len(missions) + 1
            reset_seed = ""
            if missions and (last_failed or (args.reset_every
                                             and len(missions) % args.reset_every == 0)):
                reset_seed = args.seed + len(resets) + 1
                stack.reset(reset_seed)
                resets.append(number)
            mission = fly_demo(args, stack, number)
            mission.update(reset_seed=reset_seed,
                           elapsed_s=round(time.monotonic() - started, 1))
            missions.append(mission)
            last_failed = mission["state"] != "SUCCEEDED"
            mission_row = {"reset_seed": reset_seed, "mission_state": mission["state"],
                           "mission_wall_s": mission["wall_s"]}
            sample(number, time.monotonic() - started)
            rss = sum(rows[-1][2]["rss_kib"] for rows in series.values()) / MIB
            print(f"[{number:>4}] {time.monotonic() - started:7.0f} s "
                  f"{'reset ' + str(reset_seed) + ', ' if reset_seed else ''}"
                  f"{mission['state']}{' at ' + mission['failed'] if mission['failed'] else ''} "
                  f"in {mission['wall_s']:.1f} s; RSS of the stack {rss:.1f} MiB", flush=True)
            if not stack.intact() or problems:
                problems.append("a process of the stack exited or was restarted "
                                f"(see {stack.log_path}): the soak ends here")
                break
    except campaign.Interrupted as signal_received:
        interrupted = str(signal_received)
        print(f"\n{interrupted}: stopping", flush=True)
        status = 128 + signal_received.signum
    except (campaign.ToolingError, rpc.grpc.RpcError, OSError) as error:
        text = (f"{error.code().name}: {error.details()}" if isinstance(error, rpc.grpc.RpcError)
                else str(error))
        print(f"soak_bench.py: {text}", file=sys.stderr, flush=True)
        status = campaign.EXIT_TOOLING
    finally:
        for signum in SIGNALS:
            signal.signal(signum, signal.SIG_IGN)
        stack.stop()
        samples_file.close()
    if stack.process is not None:
        problems += unclean_stops(stack.log_path)
    wall_s = time.monotonic() - started

    n = len(missions)
    summary = {"command": command, "machine": main_job_bench.machine(),
               "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
               "launcher_args": args.launcher_args, "reset_every": args.reset_every,
               "seed": args.seed, "missions_done": n, "resets": len(resets),
               "reset_before_missions": resets, "wall_s": round(wall_s, 1),
               "plateau_mib_per_h": args.plateau_mib_per_h,
               "marks": list(marks(n, args.warmup_missions)) if n else [0, 0, 0],
               "interrupted": interrupted, "problems": problems,
               "mission_summary": summarize_missions(missions),
               "processes": {name: summarize_process(rows, n, args)
                             for name, rows in series.items()} if n else {},
               "missions": missions}
    with open(os.path.join(args.out, "summary.json"), "w") as f:
        json.dump(summary, f, indent=2)
        f.write("\n")
    print(f"\n## soak_bench\n\n- command: `{command}`\n- machine: {summary['machine']}\n"
          f"- date: {summary['date']}")
    if interrupted:
        print(f"- interrupted by {interrupted} after {n} missions")
    if n:
        print_table(summary)
    if args.plot and n:
        drawn = plot(args.plot, series, resets)
        print(f"plot: {args.plot}" if drawn else "plot skipped: matplotlib is not installed")
    print(f"\nsamples: {os.path.join(args.out, 'samples.csv')}, summary: "
          f"{os.path.join(args.out, 'summary.json')}")

    for problem in problems:
        print(f"FAILED: {problem}")
    if status:
        return status
    failed = [m for m in missions if m["state"] != "SUCCEEDED"]
    for m in failed:
        print(f"FAILED: mission {m['mission']}: {m['state']} {m['failed']}")
    not_flat = [name for name, p in summary["processes"].items() if p["plateaued"] is False]
    if not_flat:
        print(f"{'FAILED' if args.check else 'note'}: no plateau (second-half slope >= "
              f"{args.plateau_mib_per_h:g} MiB/h): {', '.join(not_flat)}")
    if args.smoke and (n != 2 or len(resets) != 1
                       or any(len(rows) != n + 1 for rows in series.values())):
        print("FAILED: the smoke run did not fly 2 missions with a Reset, every process "
              "sampled after each")
        return 1
    no_heap = sorted(heap_unread | {name for name, rows in series.items()
                                    if name in heap_readers
                                    and any(sample.get("heap_kib", 0) <= 0
                                            for _, _, sample in rows)})
    if args.smoke and (no_heap or len(heap_readers) < 3):
        print(f"FAILED: the heap in use was not read from every /metrics (read from "
              f"{', '.join(sorted(heap_readers)) or 'none'}; missing in "
              f"{', '.join(no_heap) or 'none'})")
        return 1
    if failed or problems or (args.check and not_flat):
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
