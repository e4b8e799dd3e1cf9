#!/usr/bin/python3
"""Bytes on a vehicle's radio link, in the fleet across hosts
(deploy/fleet/fleet.py), for both data paths in the same run:

- nats: a broker per host, linked over NATS (decision 39);
- broker: the one broker on the ground, that every vehicle's systems and the
  simulator use over gRPC (the path before).

For each: at --time-scale (free running at 1x: a real vehicle's pace, so the
bytes per wall second are a radio's budget; 'max': the deterministic mode),
the fleet idle (systems registered, nothing active) for --idle-s,
then the three vehicles flying the swarm mission. The bytes are the vehicle
radio veth's counters (both directions: gRPC control plane, data, relay),
per second of wall time and per second of simulated time (the deterministic
mode runs at the machine's pace). Needs root; exits 77 otherwise.

    sudo /usr/bin/python3 tests/bench/fleet/radio_bench.py --build-dir build
"""

import argparse
import glob
import json
import os
import re
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
from fleet import demo, rpc  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import latency_probe  # noqa: E402

PROBE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "latency_probe.py")
# The latency probe: samples at a rate under the vehicles' --link-max-rate-hz
# (so that none is held back), enough for a p99.
PROBE_COUNT, PROBE_RATE_HZ = 300, 8.0


def link_bytes(fleet, robot):
    stats = f"/sys/class/net/{fleet.radio_veth(robot)}/statistics"
    with open(f"{stats}/rx_bytes") as rx, open(f"{stats}/tx_bytes") as tx:
        return int(rx.read()) + int(tx.read())


def sim_seconds(fleet):
    client = rpc.Client(fleet.simulator.address, [demo.SIMULATOR])
    call = client.stream(demo.SIMULATOR, "WatchState", {"robot_ids": [fleet.robots[0]]})
    try:
        state = rpc.to_dict(next(iter(call)).state)
    finally:
        call.cancel()
        client.close()
    return demo.timestamp_s(state["header"]["stamp"])


def window(fleet, run):
    """Runs `run()`; bytes per vehicle link per wall s and per simulated s."""
    before = {robot: link_bytes(fleet, robot) for robot in fleet.robots}
    wall0, sim0 = time.monotonic(), sim_seconds(fleet)
    result = run()
    wall, sim = time.monotonic() - wall0, sim_seconds(fleet) - sim0
    rates = {}
    for robot in fleet.robots:
        moved = link_bytes(fleet, robot) - before[robot]
        rates[robot] = {"bytes": moved, "per_wall_s": moved / wall,
                        "per_sim_s": moved / sim if sim > 0 else None}
    return {"wall_s": wall, "sim_s": sim, "links": rates, "result": result}


def percentile(values, q):
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))]


def delivery(fleet, host, robot):
    """One-way delays of samples published on `host` (its 127.0.0.1 broker
    address: the host's broker, or on the single-broker path the ground's
    through the radio's relay) and received from the ground's broker."""
    topic = f"robots/{robot}/latency_probe"
    follower = latency_probe.Follower(fleet.ground_broker.address, topic)
    time.sleep(2.0)  # the ground's want reaches every broker
    subprocess.run(["ip", "netns", "exec", fleet.ns(host), sys.executable, PROBE, "publish",
                    "--channel", f"127.0.0.1:{fleet_module.BROKER_PORT}", "--topic", topic,
                    "--count", str(PROBE_COUNT), "--rate-hz", str(PROBE_RATE_HZ)],
                   check=True, capture_output=True, timeout=PROBE_COUNT / PROBE_RATE_HZ + 60)
    time.sleep(1.0)
    delays = follower.stop()
    if not delays:
        return {"received": 0}
    return {"received": len(delays), "sent": PROBE_COUNT,
            "median_ms": statistics.median(delays) * 1e3,
            "p99_ms": percentile(delays, 0.99) * 1e3, "max_ms": max(delays) * 1e3}


def link_topics(address):
    """A broker's link counters per topic: {topic: samples out}."""
    with urllib.request.urlopen(f"http://{address}/metrics", timeout=10) as page:
        text = page.read().decode()
    out = {}
    for m in re.finditer(r'^behaviorlib_channel_link_samples_out_total\{topic="([^"]+)"\} (\S+)$',
                         text, re.M):
        out[m.group(1)] = float(m.group(2))
    return out


def relay_bytes(run_dir, robot):
    """What the vehicle's radio relay carried per mapping, as it printed at
    its exit: {"listen -> target": [towards the target, back]}."""
    carried = {}
    for path in glob.glob(os.path.join(run_dir, "**", f"radio_relay-{robot}*.log"),
                          recursive=True):
        with open(path) as f:
            for m in re.finditer(r"radio_relay: (\S+) -> (\S+): (\d+) bytes \S+ (\d+)",
                                 f.read()):
                carried[f"{m.group(1)} -> {m.group(2)}"] = [int(m.group(3)), int(m.group(4))]
    return carried


def measure(build_dir, path, idle_s, time_scale):
    run_dir = tempfile.mkdtemp(prefix=f"behaviorlib-radio-bench-{path}-")
    with fleet_module.Fleet(build_dir, run_dir, vehicles=3, say=lambda _: None,
                            data_path=path, time_scale=time_scale) as fleet:
        client = fleet.coordinator_client()
        fleet.wait_for_systems(client)
        time.sleep(2.0)
        idle = window(fleet, lambda: time.sleep(idle_s))
        # The floor: the same probe on the ground host itself (no radio).
        latency = {"floor (ground to ground)": delivery(fleet, "ground", "ground"),
                   "drone1 to ground": delivery(fleet, "drone1", "drone1")}
        flying = window(fleet, lambda: {
            robot: status.get("state") for robot, status in
            fleet_module.fly_swarm(fleet, client, 300.0, lambda _: None).items()})
        topics = (link_topics(fleet.by_robot["drone1"][-len(fleet.systems) - 1].metrics_address)
                  if path == "nats" else {})
        client.close()
    return {"idle": idle, "flying": flying, "latency": latency, "drone1_link_topics": topics,
            "drone1_relay_bytes": relay_bytes(run_dir, "drone1")}


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--build-dir", default=os.path.join(REPO, "build"))
    parser.add_argument("--idle-s", type=float, default=20.0)
    parser.add_argument("--out", default="")
    parser.add_argument("--time-scale", default="max",
                        help="'max' (the deterministic mode) or simulated s per wall s")
    args = parser.parse_args()
    if os.geteuid() != 0:
        print("SKIPPED: needs root (network namespaces)")
        return 77
    results = {path: measure(os.path.abspath(args.build_dir), path, args.idle_s, args.time_scale)
               for path in ("nats", "broker")}
    print("| data path | phase | wall s | simulated s | kB/s (wall) per vehicle link, median |"
          " kB per simulated s | missions |")
    print("|---|---|---|---|---|---|---|")
    if args.out:
        with open(args.out, "w") as f:
            json.dump(results, f, indent=1)
    for path, phases in results.items():
        for phase in ("idle", "flying"):
            r = phases[phase]
            walls = sorted(v["per_wall_s"] for v in r["links"].values())
            sims = sorted(v["per_sim_s"] or 0 for v in r["links"].values())
            missions = ", ".join(f"{k}: {v.replace('MISSION_STATE_', '')}"
                                 for k, v in (r["result"] or {}).items())
            print(f"| {path} | {phase} | {r['wall_s']:.1f} | {r['sim_s']:.1f} | "
                  f"{walls[1] / 1e3:.2f} ({walls[0] / 1e3:.2f}-{walls[-1] / 1e3:.2f}) | "
                  f"{sims[1] / 1e3:.2f} | {missions} |")
    print("\n| data path | from | samples received | median ms | p99 ms | max ms |")
    print("|---|---|---|---|---|---|")
    for path, r in results.items():
        for where, d in r["latency"].items():
            if not d.get("received"):
                print(f"| {path} | {where} | 0 | | | |")
                continue
            print(f"| {path} | {where} | {d['received']}/{d['sent']} | {d['median_ms']:.1f} | "
                  f"{d['p99_ms']:.1f} | {d['max_ms']:.1f} |")
    for path, r in results.items():
        print(f"\n{path}: drone1's relay, bytes per mapping (towards, back):")
        for mapping, (up, down) in sorted(r["drone1_relay_bytes"].items()):
            print(f"  {mapping}: {up} {down}")
        if r["drone1_link_topics"]:
            print(f"{path}: drone1's link, samples out per topic:")
            for topic, n in sorted(r["drone1_link_topics"].items(), key=lambda kv: -kv[1]):
                print(f"  {topic}: {n:.0f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
