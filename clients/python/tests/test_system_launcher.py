"""The local launcher (deploy/local/launch.py) starting a Python behavior system beside the C++
ones: --python-systems deterministic_wait_system.py in the deterministic mode, its behavior
activated through the coordinator with the Python client.

    BEHAVIORLIB_BUILD_DIR=build venv/bin/python -m pytest -q \
        clients/python/tests/test_system_launcher.py

The Python system runs on $BEHAVIORLIB_PYTHON, set here to this test's own interpreter unless
given (it has the behaviorlib package under test). Everything the launcher started is stopped at
the end (Ctrl-C, then SIGKILL of whatever is left), passed or failed.
"""

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile

import pytest

from behaviorlib import Fleet

from conftest import (BUILD_DIR, LAUNCHER, LAUNCHER_PYTHON, REPO, SERVING, Launcher,
                      barrier_notes, kill_launched, read_ports)

SCRIPT = os.path.join("clients", "python", "tests", "deterministic_wait_system.py")
PROCESS = "deterministic_wait_system"  # the script's file name
SYSTEM = "python_deterministic_waits"  # what the script registers
TICK_NS = 10_000_000


# The Python systems' interpreter: this one (it has the package under test) unless given.
PYTHON = os.environ.get("BEHAVIORLIB_PYTHON", sys.executable)


@pytest.fixture(scope="module")
def stack():
    run_dir = tempfile.mkdtemp(prefix="behaviorlib-python-launcher-")
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("BEHAVIORLIB_PYTHON", PYTHON)  # the launcher inherits it
        launcher = Launcher([
            LAUNCHER_PYTHON, LAUNCHER, "--build-dir", BUILD_DIR, "--run-dir", run_dir,
            "--time-scale", "max", "--vehicles", "drone1", "--no-console",
            "--systems", "quadrotor_motion_with_pid_control", "--python-systems", SCRIPT])
    failed = True
    try:
        launcher.wait_for(re.escape(SERVING), 120, "the launcher serving")
        yield launcher, run_dir
        failed = False
    finally:
        try:
            code = launcher.interrupt(timeout_s=60)
        finally:
            launcher.kill()
            kill_launched(run_dir)
        if failed:
            print(launcher.output()[-4000:], "\n".join(barrier_notes(run_dir)))
        else:
            # Stopped in order like the others: SIGTERM, then a clean exit.
            assert code == 128 + signal.SIGINT, launcher.output()[-4000:]
            assert re.search(rf"^  {PROCESS} +exited with code 0$", launcher.output(),
                             re.MULTILINE), launcher.output()[-4000:]
            assert f"{SYSTEM}: signal {signal.SIGTERM.value}, interrupting" in log(run_dir,
                                                                                  PROCESS)
        shutil.rmtree(run_dir, ignore_errors=True)


def log(run_dir, name):
    with open(os.path.join(run_dir, "logs", f"{name}.log"), errors="replace") as f:
        return f.read()


def address(run_dir, name):
    return f"127.0.0.1:{read_ports(os.path.join(run_dir, 'ports', f'{name}.ports'))['grpc_port']}"


def test_the_python_system_is_started_like_a_cpp_system(stack):
    launcher, run_dir = stack
    # Named after its script, listed with the others.
    assert re.search(rf"^  {PROCESS} +gRPC 127\.0\.0\.1:\d+", launcher.output(), re.MULTILINE)
    command = log(run_dir, PROCESS).splitlines()[0]
    simulator = address(run_dir, "simulator")
    assert command.startswith(f"$ {PYTHON} {os.path.join(REPO, SCRIPT)} ")
    for flags in (["--robot-id", "drone1"], ["--clock", "sim"],
                  ["--flight-controller", simulator], ["--follow-time", simulator],
                  ["--coordinator", address(run_dir, "coordinator")],
                  ["--listen", "127.0.0.1:0"], ["--port-file"]):
        assert " ".join(flags) in command, command
    # The simulator waited for it too: every system of the robot follows the grants.
    simulator_log = log(run_dir, "simulator")
    assert "waiting for 3 followers" in simulator_log
    assert f"simulator: {SYSTEM}/drone1 follows the time grants" in simulator_log
    # Its metrics are a Prometheus target, labelled with the system it registered.
    with open(os.path.join(run_dir, "prometheus_targets.json")) as f:
        targets = json.load(f)
    assert {"job": "behavior_system", "system": SYSTEM, "robot": "drone1"} in \
        [t["labels"] for t in targets]


def test_its_behavior_runs_through_the_coordinator_in_simulated_time(stack):
    _, run_dir = stack
    with Fleet(address(run_dir, "coordinator")) as fleet:
        assert [s.system for s in fleet.systems("drone1") if s.system == SYSTEM]
        drone = fleet.robot("drone1")
        assert "TEST_WAIT" in drone.behaviors
        ended = drone.test_wait(duration_s=1)
    assert ended.cause == "GOAL_ACHIEVED", ended
    # Deterministic: one simulated second to the tick, every tick at its time.
    assert 1.0 <= ended.active_duration_s < 1.0 + TICK_NS / 1e9
    measured = json.loads(ended.message)
    assert (measured["ticks"], measured["gaps_ns"]) == (100, [TICK_NS])


@pytest.mark.parametrize("flags, said", [
    (["--python-systems", "no/such/system.py"], "no/such/system.py is not a file"),
    (["--python-systems", f"{SCRIPT},{SCRIPT}"],
     f"a process is named {PROCESS} already"),
    (["--python-systems", SCRIPT, "--tls"], "Python behavior systems serve no TLS yet"),
])
def test_bad_python_systems_are_refused_before_anything_starts(flags, said):
    done = subprocess.run([LAUNCHER_PYTHON, LAUNCHER, "--build-dir", BUILD_DIR, *flags],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 2, done.stderr
    assert said in done.stderr
