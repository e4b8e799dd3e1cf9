#!/usr/bin/python3
"""A lost radio, on both data paths in the same run (deploy/fleet/fleet.py,
decision 39):

- nats: a broker per host, linked over NATS;
- broker: the one broker on the ground, that every vehicle's systems and the
  simulator use over gRPC (the path before).

For each, the fleet idle in the deterministic mode (systems registered, the
ground's console following every vehicle), drone1's radio is cut for
--cut-s and restored, --runs times. Measured in wall time:

- detected: from the cut until the coordinator reports drone1's systems not
  up (its grace period: 5 s in the deterministic mode);
- data back: from the restore until a sample published on drone1's host
  reaches the ground's broker again (latency_probe.py publishing 5 a second
  inside drone1's namespace to its 127.0.0.1 broker address: drone1's own
  broker, or on the one-broker path the ground's through the radio's relay;
  this script subscribes to the ground's broker);
- registered again: from the restore until every system of drone1 is up.

Needs root; exits 77 otherwise.

    sudo /usr/bin/python3 tests/bench/fleet/lost_link_bench.py --build-dir build
"""

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
import urllib.request

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.dirname(
    os.path.abspath(__file__)))))
sys.path.insert(0, os.path.join(REPO, "deploy", "fleet"))

import fleet as fleet_module  # noqa: E402
from fleet import demo  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import latency_probe  # noqa: E402

ROBOT = "drone1"
PROBE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "latency_probe.py")
TOPIC = f"robots/{ROBOT}/lost_link_probe"
POLL_S = 0.1


def first_after(follower, t):
    """The first arrival after `t` (time.monotonic), or None."""
    return next((a for a in follower.arrivals if a > t), None)


def peers(broker):
    """The brokers a linked broker hears (behaviorlib_channel_link_peers)."""
    with urllib.request.urlopen(f"http://{broker.metrics_address}/metrics", timeout=5) as page:
        for line in page.read().decode().splitlines():
            if line.startswith("behaviorlib_channel_link_peers "):
                return float(line.split()[1])
    return None


def systems_up(client, systems):
    reply = client.call(demo.COORDINATOR, "ListSystems", {"robot_id": ROBOT})
    states = [s.get("state") for s in reply.get("systems", [])]
    return len(states) == len(systems) and all(s == "SYSTEM_STATE_UP" for s in states)


def wait_until(predicate, timeout_s):
    """Seconds until predicate() held (polled), or None."""
    start = time.monotonic()
    while time.monotonic() - start < timeout_s:
        if predicate():
            return time.monotonic() - start
        time.sleep(POLL_S)
    return None


def measure(build_dir, path, runs, cut_s):
    run_dir = tempfile.mkdtemp(prefix=f"behaviorlib-lost-link-bench-{path}-")
    results = []
    with fleet_module.Fleet(build_dir, run_dir, vehicles=3, say=lambda _: None,
                            data_path=path) as fleet:
        client = fleet.coordinator_client()
        fleet.wait_for_systems(client)
        arrivals = latency_probe.Follower(fleet.ground_broker.address, TOPIC)
        publisher = subprocess.Popen(
            ["ip", "netns", "exec", fleet.ns(ROBOT), sys.executable, PROBE, "publish",
             "--channel", f"127.0.0.1:{fleet_module.BROKER_PORT}", "--topic", TOPIC,
             "--count", "1000000", "--rate-hz", "5"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            for _ in range(runs):
                if wait_until(lambda: arrivals.arrivals
                              and time.monotonic() - arrivals.arrivals[-1] < 0.5, 60) is None:
                    raise RuntimeError(f"{ROBOT}'s samples do not reach the ground")
                heard = peers(fleet.ground_broker) if path == "nats" else None
                cut_at = time.monotonic()
                fleet.cut(ROBOT)
                # The coordinator's view, and the data link's own: the
                # ground's broker hears one broker less.
                detected = link_detected = None
                while time.monotonic() - cut_at < cut_s:
                    elapsed = time.monotonic() - cut_at
                    if detected is None and not systems_up(client, fleet.systems):
                        detected = elapsed
                    if (link_detected is None and heard is not None
                            and peers(fleet.ground_broker) < heard):
                        link_detected = elapsed
                    time.sleep(POLL_S)
                fleet.restore(ROBOT)
                restored_at = time.monotonic()
                registered = wait_until(lambda: systems_up(client, fleet.systems), 120)
                if wait_until(lambda: first_after(arrivals, restored_at), 120) is None:
                    raise RuntimeError(f"{ROBOT}'s data never came back")
                results.append({"detected_s": detected, "link_detected_s": link_detected,
                                "data_back_s": first_after(arrivals, restored_at) - restored_at,
                                "registered_s": registered})
                time.sleep(3.0)
        finally:
            publisher.kill()
            publisher.wait()
            arrivals.stop()
            client.close()
    return results


def summary(values):
    values = [v for v in values if v is not None]
    if not values:
        return "never"
    return (f"{statistics.median(values):.1f} ({min(values):.1f}-{max(values):.1f})"
            if len(values) > 1 else f"{values[0]:.1f}")


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--build-dir", default=os.path.join(REPO, "build"))
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--cut-s", type=float, default=15.0)
    parser.add_argument("--out", default="")
    args = parser.parse_args()
    if os.geteuid() != 0:
        print("SKIPPED: needs root (network namespaces)")
        return 77
    results = {path: measure(os.path.abspath(args.build_dir), path, args.runs, args.cut_s)
               for path in ("nats", "broker")}
    print(f"({args.runs} cuts of {args.cut_s:g} s; median (min-max) s)")
    print("| data path | systems down (after the cut) | a broker less (after the cut) |"
          " data back (after the restore) | registered again (after the restore) |")
    print("|---|---|---|---|---|")
    for path, runs in results.items():
        print(f"| {path} | {summary([r['detected_s'] for r in runs])} | "
              f"{summary([r['link_detected_s'] for r in runs])} | "
              f"{summary([r['data_back_s'] for r in runs])} | "
              f"{summary([r['registered_s'] for r in runs])} |")
    if args.out:
        with open(args.out, "w") as f:
            json.dump(results, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
