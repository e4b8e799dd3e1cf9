"""The README's "Python" section, run as written: its install commands in a
fresh home directory, and its Python blocks against the real stack
(conftest.py) with $COORDINATOR set, as the section's text says."""

import os
import re
import shutil
import subprocess
import sys
import tempfile

import pytest

from behaviorlib import Fleet, _core
from behaviorlib import numpy_helpers as nph
from conftest import REPO


def readme_blocks():
    """{name: (language, code)} of the blocks marked readme_python_test."""
    with open(os.path.join(REPO, "README.md")) as f:
        text = f.read()
    return {name: (language, code) for name, language, code in re.findall(
        r"<!-- readme_python_test: (\w+) -->\n```(\w+)\n(.*?)```", text, re.DOTALL)}


def test_the_readme_marks_its_python_blocks():
    assert {name: language for name, (language, _) in readme_blocks().items()} == {
        "install": "sh", "sync": "python", "asyncio": "python", "telemetry": "python"}


def test_the_install_commands_make_a_venv_with_the_package():
    code = readme_blocks()["install"][1]
    left_behind = [os.path.join(REPO, "clients", "python", d)
                   for d in ("build", "behaviorlib.egg-info")]
    existed = [os.path.exists(d) for d in left_behind]
    home = tempfile.mkdtemp(prefix="behaviorlib-readme-")
    try:
        env = dict(os.environ, HOME=home, PIP_CONFIG_FILE=os.devnull,
                   PIP_DISABLE_PIP_VERSION_CHECK="1")
        env.pop("VIRTUAL_ENV", None)
        # Debian's python3, as on a fresh machine (not this venv's).
        env["PATH"] = "/usr/bin:/bin"
        subprocess.run(["bash", "-euc", code], cwd=REPO, env=env, check=True, timeout=300)
        python = os.path.join(home, "behaviorlib-venv", "bin", "python")
        out = subprocess.run([python, "-c", "import behaviorlib, behaviorlib.v1.coordinator_pb2 "
                              "as c; print(c.DESCRIPTOR.services_by_name['Coordinator'].name)"],
                             capture_output=True, text=True, check=True, env=env).stdout
        assert out.strip() == "Coordinator"
    finally:
        shutil.rmtree(home, ignore_errors=True)
        # pip builds in the source directory: leave it as it was.
        for directory, was_there in zip(left_behind, existed):
            if not was_there:
                shutil.rmtree(directory, ignore_errors=True)


def run_block(name, coordinator):
    completed = subprocess.run([sys.executable, "-c", readme_blocks()[name][1]], cwd=REPO,
                               env=dict(os.environ, COORDINATOR=coordinator),
                               capture_output=True, text=True, timeout=240)
    print(completed.stdout, completed.stderr)
    assert completed.returncode == 0, completed.stderr
    return completed.stdout


def test_the_sync_block_flies_and_runs_the_demo_mission(coordinator):
    out = run_block("sync", coordinator)
    lines = out.splitlines()
    assert lines[0].startswith("GOAL_ACHIEVED at 1.")
    assert lines[1].startswith("StatusCode.FAILED_PRECONDITION") and "LANDED" in lines[1]
    assert lines[2] == "SITUATION_NOT_SUITABLE SITUATION_REASON_FLIGHT_STATE", lines[2]
    assert lines[3] == "PARAMETER_OUT_OF_RANGE parameters.duration_s", lines[3]
    assert lines[4] == "GOAL_ACHIEVED"
    assert lines[5] == ("SUCCEEDED ['WAIT', 'TAKE_OFF', 'FOLLOW_PATH', "
                        "'ROTATE_WITH_PID_CONTROL', 'LAND']")


def test_the_asyncio_block_writes_a_belief_and_watches_an_event(coordinator):
    out = run_block("asyncio", coordinator)
    assert out.splitlines()[0] == "{'x': 1.0, 'y': 2.0}"
    assert "cause: TERMINATION_CAUSE_GOAL_ACHIEVED" in out


def test_the_telemetry_block_reads_the_vehicle_while_it_flies(coordinator):
    lines = run_block("telemetry", coordinator).splitlines()
    assert lines[0] == "1", lines  # FLIGHT_STATE_LANDED
    assert 0.0 < float(lines[1]) <= 1.0, lines
    cause, yaw = lines[2].split()
    # The heading it printed is the vehicle's (which the tests before may
    # have turned): the simulator's true one, to the printed 0.01 rad.
    with Fleet(coordinator) as fleet:
        truth = _core.unpack_sample(fleet.robot("drone1").sample("ground_truth_pose",
                                                                 max_age_s=None))
    assert cause == "GOAL_ACHIEVED" and float(yaw) == pytest.approx(nph.yaw(truth), abs=0.02), \
        (lines, nph.yaw(truth))
    assert lines[3] == "GOAL_ACHIEVED", lines
