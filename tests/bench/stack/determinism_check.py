"""The deterministic mode, run after run: flies the demo mission with the
launcher (deploy/local/launch.py --demo --time-scale max) several times with
one seed, and compares each run with the first.

    python3 tests/bench/stack/determinism_check.py --build-dir build --runs 3
    python3 tests/bench/stack/determinism_check.py --runs 3 -- \
        --systems quadrotor_motion_with_pid_control,multi_sensor_fusion

Per run it prints the mission's result, the simulated and wall time of the
mission and their ratio (the speed-up over real time), and against the first
run:
- whether every step ended with the same termination cause;
- the path deviation: for every ground-truth sample of one run, the distance
  to the other run's track (a polyline), both ways, the largest; a shift in
  time (an activation landing a quantum later) does not count, a different
  flight does;
- the time-aligned deviation: the distance between the two runs' positions
  at the same simulated time since the mission's first activation.
Exits 1 when a mission failed, the causes differ, or the path deviation
exceeds --tolerance-m (1 cm). Extra launcher arguments go after `--`.
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

REPO = os.path.abspath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", ".."))
LAUNCHER = os.path.join(REPO, "deploy", "local", "launch.py")
sys.path.insert(0, os.path.join(REPO, "deploy", "local"))
# What "the same path" means, shared with deploy/local/campaign.py.
from determinism import aligned_deviation, path_deviation  # noqa: E402


def run_once(args, extra, run_dir):
    argv = [sys.executable, LAUNCHER, "--build-dir", args.build_dir, "--run-dir", run_dir,
            "--demo", "--time-scale", "max", "--seed", str(args.seed)] + extra
    started = time.monotonic()
    result = subprocess.run(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            timeout=args.timeout_s)
    wall_s = time.monotonic() - started
    report_path = os.path.join(run_dir, "report.json")
    if not os.path.exists(report_path):
        raise RuntimeError(f"no report (launcher exit {result.returncode}):\n{result.stdout[-2000:]}")
    with open(report_path) as f:
        report = json.load(f)
    with open(os.path.join(run_dir, "trajectory.json")) as f:
        trajectories = json.load(f)
    robot = next(iter(trajectories))
    samples = [(s[0], s[1], s[2], s[3]) for s in trajectories[robot]]
    mission = report.get("mission", {})
    steps = [(s.get("name", ""), s.get("cause", "")) for s in mission.get("steps", [])]
    timeline = report.get("timeline", [])
    sim_times = [e["sim_time_s"] for e in timeline if e.get("sim_time_s") is not None]
    mission_wall_s = _mission_wall_s(result.stdout)
    return {"state": mission.get("state", "?"), "steps": steps, "samples": samples,
            "t0": min(sim_times) if sim_times else None,
            "sim_s": (max(sim_times) - min(sim_times)) if sim_times else 0.0,
            "mission_wall_s": mission_wall_s, "wall_s": wall_s}


def _mission_wall_s(stdout):
    """The launcher's '[  6.4 s] mission NAME: SUCCEEDED' line: the mission's
    wall time."""
    for line in stdout.splitlines():
        line = line.strip()
        if line.startswith("[") and "] mission " in line and line.rstrip().endswith(
                ("SUCCEEDED", "FAILED", "ABORTED")):
            try:
                return float(line[1:line.index("s]")].strip())
            except ValueError:
                pass
    return None


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--build-dir", default=os.path.join(REPO, "build"))
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--tolerance-m", type=float, default=0.01)
    parser.add_argument("--timeout-s", type=float, default=300.0)
    parser.add_argument("--keep", default="",
                        help="keep the run directories under this directory (default: removed)")
    parser.add_argument("extra", nargs="*", help="launcher arguments (after --)")
    args = parser.parse_args()
    if not 1 <= args.runs <= 10:
        parser.error("--runs must be within [1, 10]")

    runs = []
    with tempfile.TemporaryDirectory(prefix="behaviorlib-determinism-") as tmp:
        root = args.keep or tmp
        for i in range(args.runs):
            runs.append(run_once(args, args.extra, os.path.join(root, f"run{i + 1}")))

    ok = True
    first = runs[0]
    print(f"deterministic mode, seed {args.seed}, launcher extra: {' '.join(args.extra) or '-'}")
    print("| run | mission | simulated (s) | mission wall (s) | speed-up | same causes "
          "| path deviation (m) | time-aligned deviation (m) |")
    print("|---:|---|---:|---:|---:|---|---:|---:|")
    for i, run in enumerate(runs):
        speed = (run["sim_s"] / run["mission_wall_s"]) if run["mission_wall_s"] else float("nan")
        same = run["steps"] == first["steps"]
        path = path_deviation(run["samples"], first["samples"]) if i else 0.0
        aligned = (aligned_deviation(run["samples"], run["t0"], first["samples"], first["t0"])
                   if i and run["t0"] is not None and first["t0"] is not None else 0.0)
        print(f"| {i + 1} | {run['state']} | {run['sim_s']:.2f} | "
              f"{run['mission_wall_s'] or float('nan'):.2f} | {speed:.1f}x | "
              f"{'yes' if same else 'NO'} | {path:.4f} | {aligned:.4f} |")
        ok = ok and run["state"].endswith("SUCCEEDED") and same and path <= args.tolerance_m
    if not ok:
        for i, run in enumerate(runs):
            print(f"run {i + 1} steps: {run['steps']}", file=sys.stderr)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
