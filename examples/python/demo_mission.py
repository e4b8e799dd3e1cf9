#!/usr/bin/env python3
"""The demo mission (deploy/missions/demo.yaml) as a Python script.

SELF_LOCALIZE_WITH_GROUND_TRUTH stays active throughout; then WAIT 1 s,
TAKE_OFF to 1.5 m (tried again up to twice when refused), FOLLOW_PATH along a
4 m square at 1 m/s (again once on WRONG_PROGRESS), ROTATE_WITH_PID_CONTROL
90 degrees left, and LAND; LAND also when a step fails. Each behavior's
method waits for its termination and returns it. The coordinator's catalog
activates what a behavior needs (FOLLOW_PATH's motion controller).

    /usr/bin/python3 deploy/local/launch.py --systems quadrotor_motion_with_pid_control
    build/venv/bin/python examples/python/demo_mission.py --coordinator 127.0.0.1:PORT

Exit code 0 when every step achieved its goal.
"""

import argparse
import math
import sys

import behaviorlib
from behaviorlib import Fleet

ALTITUDE_M = 1.5
SQUARE_M = [{"x": 4.0, "y": 0.0, "z": ALTITUDE_M}, {"x": 4.0, "y": 4.0, "z": ALTITUDE_M},
            {"x": 0.0, "y": 4.0, "z": ALTITUDE_M}, {"x": 0.0, "y": 0.0, "z": ALTITUDE_M}]


def attempt(name, behavior, parameters, retry_on=(), retries=0):
    """Runs one step: the behavior's termination, tried again `retries` times
    when it ends with a cause in `retry_on` (or is refused, with
    "REFUSED")."""
    for tried in range(retries + 1):
        last = tried == retries
        try:
            result = behavior(**parameters)
        except behaviorlib.FailedPrecondition as refused:
            print(f"{name}: refused: {refused.message}")
            if "REFUSED" not in retry_on or last:
                raise
            continue
        print(f"{name}: {result.behavior} {result.cause} ({result.message})")
        if result.cause not in retry_on or last:
            return result
    raise AssertionError("unreachable")


def fly(drone):
    steps = [
        ("settle", drone.wait, {"duration_s": 1.0}, (), 0),
        ("take_off", drone.take_off, {"altitude_m": ALTITUDE_M}, ("REFUSED",), 2),
        ("fly_square", drone.follow_path, {"path_m": SQUARE_M, "speed_m_s": 1.0},
         ("WRONG_PROGRESS",), 1),
        ("turn_left", drone.rotate_with_pid_control, {"yaw_rad": math.pi / 2, "relative": True},
         (), 0),
        ("land", drone.land, {}, (), 0),
    ]
    for name, behavior, parameters, retry_on, retries in steps:
        if not attempt(name, behavior, parameters, retry_on, retries).succeeded:
            return False
    return True


def main(argv):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--coordinator", required=True, help="host:port")
    parser.add_argument("--robot", default="drone1")
    args = parser.parse_args(argv)

    with Fleet(args.coordinator) as fleet:
        drone = fleet.robot(args.robot)
        localize = drone.self_localize_with_ground_truth.start()
        succeeded = False
        try:
            succeeded = fly(drone)
        except behaviorlib.Error as error:
            print(f"failed: {error}")
        finally:
            if not succeeded:
                print(f"safety: {drone.land()}")  # the mission file's safety step
            localize.deactivate()
    print("mission succeeded" if succeeded else "mission failed")
    return 0 if succeeded else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
