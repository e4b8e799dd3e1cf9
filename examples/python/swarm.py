#!/usr/bin/env python3
"""Two vehicles (or more) flown at once with the asyncio client.

Each vehicle takes off to its own altitude, flies 2 m out along y and back,
and lands; the vehicles fly concurrently (asyncio.gather), each waiting only
for its own behaviors' terminations. Each vehicle also writes where it went
into belief memory (swarm_example/<robot>/turn_point_m), and the script reads
them back at the end.

Vehicle i starts at x = 2 i m, where the simulator places the vehicles of
--vehicles in an empty field (deploy/local/launch.py --vehicles drone1,drone2).

    build/venv/bin/python examples/python/swarm.py --coordinator 127.0.0.1:PORT \\
        --robots drone1,drone2

Exit code 0 when every vehicle's every behavior achieved its goal.
"""

import argparse
import asyncio
import sys

from behaviorlib import aio


async def fly(fleet, robot_id, x_m, altitude_m):
    drone = await fleet.robot(robot_id)
    localize = await drone.self_localize_with_ground_truth.start()
    results = []
    try:
        results.append(await drone.take_off(altitude_m=altitude_m))
        turn_point = {"x": x_m, "y": 2.0, "z": altitude_m}
        await fleet.beliefs.write(f"swarm_example/{robot_id}/turn_point_m", turn_point,
                                  writer=f"{robot_id}/swarm.py")
        if results[-1].succeeded:
            results.append(await drone.follow_path(
                path_m=[turn_point, {"x": x_m, "y": 0.0, "z": altitude_m}], speed_m_s=1.0))
        results.append(await drone.land())
    finally:
        await localize.deactivate()
    for result in results:
        print(f"{robot_id}: {result.behavior} {result.cause} ({result.message})")
    return all(result.succeeded for result in results)


async def main(args):
    robots = args.robots.split(",")
    async with aio.Fleet(args.coordinator) as fleet:
        flown = await asyncio.gather(*[
            fly(fleet, robot_id, 2.0 * i, 1.0 + 0.5 * i) for i, robot_id in enumerate(robots)])
        for belief in await fleet.beliefs.list(prefix="swarm_example/"):
            print(f"{belief.key} = {aio.Beliefs.value(belief)} (by {belief.writer})")
    print("swarm succeeded" if all(flown) else "swarm failed")
    return 0 if all(flown) else 1


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--coordinator", required=True, help="host:port")
    parser.add_argument("--robots", default="drone1,drone2")
    sys.exit(asyncio.run(main(parser.parse_args())))
