"""The main job's figures, measured again: every figure README.md states
about the demo stack as the launcher runs it by default (the console on, the
recorder on with --demo), each beside the README's value, in one command.

    python3 tests/bench/stack/main_job_bench.py --build-dir build --runs 3
    python3 tests/bench/stack/main_job_bench.py --only idle,speedup --check
    python3 tests/bench/stack/main_job_bench.py --smoke

Each figure is one row of FIGURES below: a regex that finds the README's value,
the configuration it was measured in, and the measurement, which reuses the
other benches: idle_bench.py's measure() (the idle stack's total CPU),
determinism_check.py's run_once() (the demo at --time-scale max: the speed-up,
and run after run the flown path), the launcher's --demo timed as it is (its
wall time, and t1 and t3 per behavior from its report.json, which the README
does not state), and build/tests/bench/channel_bench (a delivery's CPU). The
runs are interleaved: run i measures every selected figure before run i + 1,
and figures of one launcher run share it.

Prints the machine, the date, a markdown table (figure | configuration |
README says | measured now | within tolerance?; medians over the runs, each run
in brackets) and the commands that measure each figure on their own, ready for
docs/benchmarks.md; progress goes to stderr. Measure on an otherwise idle
machine: other launchers running are reported under the table.

Exits 1 when a regex no longer finds exactly one value in README.md (the README
and this bench drifted apart), when a measurement fails (a mission that does
not succeed, a bench that exits non-zero), or, with --check, when a figure is
out of tolerance (a cost above README x --tolerance, a speed-up below README /
--tolerance). --smoke measures nothing: it checks the regexes and prints the
table with "-" measured.
"""

import argparse
import collections
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
import types

REPO = os.path.abspath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", ".."))
LAUNCHER = os.path.join(REPO, "deploy", "local", "launch.py")
README = os.path.join(REPO, "README.md")
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import determinism_check  # noqa: E402
import idle_bench  # noqa: E402

# idle_bench.py's own window: CPU over 20 s of wall time, 5 s after the stack serves.
IDLE = idle_bench.window_arguments("").parse_args([])
# channel_bench's configuration of the README's figure (its defaults, stated).
CHANNEL = ["--rate-hz", "1000", "--subscribers", "10", "--window-s", "10"]
SEED = 1

COST, SPEED, NOT_STATED, NOT_MEASURED = "cost", "speed-up", "not stated", "not re-measured"


class JobError(Exception):
    """A measurement that failed (kept, so that the figures sharing it do not run it again)."""


class Session:
    """The measurements of one invocation: each job once per run, its result or error kept."""

    def __init__(self, args, tmp):
        self.args, self.tmp, self.run = args, tmp, 0
        self.build_dir = os.path.abspath(args.build_dir)
        self.done = {}

    def once(self, key, job):
        if (self.run, key) not in self.done:
            print(f"run {self.run + 1}/{self.args.runs}: {' '.join(map(str, key))}",
                  file=sys.stderr, flush=True)
            try:
                self.done[(self.run, key)] = (job(), None)
            except Exception as error:  # reported in the table; the exit status is 1
                self.done[(self.run, key)] = (None, f"{type(error).__name__}: {error}")
        return self.result(self.run, key)

    def result(self, run, key):
        if (run, key) not in self.done:
            raise JobError(f"{' '.join(map(str, key))} did not run in run {run + 1}")
        value, error = self.done[(run, key)]
        if error:
            raise JobError(error)
        return value

    def run_dir(self, name):
        return os.path.join(self.tmp, f"run{self.run + 1}-{name}")


def idle_total(scale, extra=()):
    """The idle stack's CPU, summed over its processes (% of one core): idle_bench.measure()."""
    def measure(s):
        rows, _rate = s.once(("idle", f"{scale}x", *extra), lambda: idle_bench.measure(
            s.build_dir, scale, IDLE.window_s, IDLE.settle_s, list(extra)))
        return sum(cpu for cpu, _rss in rows.values())
    return measure


def demo_max(s, extra=()):
    """The demo at --time-scale max: determinism_check.run_once(), which must succeed."""
    def job():
        options = types.SimpleNamespace(build_dir=s.build_dir, seed=SEED,
                                        timeout_s=s.args.timeout_s)
        run = determinism_check.run_once(options, list(extra),
                                         s.run_dir("max" + "".join(extra)))
        if not run["state"].endswith("SUCCEEDED"):
            raise RuntimeError(f"the mission ended {run['state']}")
        if not run["mission_wall_s"] or not run["sim_s"]:
            raise RuntimeError("no mission time in the launcher's output or report")
        return run
    return s.once(("demo --time-scale max", *extra), job)


def speedup(extra=()):
    """Simulated span of the mission's events over the mission's wall time."""
    def measure(s):
        run = demo_max(s, extra)
        return run["sim_s"] / run["mission_wall_s"]
    return measure


def path_vs_first_run(s):
    """Run i's flown path against run 1's, same seed (determinism_check's measure), in mm."""
    run = demo_max(s)
    if s.run == 0:
        return None
    first = s.result(0, ("demo --time-scale max",))
    return 1000.0 * determinism_check.path_deviation(run["samples"], first["samples"])


def demo_default(s):
    """The launcher's --demo as it is (no option but the directories), timed; its report."""
    def job():
        run_dir = s.run_dir("demo")
        argv = [sys.executable, LAUNCHER, "--build-dir", s.build_dir, "--demo", "--run-dir",
                run_dir]
        started = time.monotonic()
        result = subprocess.run(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                text=True, timeout=s.args.timeout_s)
        wall_s = time.monotonic() - started
        if result.returncode != 0:
            raise RuntimeError(f"the launcher exited with {result.returncode}: "
                               f"{result.stdout[-500:]}")
        with open(os.path.join(run_dir, "report.json")) as f:
            report = json.load(f)
        return {"wall_s": wall_s, "behaviors": report["behaviors"]}
    return s.once(("demo",), job)


def demo_wall(s):
    return demo_default(s)["wall_s"]


def per_behavior(key):
    """One value per behavior the demo activated, from its report.json."""
    def measure(s):
        return {b["behavior"]: b[key] for b in demo_default(s)["behaviors"]
                if b.get(key) is not None}
    return measure


def channel_bench_path(build_dir):
    return os.path.join(build_dir, "tests", "bench", "channel_bench")


def delivery(mode):
    """channel_bench's total CPU per delivery (µs, all processes) in one mode, one run."""
    def job(s):
        binary = channel_bench_path(s.build_dir)
        if not os.access(binary, os.X_OK):
            raise RuntimeError(f"{binary} is not built (the target channel_bench)")
        argv = [binary, *CHANNEL, "--runs", "1", "--modes", "stream,ring"]
        result = subprocess.run(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                text=True, timeout=s.args.timeout_s)
        totals = dict(re.findall(r"^\| (stream|ring) \|.*\| \*\*([0-9.]+)\*\* \(",
                                 result.stdout, re.M))
        if result.returncode != 0 or set(totals) != {"stream", "ring"}:
            raise RuntimeError(f"channel_bench exited with {result.returncode}: "
                               f"{result.stdout[-500:]}")
        return {m: float(v) for m, v in totals.items()}

    def measure(s):
        return s.once(("channel_bench",), lambda: job(s))[mode]
    return measure


Figure = collections.namedtuple(
    "Figure", "name label unit kind regex config measure command summary",
    defaults=(statistics.median,))

_IDLE = (f"launch.py without --demo: one robot, every built system, console on; CPU of every "
         f"process over {IDLE.window_s:g} s, {IDLE.settle_s:g} s after it serves")
_IDLE_CMD = ("python3 tests/bench/stack/idle_bench.py --build-dir {build} --time-scales 1,10 "
             f"--window-s {IDLE.window_s:g} --settle-s {IDLE.settle_s:g} --runs {{runs}}")
_MAX = f"launch.py --demo --time-scale max --seed {SEED}"
_MAX_CMD = "python3 tests/bench/stack/determinism_check.py --build-dir {build} --runs {runs}"
_DEMO = "the demo's DIR/report.json (the demo-wall run): per behavior, "
_DEMO_CMD = "python3 deploy/local/launch.py --build-dir {build} --demo --run-dir DIR"
_CHANNEL = ("channel_bench: 1 publisher at 1 kHz, one topic, 10 subscriber processes, 10 s; "
            "CPU of every process / deliveries; ")
_CHANNEL_CMD = ("{build}/tests/bench/channel_bench " + " ".join(CHANNEL)
                + " --runs {runs} --modes stream,ring")

# Every figure the README states about the main job: name (for --only), label, unit, kind,
# the regex of the README's value (whitespace collapsed; None: not stated), configuration,
# measurement (None: not re-measured here), the command that measures it on its own.
FIGURES = [
    Figure("idle-1x", "idle stack, 1x", " %", COST,
           r"costs about ([0-9.]+) % of one core at 1x",
           _IDLE + "; --time-scale 1", idle_total(1), _IDLE_CMD),
    Figure("idle-10x", "idle stack, 10x", " %", COST,
           r"of one core at 1x and ([0-9.]+) % at 10x",
           _IDLE + "; --time-scale 10", idle_total(10), _IDLE_CMD),
    Figure("idle-1x-no-console", "idle stack, 1x, no console", " %", COST,
           r"at 10x, ([0-9.]+) % and [0-9.]+ % with `--no-console`",
           "the same with --no-console; --time-scale 1", idle_total(1, ("--no-console",)),
           _IDLE_CMD + " -- --no-console"),
    Figure("idle-10x-no-console", "idle stack, 10x, no console", " %", COST,
           r"at 10x, [0-9.]+ % and ([0-9.]+) % with `--no-console`",
           "the same with --no-console; --time-scale 10", idle_total(10, ("--no-console",)),
           _IDLE_CMD + " -- --no-console"),
    Figure("speedup-max", "demo speed-up at --time-scale max", "x", SPEED,
           r"The demo flies this way at about ([0-9.]+)x as the launcher runs it",
           _MAX + ", console and recorder on: simulated span of the mission's events / the "
           "mission's wall time", speedup(), _MAX_CMD),
    Figure("speedup-max-no-observers", "demo speed-up, console and recorder off", "x", SPEED,
           r"; ([0-9.]+)x with both off in the same run",
           "the same with --no-record --no-console, right after it",
           speedup(("--no-record", "--no-console")), _MAX_CMD + " -- --no-record --no-console"),
    Figure("path-max", "flown path, run i against run 1", " mm", COST,
           r"the flown path agrees within ([0-9.]+) mm",
           _MAX + " (the speed-up's runs): largest distance between the two tracks; the "
           "largest over the runs; needs --runs 2 or more", path_vs_first_run, _MAX_CMD,
           max),
    Figure("demo-wall", "demo wall time", " s", COST,
           r"About ([0-9.]+) s of wall time after the build",
           "launch.py --demo (default 2x; console and recorder on), built: the command's wall "
           "time, timed from outside", demo_wall, _DEMO_CMD),
    Figure("t1-cpu", "t1 CPU", " µs", NOT_STATED, None,
           _DEMO + "monitoring functions per tick, thread CPU clock", per_behavior("t1_cpu_us"),
           _DEMO_CMD),
    Figure("t1-wall", "t1 wall", " µs", NOT_STATED, None,
           _DEMO + "monitoring functions per tick, wall time", per_behavior("t1_us"),
           _DEMO_CMD),
    Figure("t3", "t3", " ms", NOT_STATED, None,
           _DEMO + "Activate to the first onExecute", per_behavior("t3_ms"),
           _DEMO_CMD),
    Figure("delivery-ring", "a delivery's CPU, shared-memory rings", " µs", COST,
           r"a delivery costs ([0-9.]+) µs of CPU over all processes at 1 kHz to 10 subscribers",
           _CHANNEL + "ring mode", delivery("ring"), _CHANNEL_CMD),
    Figure("delivery-stream", "a delivery's CPU, a gRPC stream each", " µs", COST,
           r"at 1 kHz to 10 subscribers, ([0-9.]+) µs on streams",
           _CHANNEL + "stream mode", delivery("stream"), _CHANNEL_CMD),
    Figure("build-steps", "build steps of the target demo", " steps", NOT_MEASURED,
           r"the CMake target `demo`: ([0-9]+) of the [0-9]+ build steps",
           "a build from scratch; not re-measured by this command", None,
           "ninja -C {build} -t commands demo | wc -l"),
]


def readme_values(text):
    """{figure name: the README's value as written}, and the drift: figures whose regex does
    not find exactly one value."""
    flat = " ".join(text.split())
    values, drift = {}, []
    for figure in FIGURES:
        if figure.regex is None:
            continue
        found = re.findall(figure.regex, flat)
        if len(found) == 1:
            values[figure.name] = found[0]
        else:
            drift.append(f"{figure.name}: /{figure.regex}/ finds {len(found)} values in "
                         f"README.md, not 1")
    return values, drift


def selected(only):
    if not only:
        return list(FIGURES)
    chosen = set()
    for name in (n for n in only.split(",") if n):
        exact = [f.name for f in FIGURES if f.name == name]
        matching = exact or [f.name for f in FIGURES if f.name.startswith(name + "-")]
        if not matching:
            raise ValueError(f"unknown figure {name}; known: "
                             f"{', '.join(f.name for f in FIGURES)}")
        chosen.update(matching)
    return [f for f in FIGURES if f.name in chosen]


def other_launchers():
    """Pids of launchers running now (this script runs none between its measurements)."""
    pids = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit() or int(entry) == os.getpid():
            continue
        try:
            with open(f"/proc/{entry}/cmdline", "rb") as f:
                argv = f.read().split(b"\0")
        except OSError:
            continue
        if any(a.endswith(b"deploy/local/launch.py") for a in argv):
            pids.append(int(entry))
    return pids


def machine():
    model = "?"
    try:
        with open("/proc/cpuinfo") as f:
            model = next((line.split(":", 1)[1].strip() for line in f
                          if line.startswith("model name")), "?")
    except OSError:
        pass
    return f"{len(os.sched_getaffinity(0))} CPUs (nproc), {model}"


def fmt(value):
    if value is None:
        return "-"
    return f"{value:.0f}" if abs(value) >= 100 else f"{value:.1f}" if abs(value) >= 10 \
        else f"{value:.2f}"


def verdict(figure, readme, summary, tolerance):
    """'yes', 'NO (limit X)' or '-'; and whether it is out of tolerance."""
    if summary is None or readme is None or figure.kind not in (COST, SPEED):
        return "-", False
    limit = float(readme) * tolerance if figure.kind == COST else float(readme) / tolerance
    ok = summary <= limit if figure.kind == COST else summary >= limit
    sign = "≤" if figure.kind == COST else "≥"
    return ("yes" if ok else "NO") + f" ({sign} {fmt(limit)})", not ok


def rows_of(figure, runs, errors, readme, smoke):
    """The table's rows of one figure: (label, config, README says, measured, values)."""
    says = (f"{readme}{figure.unit}" if readme is not None
            else "not stated" if figure.kind == NOT_STATED else "?")
    if smoke:
        return [(figure.label, figure.config, says, "-", None)]
    if figure.measure is None:
        return [(figure.label, figure.config, says, "not re-measured by this command", None)]
    if errors:
        return [(figure.label, figure.config, says, "error: " + errors[0][:120], None)]
    if any(isinstance(v, dict) for v in runs):
        keys = list(dict.fromkeys(k for v in runs if v for k in v))
        return [(f"{figure.label}, {k}", figure.config if i == 0 else "as above", says,
                 *measured(figure, [v.get(k) for v in runs if v])) for i, k in enumerate(keys)]
    return [(figure.label, figure.config, says, *measured(figure, runs))]


def measured(figure, runs):
    values = [v for v in runs if v is not None]
    if not values:
        return "- (needs --runs 2 or more)" if figure.name == "path-max" else "-", None
    summary = figure.summary(values)
    each = f" ({', '.join(fmt(v) for v in values)})" if len(runs) > 1 else ""
    return f"{fmt(summary)}{figure.unit}{each}", summary


def main():
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--build-dir", default=os.path.join(REPO, "build"))
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--only", default="", metavar="NAME[,NAME]",
                        help="these figures (a name, or the start of names before a '-': "
                             "idle, speedup, t1, delivery, ...); default: all")
    parser.add_argument("--tolerance", type=float, default=1.5,
                        help="a cost within README x this, a speed-up within README / this")
    parser.add_argument("--check", action="store_true",
                        help="exit 1 when a figure is out of tolerance")
    parser.add_argument("--timeout-s", type=float, default=300.0,
                        help="of each launcher or channel_bench run")
    parser.add_argument("--smoke", action="store_true",
                        help="no measurement: check the README's regexes, print the table")
    args = parser.parse_args()
    if not 1 <= args.runs <= 10:
        parser.error("--runs must be within [1, 10]")
    if args.tolerance < 1:
        parser.error("--tolerance must be 1 or more")
    try:
        figures = selected(args.only)
    except ValueError as error:
        parser.error(str(error))
    with open(README, encoding="utf-8") as f:
        readme, drift = readme_values(f.read())
    build = os.path.relpath(os.path.abspath(args.build_dir), REPO)

    started = time.gmtime()
    results = {f.name: ([], []) for f in figures}  # per run: values, errors
    others = set()
    if not args.smoke:
        with tempfile.TemporaryDirectory(prefix="behaviorlib-main-job-") as tmp:
            session = Session(args, tmp)
            for run in range(args.runs):
                session.run = run
                for figure in figures:
                    others.update(other_launchers())
                    if figure.measure is None:
                        continue
                    values, errors = results[figure.name]
                    try:
                        values.append(figure.measure(session))
                    except Exception as error:  # JobError, or a report without a key
                        values.append(None)
                        text = str(error) if isinstance(error, JobError) else repr(error)
                        errors.append(f"run {run + 1}: {text}")
    ended = time.gmtime()

    print("# main_job_bench: the README's figures about the main job, measured again\n")
    print(f"- machine: {machine()}")
    print(f"- date: {time.strftime('%a %b %d %H:%M', started)}–"
          f"{time.strftime('%H:%M UTC %Y', ended)}")
    print(f"- build: {build}; " + ("smoke: nothing measured" if args.smoke else
                                   f"{args.runs} run(s), medians (each run in brackets)")
          + f"; tolerance {args.tolerance:g}: a cost ≤ README x {args.tolerance:g}, "
          f"a speed-up ≥ README / {args.tolerance:g}\n")
    print("| figure | configuration | README says | measured now | within tolerance? |")
    print("|---|---|---:|---|---|")
    out_of_tolerance, failed = [], []
    for figure in figures:
        values, errors = results[figure.name]
        failed += [f"{figure.name}: {e}" for e in errors]
        for label, config, says, now, summary in rows_of(
                figure, values, errors, readme.get(figure.name), args.smoke):
            within, out = verdict(figure, readme.get(figure.name), summary, args.tolerance)
            if out:
                out_of_tolerance.append(label)
            print(f"| {label} | {config} | {says} | {now} | {within} |")

    print("\nCommands (each measures its figures on its own; this command ran the same through "
          "idle_bench.measure(), determinism_check.run_once(), the launcher and channel_bench, "
          "one run at a time):\n")
    for command in dict.fromkeys(f.command for f in figures):
        names = ", ".join(f.name for f in figures if f.command == command)
        print(f"- `{command.format(build=build, runs=args.runs)}` ({names})")

    status = 0
    for line in drift:
        print(f"\nREADME drift: {line}")
        status = 1
    for line in failed:
        print(f"\nFAILED: {line}")
        status = 1
    if others:
        print(f"\nWARNING: other launchers ran during the measurement (pids "
              f"{', '.join(map(str, sorted(others)))}): the timings are not comparable")
    if out_of_tolerance:
        print(f"\nOut of tolerance: {', '.join(out_of_tolerance)}")
        if args.check:
            status = 1
    return status


if __name__ == "__main__":
    sys.exit(main())
