"""CIRCLE_AROUND (examples/python_behavior) flown in a mission beside the C++ systems: the local
launcher in the deterministic mode starts the Python system with the C++ ones, the coordinator's
catalog plan activates the motion controller, and the vehicle's true path (read through the
client's telemetry) goes once around the circle."""

import math
import os
import re
import shutil
import tempfile
import threading

import pytest

from behaviorlib import Fleet, mission_state
from behaviorlib import numpy_helpers as nph

from conftest import BUILD_DIR, LAUNCHER, LAUNCHER_PYTHON, REPO, SERVING, Launcher, barrier_notes
from conftest import kill_launched, read_ports

EXAMPLE = os.path.join(REPO, "examples", "python_behavior")
CENTER, RADIUS, ALTITUDE = (2.0, 0.0), 1.5, 1.5


@pytest.fixture(scope="module")
def stack():
    run_dir = tempfile.mkdtemp(prefix="behaviorlib-circle-")
    launcher = Launcher([
        LAUNCHER_PYTHON, LAUNCHER, "--build-dir", BUILD_DIR, "--run-dir", run_dir,
        "--time-scale", "max", "--vehicles", "drone1",
        "--systems", "quadrotor_motion_with_pid_control",
        "--python-systems", os.path.join("examples", "python_behavior", "system.py")])
    failed = True
    try:
        launcher.wait_for(re.escape(SERVING), 120, "the launcher serving")
        ports = read_ports(os.path.join(run_dir, "ports", "coordinator.ports"))
        yield f"127.0.0.1:{ports['grpc_port']}"
        failed = False
    finally:
        try:
            launcher.interrupt(timeout_s=60)
        finally:
            launcher.kill()
            kill_launched(run_dir)
        if failed:
            print(launcher.output()[-4000:], "\n".join(barrier_notes(run_dir)))
        shutil.rmtree(run_dir, ignore_errors=True)


def test_the_python_behavior_flies_its_circle_in_a_mission(stack):
    with Fleet(stack) as fleet:
        drone = fleet.robot("drone1")
        assert "CIRCLE_AROUND" in drone.behaviors
        assert [s.system for s in fleet.systems("drone1") if s.system == "python_circle_around"]
        # The true path, while the mission flies.
        path = []
        poses = drone.subscribe("ground_truth_pose", max_rate_hz=200)
        reader = threading.Thread(target=lambda: path.extend(nph.position(p) for p in poses))
        reader.start()
        try:
            status = fleet.missions.run(file=os.path.join(EXAMPLE, "circle_mission.yaml"),
                                        timeout_s=240)
        finally:
            poses.close()
            reader.join(30)
    steps = {step.name: step for step in status.steps}
    assert mission_state(status) == "SUCCEEDED", status
    circle = steps["circle"]
    print(circle.message, f"({len(path)} true poses read)")
    assert circle.behavior == "CIRCLE_AROUND"
    assert re.match(r"flew 1 turns of 1\.5 m around \(2, 0, 1\.5\) in [\d.]+ s; max distance "
                    r"from the reference [\d.]+ m", circle.message), circle.message
    # Where the vehicle flew on the circle (within 0.3 m of it), by 20-degree sector: every
    # sector of the turn was flown through.
    sectors = set()
    for x, y, z in path:
        distance = math.hypot(x - CENTER[0], y - CENTER[1])
        if abs(distance - RADIUS) <= 0.3 and abs(z - ALTITUDE) <= 0.3:
            sectors.add(int(math.degrees(math.atan2(y - CENTER[1], x - CENTER[0])) % 360 // 20))
    assert sectors == set(range(18)), sorted(sectors)
