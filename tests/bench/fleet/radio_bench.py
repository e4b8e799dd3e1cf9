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
import json
import os
import sys
import tempfile
import time

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.dirname(
    os.path.abspath(__file__)))))
sys.path.insert(0, os.path.join(REPO, "deploy", "fleet"))

import fleet as fleet_module  # noqa: E402
from fleet import demo, rpc  # noqa: E402


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


def measure(build_dir, path, idle_s, time_scale):
    run_dir = tempfile.mkdtemp(prefix=f"behaviorlib-radio-bench-{path}-")
    with fleet_module.Fleet(build_dir, run_dir, vehicles=3, say=lambda _: None,
                            data_path=path, time_scale=time_scale) as fleet:
        client = fleet.coordinator_client()
        fleet.wait_for_systems(client)
        time.sleep(2.0)
        idle = window(fleet, lambda: time.sleep(idle_s))
        flying = window(fleet, lambda: {
            robot: status.get("state") for robot, status in
            fleet_module.fly_swarm(fleet, client, 300.0, lambda _: None).items()})
        client.close()
    return {"idle": idle, "flying": flying}


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
    for path, phases in results.items():
        for phase, r in phases.items():
            walls = sorted(v["per_wall_s"] for v in r["links"].values())
            sims = sorted(v["per_sim_s"] or 0 for v in r["links"].values())
            missions = ", ".join(f"{k}: {v.replace('MISSION_STATE_', '')}"
                                 for k, v in (r["result"] or {}).items())
            print(f"| {path} | {phase} | {r['wall_s']:.1f} | {r['sim_s']:.1f} | "
                  f"{walls[1] / 1e3:.2f} ({walls[0] / 1e3:.2f}-{walls[-1] / 1e3:.2f}) | "
                  f"{sims[1] / 1e3:.2f} | {missions} |")
    if args.out:
        with open(args.out, "w") as f:
            json.dump(results, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
