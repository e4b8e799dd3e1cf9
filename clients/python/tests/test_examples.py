"""examples/python/ run as a user runs them, against the real stack
(conftest.py): the demo mission as a script, and two vehicles at once."""

import ast
import os
import re
import subprocess
import sys

from conftest import REPO

EXAMPLES = os.path.join(REPO, "examples", "python")


def run_example(name, *args):
    completed = subprocess.run([sys.executable, os.path.join(EXAMPLES, name), *args],
                               capture_output=True, text=True, timeout=240)
    print(completed.stdout, completed.stderr)
    return completed


def test_the_demo_mission_script_flies_every_step(coordinator):
    completed = run_example("demo_mission.py", "--coordinator", coordinator, "--robot", "drone1")
    assert completed.returncode == 0, completed.stdout + completed.stderr
    steps = re.findall(r"^(\w+): (\w+) (\w+) \(", completed.stdout, re.MULTILINE)
    assert steps == [("settle", "WAIT", "GOAL_ACHIEVED"), ("take_off", "TAKE_OFF", "GOAL_ACHIEVED"),
                     ("fly_square", "FOLLOW_PATH", "GOAL_ACHIEVED"),
                     ("turn_left", "ROTATE_WITH_PID_CONTROL", "GOAL_ACHIEVED"),
                     ("land", "LAND", "GOAL_ACHIEVED")], completed.stdout
    assert completed.stdout.rstrip().endswith("mission succeeded")


def test_the_swarm_script_flies_two_vehicles_at_once(coordinator):
    completed = run_example("swarm.py", "--coordinator", coordinator, "--robots", "drone1,drone2")
    assert completed.returncode == 0, completed.stdout + completed.stderr
    for robot in ("drone1", "drone2"):
        flown = re.findall(rf"^{robot}: (\w+) (\w+) \(", completed.stdout, re.MULTILINE)
        assert flown == [("TAKE_OFF", "GOAL_ACHIEVED"), ("FOLLOW_PATH", "GOAL_ACHIEVED"),
                         ("LAND", "GOAL_ACHIEVED")], completed.stdout
    turn_points = dict(re.findall(r"^swarm_example/(\w+)/turn_point_m = (\{.*\}) \(by ",
                                  completed.stdout, re.MULTILINE))
    assert {robot: ast.literal_eval(point) for robot, point in turn_points.items()} == {
        "drone1": {"x": 0.0, "y": 2.0, "z": 1.0}, "drone2": {"x": 2.0, "y": 2.0, "z": 1.5}}
    assert completed.stdout.rstrip().endswith("swarm succeeded")
