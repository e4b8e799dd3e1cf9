"""Idle cost and start time of the compose deployment in containers, beside
the local launcher's, in one run: the stack of deploy/compose (with
docker-compose.offline.yml; Grafana left out) brought up with
docker-compose from behaviorlib:latest, the vehicle landed, and each
container's server (its PID 1, seen from the host) read from /proc over a
window of wall time, once per time scale; then the same for the local
launcher (tests/bench/stack/idle_bench.py's measure()).

    python3 tests/bench/stack/container_idle_bench.py --build-dir build \
        --time-scales 1,10 --window-s 20 --runs 3

Needs a Docker engine (DOCKER_HOST or the default socket) and the image
(scripts/container-tests.sh makes both). Prints, per time scale, the total
CPU of the containers as % of one core (median of the runs, and each run),
the busiest containers, and the seconds from `up -d` to every service
healthy; then the launcher's total.
"""

import os
import statistics
import sys
import tempfile
import time

REPO = os.path.abspath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", ".."))
sys.path.insert(0, os.path.join(REPO, "tests", "container"))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import compose_stack_test as cst  # noqa: E402
import idle_bench  # noqa: E402


def container_ids(stack, services):
    return {s: stack.inspect(stack.container(s))["Id"] for s in services}


def cgroup_cpu_seconds(container_id):
    """CPU time of everything in the container (its server and the health
    probes Docker runs in it), from cgroup v1's cpuacct (the cgroupfs driver
    puts containers under docker/); None where that file does not exist."""
    try:
        with open(f"/sys/fs/cgroup/cpuacct/docker/{container_id}/cpuacct.usage") as f:
            return int(f.read()) / 1e9
    except OSError:
        return None


def healthy_after(stack, services, started, timeout_s=300):
    def all_healthy():
        return all(stack.inspect(stack.container(s))["State"].get("Health", {}).get("Status")
                   == "healthy" for s in services)
    cst.wait_for(all_healthy, timeout_s, "every service healthy", interval_s=0.5)
    return time.monotonic() - started


def measure_containers(build_dir, time_scale, window_s, settle_s):
    cst.BUILD_DIR = build_dir
    with tempfile.TemporaryDirectory(prefix="container-idle-bench-") as work:
        stack = cst.Stack(work)
        stack.env["SIMULATOR_TIME_SCALE"] = str(time_scale)
        for name in ("BEHAVIOR_SYSTEM_FOLLOW_TIME", "COORDINATOR_GRACE_PERIOD_S"):
            stack.env.pop(name, None)
        stack.down(volumes=True)
        try:
            started = time.monotonic()
            services = stack.up()
            stack.env["SIMULATOR_MIN_FOLLOWERS"] = "0"
            up_s = healthy_after(stack, services, started)
            time.sleep(settle_s)
            measured = stack.behaviorlib_services(services)
            ids = container_ids(stack, measured)
            pids = {s: stack.inspect(ids[s])["State"]["Pid"] for s in measured}
            before = {s: (cgroup_cpu_seconds(ids[s]), idle_bench.cpu_seconds(pids[s]))
                      for s in measured}
            t0 = time.monotonic()
            time.sleep(window_s)
            elapsed = time.monotonic() - t0
            after = {s: (cgroup_cpu_seconds(ids[s]), idle_bench.cpu_seconds(pids[s]))
                     for s in measured}
            rss = {s: idle_bench.rss_kib(p) / 1024 for s, p in pids.items()}
            # (the container with its health probes, its server alone)
            share = {s: tuple(100.0 * (a - b) / elapsed if a is not None and b is not None
                              else float("nan") for a, b in zip(after[s], before[s]))
                     for s in measured}
            return share, rss, up_s
        finally:
            stack.down(volumes=True)


def main():
    args = idle_bench.window_arguments(__doc__).parse_args()
    build_dir = os.path.abspath(args.build_dir)
    if not cst.engine_answers():
        print("no Docker engine answers")
        return cst.SKIP
    for scale in args.time_scales.split(","):
        totals, servers, ups, per = [], [], [], {}
        for _ in range(args.runs):
            share, rss, up_s = measure_containers(build_dir, scale, args.window_s, args.settle_s)
            totals.append(sum(c for c, _ in share.values()))
            servers.append(sum(p for _, p in share.values()))
            ups.append(up_s)
            for s, v in share.items():
                per.setdefault(s, []).append((v[0], v[1], rss[s]))
        print(f"\n== containers at {scale}x: total {statistics.median(totals):.2f} % of a core "
              f"with the health probes (runs: {', '.join(f'{t:.2f}' for t in totals)}), "
              f"the servers alone {statistics.median(servers):.2f} % (runs: "
              f"{', '.join(f'{t:.2f}' for t in servers)}); up -d to healthy "
              f"{statistics.median(ups):.1f} s (runs: {', '.join(f'{u:.1f}' for u in ups)})")
        print(f"  {'container':48s} {'with probes':>11s} {'server':>8s} {'RSS':>10s}")
        for s, values in sorted(per.items(), key=lambda kv: -statistics.median(
                v for v, _, _ in kv[1])):
            print(f"  {s:48s} {statistics.median(v for v, _, _ in values):9.2f} % "
                  f"{statistics.median(p for _, p, _ in values):6.2f} % "
                  f"{statistics.median(r for _, _, r in values):6.1f} MiB")
        launcher, serving = [], []
        for _ in range(args.runs):
            started = time.monotonic()
            rows, _rate = idle_bench.measure(build_dir, scale, args.window_s, args.settle_s, [])
            launcher.append(sum(cpu for cpu, _ in rows.values()))
            serving.append(time.monotonic() - started - args.window_s - args.settle_s)
        print(f"== local launcher at {scale}x: total {statistics.median(launcher):.2f} % of a "
              f"core (runs: {', '.join(f'{t:.2f}' for t in launcher)}); start to serving and "
              f"stop about {statistics.median(serving):.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
