"""NAVIGATE_TO from room A to room D over simulator seeds (issue 41's figures, decision 48).

Each seed flies deploy/missions/go_to_room_d.yaml with the local launcher in the deterministic
mode (--time-scale max), localized by the lidar SLAM, and is measured from its report, its
timeline and the vehicle's true track (trajectory.json) for the first NAVIGATE_TO (room A to
the point in room D):

  - success: the step ended GOAL_ACHIEVED (and the mission SUCCEEDED);
  - time to goal, in simulated seconds, from the activation to the finished event;
  - the length of the true track over that time, against the shortest path in the true map for
    a vehicle of the same radius (a grid search on the world file's plan view, 5 cm cells,
    8-connected, then shortened by line of sight: within a few centimetres of the exact one);
  - the plans (made, followed while flying, after a wall seen ahead) and the planning times,
    from the behavior's finished message;
  - the closest approach of the true track (while flying) to a wall or to a box that reaches
    the vehicle's height, in plan view.

    /usr/bin/python3 tests/bench/stack/navigate_bench.py --build-dir build --seeds 20
    /usr/bin/python3 tests/bench/stack/navigate_bench.py --build-dir build --seeds 10 \\
        --require-all --min-clearance-m 0.25      # as a test: every seed must pass

With --require-all the exit status is 1 when a seed fails, or when a track came nearer a
surface than --min-clearance-m.
"""

import argparse
import heapq
import json
import math
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time

REPO = os.path.abspath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", ".."))
LAUNCHER = os.path.join(REPO, "deploy", "local", "launch.py")
MISSION = os.path.join(REPO, "deploy", "missions", "go_to_room_d.yaml")
WORLD = os.path.join(REPO, "simulator", "worlds", "rooms.yaml")
sys.path.insert(0, os.path.dirname(LAUNCHER))
import report  # noqa: E402  (deploy/local/report.py: the world file's plan view)

START = (2.0, 2.0)
GOAL = (15.5, 8.0)
ALTITUDE_M = 1.2
RADIUS_M = 0.35
CELL_M = 0.05
PLANS = re.compile(r"(\d+) plans \((\d+) followed while flying, (\d+) after a wall seen ahead, "
                   r"(\d+) after straying\)")
TIMES = re.compile(r"plan time median ([\d.]+) ms, longest ([\d.]+) ms")
LONGEST = re.compile(r"the (\d+) longest: ([\d., ]+) ms")


def pooled_p99(runs):
    """The 99th percentile (nearest rank) of every plan of `runs`, exact from
    each flight's longest plans as long as each stated at least as many as
    the percentile lies from the top; None otherwise."""
    total = sum(r["plans"] for r in runs)
    from_top = total - int(math.ceil(0.99 * total)) + 1  # 1: the longest
    if not runs or any(len(r["plan_longest_ms_list"]) < min(from_top, r["plans"]) for r in runs):
        return None
    longest = sorted((t for r in runs for t in r["plan_longest_ms_list"]), reverse=True)
    return longest[from_top - 1], total


def percentile(values, q):
    ordered = sorted(values)
    if not ordered:
        return float("nan")
    return ordered[min(len(ordered) - 1, int(math.ceil(q * len(ordered))) - 1)]


def segment_distance(p, a, b):
    (px, py), (ax, ay), (bx, by) = p, a, b
    dx, dy = bx - ax, by - ay
    length2 = dx * dx + dy * dy
    t = 0.0 if length2 == 0 else max(0.0, min(1.0, ((px - ax) * dx + (py - ay) * dy) / length2))
    return math.hypot(px - (ax + t * dx), py - (ay + t * dy))


def polygon_distance(p, corners):
    """Distance from p to a convex polygon (0 inside)."""
    edges = list(zip(corners, corners[1:] + corners[:1]))
    signs = {(b[0] - a[0]) * (p[1] - a[1]) - (b[1] - a[1]) * (p[0] - a[0]) > 0 for a, b in edges}
    if len(signs) == 1:
        return 0.0
    return min(segment_distance(p, a, b) for a, b in edges)


def obstacles():
    """The world's walls, and its boxes that reach the vehicle's lowest point, in plan view."""
    import yaml  # Debian's python3-yaml
    with open(WORLD) as f:
        data = yaml.safe_load(f)
    footprints = report.world_footprints(WORLD)
    shapes = list(footprints["walls"])
    for box, outline in zip(data.get("boxes") or [], footprints["boxes"]):
        if float(box["center_m"][2]) + float(box["size_m"][2]) / 2 >= ALTITUDE_M - RADIUS_M:
            shapes.append(outline)
    return shapes


def shortest_path_m(shapes):
    """The shortest way from START to GOAL for a disc of RADIUS_M among `shapes`."""
    xs = [x for s in shapes for x, _ in s]
    ys = [y for s in shapes for _, y in s]
    x0, y0 = min(xs), min(ys)
    w = int((max(xs) - x0) / CELL_M) + 1
    h = int((max(ys) - y0) / CELL_M) + 1
    centre = lambda i, j: (x0 + (i + 0.5) * CELL_M, y0 + (j + 0.5) * CELL_M)  # noqa: E731
    free = [[min(polygon_distance(centre(i, j), s) for s in shapes) > RADIUS_M
             for j in range(h)] for i in range(w)]
    cell = lambda p: (int((p[0] - x0) / CELL_M), int((p[1] - y0) / CELL_M))  # noqa: E731
    start, goal = cell(START), cell(GOAL)
    dist = {start: 0.0}
    parent = {}
    queue = [(0.0, start)]
    while queue:
        d, c = heapq.heappop(queue)
        if c == goal:
            break
        if d > dist.get(c, math.inf):
            continue
        for di in (-1, 0, 1):
            for dj in (-1, 0, 1):
                n = (c[0] + di, c[1] + dj)
                if (di, dj) == (0, 0) or not (0 <= n[0] < w and 0 <= n[1] < h):
                    continue
                if not free[n[0]][n[1]]:
                    continue
                nd = d + CELL_M * math.hypot(di, dj)
                if nd < dist.get(n, math.inf):
                    dist[n] = nd
                    parent[n] = c
                    heapq.heappush(queue, (nd, n))
    chain = [goal]
    while chain[-1] != start:
        chain.append(parent[chain[-1]])
    points = [centre(*c) for c in reversed(chain)]

    def visible(a, b):
        steps = int(math.hypot(b[0] - a[0], b[1] - a[1]) / (CELL_M / 2)) + 1
        for k in range(steps + 1):
            p = (a[0] + (b[0] - a[0]) * k / steps, a[1] + (b[1] - a[1]) * k / steps)
            i, j = cell(p)
            if not (0 <= i < w and 0 <= j < h) or not free[i][j]:
                return False
        return True

    path = [points[0]]
    i = 0
    while i < len(points) - 1:
        j = len(points) - 1
        while j > i + 1 and not visible(points[i], points[j]):
            j -= 1
        path.append(points[j])
        i = j
    return sum(math.hypot(b[0] - a[0], b[1] - a[1]) for a, b in zip(path, path[1:]))


def fly(build_dir, seed, keep):
    run_dir = tempfile.mkdtemp(prefix=f"navigate-bench-{seed}-")
    argv = [sys.executable, LAUNCHER, "--build-dir", build_dir, "--run-dir", run_dir, "--demo",
            "--time-scale", "max", "--seed", str(seed), "--world", "rooms",
            "--systems", "quadrotor_motion_with_pid_control,navigation_with_lidar",
            "--mission", MISSION, "--mission-timeout-s", "400"]
    started = time.monotonic()
    result = subprocess.run(argv, capture_output=True, text=True, timeout=900)
    wall_s = time.monotonic() - started
    out = {"seed": seed, "wall_s": wall_s, "run_dir": run_dir}
    try:
        with open(os.path.join(run_dir, "report.json")) as f:
            rep = json.load(f)
        with open(os.path.join(run_dir, "trajectory.json")) as f:
            track = json.load(f)["drone1"]
    except (OSError, ValueError, KeyError) as error:
        out.update(ok=False, why=f"no report ({error}); launcher exit {result.returncode}")
        return out
    robot = rep["robots"]["drone1"]
    mission = robot["mission"]
    events = [e for e in robot["timeline"] if e.get("behavior") == "NAVIGATE_TO"]
    first = [e for e in events if e["activation_id"] == events[0]["activation_id"]] if events else []
    finished = next((e for e in first if e["event"] == "finished"), None)
    if not first or finished is None:
        out.update(ok=False, why=f"no NAVIGATE_TO finished; mission {mission.get('state')}")
        return out
    t0, t1 = first[0]["sim_time_s"], finished["sim_time_s"]
    window = [s for s in track if t0 <= s[0] <= t1]
    flying = [s for s in track if s[4] == "FLIGHT_STATE_FLYING"]
    message = finished.get("message", "")
    plans = PLANS.search(message)
    times = TIMES.search(message)
    longest = LONGEST.search(message)
    out.update(
        ok=finished.get("cause") == "GOAL_ACHIEVED"
        and mission.get("state") == "MISSION_STATE_SUCCEEDED",
        why=f"{finished.get('cause')}: {message}; mission {mission.get('state')}",
        time_s=t1 - t0,
        length_m=sum(math.hypot(b[1] - a[1], b[2] - a[2]) for a, b in zip(window, window[1:])),
        plans=int(plans.group(1)) if plans else None,
        followed=int(plans.group(2)) if plans else None,
        walls_ahead=int(plans.group(3)) if plans else None,
        plan_median_ms=float(times.group(1)) if times else None,
        plan_longest_ms=float(times.group(2)) if times else None,
        plan_longest_ms_list=[float(t) for t in longest.group(2).split(", ")] if longest else [],
        flying=[(s[1], s[2]) for s in flying if s[3] > 0.3])
    if out["ok"] and not keep:
        shutil.rmtree(run_dir, ignore_errors=True)
    return out


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--build-dir", default=os.path.join(REPO, "build"))
    parser.add_argument("--seeds", type=int, default=20)
    parser.add_argument("--first-seed", type=int, default=1)
    parser.add_argument("--require-all", action="store_true")
    parser.add_argument("--min-clearance-m", type=float, default=0.25)
    parser.add_argument("--keep", action="store_true", help="keep every run directory")
    args = parser.parse_args()
    build_dir = os.path.abspath(args.build_dir)
    shapes = obstacles()
    shortest = shortest_path_m(shapes)
    print(f"shortest path in the true map for a radius of {RADIUS_M} m: {shortest:.2f} m",
          flush=True)
    runs = []
    for seed in range(args.first_seed, args.first_seed + args.seeds):
        run = fly(build_dir, seed, args.keep)
        if run.get("flying"):
            run["closest_m"] = min(polygon_distance(p, s) for p in run["flying"] for s in shapes)
        run.pop("flying", None)
        runs.append(run)
        if run["ok"]:
            print(f"seed {seed}: {run['time_s']:.1f} s, {run['length_m']:.2f} m "
                  f"({run['length_m'] / shortest:.2f}x), {run['plans']} plans "
                  f"({run['followed']} followed while flying, {run['walls_ahead']} after a wall "
                  f"ahead), plan median {run['plan_median_ms']} ms, longest "
                  f"{run['plan_longest_ms']} ms, closest {run.get('closest_m', float('nan')):.3f}"
                  f" m; {run['wall_s']:.1f} s wall", flush=True)
        else:
            print(f"seed {seed}: FAILED: {run['why']} (kept: {run['run_dir']})", flush=True)
    good = [r for r in runs if r["ok"]]
    print(f"\nsucceeded: {len(good)} of {len(runs)}")
    if good:
        ratios = [r["length_m"] / shortest for r in good]
        print(f"time to goal (simulated s): median {statistics.median(r['time_s'] for r in good):.1f}, "
              f"p99 {percentile([r['time_s'] for r in good], 0.99):.1f}")
        print(f"track length / shortest ({shortest:.2f} m): median {statistics.median(ratios):.2f}, "
              f"p99 {percentile(ratios, 0.99):.2f}")
        print(f"plans per flight: median {statistics.median(r['plans'] for r in good)}, "
              f"max {max(r['plans'] for r in good)}; followed while flying: median "
              f"{statistics.median(r['followed'] for r in good)}; after a wall ahead: median "
              f"{statistics.median(r['walls_ahead'] for r in good)}, max "
              f"{max(r['walls_ahead'] for r in good)}")
        p99 = pooled_p99(good)
        print(f"plan time (ms): median of the flights' medians "
              f"{statistics.median(r['plan_median_ms'] for r in good):.1f}, p99 of all "
              + (f"{p99[0]:.1f} (nearest rank over {p99[1]} plans)" if p99 else
                 "not known (a flight stated too few of its longest)")
              + f", longest of all {max(r['plan_longest_ms'] for r in good):.1f}")
    closest = [r["closest_m"] for r in runs if "closest_m" in r]
    if closest:
        print(f"closest approach to a surface: {min(closest):.3f} m (median of the flights' "
              f"{statistics.median(closest):.3f} m)")
    if args.require_all:
        failed = [r["seed"] for r in runs if not r["ok"]]
        near = [r["seed"] for r in runs if r.get("closest_m", 1.0) < args.min_clearance_m]
        if failed or near:
            print(f"FAILED: seeds {failed} did not reach the goal; seeds {near} came nearer a "
                  f"surface than {args.min_clearance_m} m", file=sys.stderr)
            return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
