"""A fleet flying the demo at once: N vehicles in the empty field (vehicle
i starts at x = 2 i m), each with basic_quadrotor_behaviors,
quadrotor_motion_with_pid_control and multi_sensor_fusion (the demo's EKF),
each flying the demo mission
(deploy/missions/demo.yaml) on a square of its own (side --side-m, from its
start, so that no two squares overlap), all started at once through the
launcher's --demo.

    python3 tests/bench/stack/fleet_bench.py --build-dir build --vehicles 10 \
        --time-scale 1

prints each mission's outcome and wall time, and CPU (seconds and % of one
core over the flight) and peak RSS per process and per vehicle (its three
behavior systems), from the launcher's report.json. Exits 1 unless every
mission succeeded.
"""

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile

REPO = os.path.abspath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", ".."))
LAUNCHER = os.path.join(REPO, "deploy", "local", "launch.py")
DEMO = os.path.join(REPO, "deploy", "missions", "demo.yaml")


# What each vehicle runs besides basic_quadrotor_behaviors: the motion
# controller and the EKF the demo mission localizes with.
FLEET_SYSTEMS = "quadrotor_motion_with_pid_control,multi_sensor_fusion"

def mission_for(robot, start_x, side_m):
    """The demo mission's text for `robot`, its square moved to start at the
    robot's start position and shrunk to `side_m`. (Edited as text: a YAML
    round trip through PyYAML would turn the `on:` keys into booleans.)"""
    with open(DEMO) as f:
        text = f.read()
    square = [(start_x + side_m, 0.0), (start_x + side_m, side_m), (start_x, side_m),
              (start_x, 0.0)]
    corners = iter(square)
    text, count = re.subn(r"\{x: [-0-9.]+, y: [-0-9.]+, z: 1\.5\}",
                          lambda _: "{x: %.2f, y: %.2f, z: 1.5}" % next(corners), text)
    if count != 4:
        raise RuntimeError(f"{DEMO}: expected the square's 4 waypoints, found {count}")
    return re.sub(r"(?m)^robot: \S+$", f"robot: {robot}", text)


def time_scale(text):
    """The launcher's --time-scale: a positive factor, or max."""
    if text == "max":
        return text
    if float(text) <= 0:
        raise argparse.ArgumentTypeError("must be positive, or max")
    return text


def main():
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--build-dir", default=os.path.join(REPO, "build"))
    parser.add_argument("--vehicles", type=int, default=10)
    parser.add_argument("--time-scale", type=time_scale, default="1",
                        help="a factor, or max for the deterministic mode (decision 18)")
    parser.add_argument("--side-m", type=float, default=1.5)
    parser.add_argument("--timeout-s", type=float, default=300.0)
    args = parser.parse_args()
    if not 1 <= args.vehicles <= 20:
        parser.error("--vehicles must be within 1..20")
    if not 0.2 <= args.side_m < 2.0:
        parser.error("--side-m must be within [0.2, 2) (vehicles start 2 m apart)")

    run_dir = tempfile.mkdtemp(prefix="behaviorlib-fleet-")
    robots = [f"drone{i + 1}" for i in range(args.vehicles)]
    argv = [sys.executable, LAUNCHER, "--build-dir", os.path.abspath(args.build_dir),
            "--run-dir", run_dir, "--demo", "--time-scale", args.time_scale,
            "--vehicles", ",".join(robots), "--systems", FLEET_SYSTEMS,
            "--mission-timeout-s", str(args.timeout_s)]
    for i, robot in enumerate(robots):
        path = os.path.join(run_dir, f"mission-{robot}.yaml")
        with open(path, "w") as f:
            f.write(mission_for(robot, 2.0 * i, args.side_m))
        argv += ["--mission", f"{robot}={path}"]
    print(f"# fleet_bench: {args.vehicles} vehicles at {args.time_scale}x, {os.cpu_count()} "
          f"CPUs; run directory {run_dir}")
    launched = subprocess.run(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                              timeout=args.timeout_s + 120)
    with open(os.path.join(run_dir, "launcher.log"), "w") as f:
        f.write(launched.stdout)
    with open(os.path.join(run_dir, "report.json")) as f:
        report = json.load(f)
    wall_s = report["settings"]["wall_s"]

    print("\n| robot | mission |\n|---|---|")
    outcomes = {}
    for line in launched.stdout.splitlines():
        m = re.match(r"mission (\S+) on (\S+): (\S+)", line)
        if m:
            outcomes[m.group(2)] = m.group(3)
    for robot in robots:
        print(f"| {robot} | {outcomes.get(robot, 'unknown')} |")

    print(f"\nlauncher wall time: {wall_s:.1f} s (start, flight, stop)\n")
    print("| process | CPU s | CPU % of a core over the run | peak RSS MiB |")
    print("|---|---:|---:|---:|")
    per_vehicle = {robot: [0.0, 0.0] for robot in robots}
    total_cpu = 0.0
    for p in report["processes"]:
        cpu = (p.get("cpu_user_s") or 0.0) + (p.get("cpu_system_s") or 0.0)
        rss = (p.get("peak_rss_kib") or 0) / 1024
        total_cpu += cpu
        print(f"| {p['name']} | {cpu:.2f} | {100 * cpu / wall_s:.1f} | {rss:.1f} |")
        for robot in robots:
            if p["name"].endswith("-" + robot):
                per_vehicle[robot][0] += cpu
                per_vehicle[robot][1] += rss
    print(f"| **total** | {total_cpu:.2f} | {100 * total_cpu / wall_s:.1f} | |")
    cpus = sorted(v[0] for v in per_vehicle.values())
    rsss = sorted(v[1] for v in per_vehicle.values())
    print(f"\nper vehicle (its three behavior systems): CPU median {cpus[len(cpus) // 2]:.2f} s "
          f"({100 * cpus[len(cpus) // 2] / wall_s:.1f} % of a core), peak RSS median "
          f"{rsss[len(rsss) // 2]:.1f} MiB")
    succeeded = all(outcomes.get(robot) == "SUCCEEDED" for robot in robots)
    print("\nall missions succeeded" if succeeded else "\nFAILED: not every mission succeeded")
    return 0 if succeeded else 1


if __name__ == "__main__":
    sys.exit(main())
