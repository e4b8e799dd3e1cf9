"""The real stack for the client's tests: deploy/local/launch.py serving on
free loopback ports, in the deterministic mode (--time-scale max: simulated
time advances in lock-step, so a loaded machine slows the flights instead of
failing them), with the vehicles drone1 and drone2.

    BEHAVIORLIB_BUILD_DIR=build venv/bin/python -m pytest clients/python/tests
"""

import json
import os
import re
import shutil
import signal
import sys
import tempfile

import pytest

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", "..", ".."))
# The repository's helpers: the launcher's port files, the tests' polling and
# their launcher runner (its output read on a thread).
sys.path[:0] = [os.path.join(REPO, "deploy", "local"), os.path.join(REPO, "tests", "deploy"),
                os.path.join(REPO, "tests", "e2e")]
from deploy_support import wait_for as wait_until  # noqa: E402
from local_demo_test import kill_launched  # noqa: E402
from local_restart_test import Launcher  # noqa: E402
from stack import read_ports  # noqa: E402

BUILD_DIR = os.path.abspath(os.environ.get("BEHAVIORLIB_BUILD_DIR", os.path.join(REPO, "build")))
LAUNCHER = os.path.join(REPO, "deploy", "local", "launch.py")
SERVING = "Ctrl-C stops everything."
# Debian's interpreter runs the launcher (it needs only python3-grpcio and
# python3-protobuf, not this package).
LAUNCHER_PYTHON = "/usr/bin/python3" if os.path.exists("/usr/bin/python3") else sys.executable


class Stack:
    """The launcher serving (local_restart_test.Launcher)."""

    def __init__(self, vehicles, systems):
        self.run_dir = tempfile.mkdtemp(prefix="behaviorlib-python-")
        self.launcher = Launcher([
            LAUNCHER_PYTHON, LAUNCHER, "--build-dir", BUILD_DIR, "--run-dir", self.run_dir,
            "--time-scale", "max", "--vehicles", ",".join(vehicles), "--systems",
            ",".join(systems)])
        self.launcher.wait_for(re.escape(SERVING), 120, "the launcher serving")

    def ports(self, name):
        return read_ports(os.path.join(self.run_dir, "ports", name + ".ports"))

    @property
    def coordinator(self):
        return f"127.0.0.1:{self.ports('coordinator')['grpc_port']}"

    def pid(self, name):
        with open(os.path.join(self.run_dir, "pids.json")) as f:
            return json.load(f)[name]

    def kill(self, name):
        """SIGKILL to a process of the stack; the launcher starts it again on
        its ports. Returns once the new process runs."""
        old = self.pid(name)
        os.kill(old, signal.SIGKILL)
        return wait_until(lambda: self.pid(name) if self.pid(name) != old else None, 30,
                          f"{name} restarted by the launcher")

    def stop(self):
        """Ctrl-C; its output."""
        try:
            self.launcher.interrupt(timeout_s=60)
        finally:
            self.launcher.kill()
            kill_launched(self.run_dir)
        return self.launcher.output()


def barrier_notes(run_dir):
    """The lines of the stack's logs in which the deterministic mode's
    bounded waits gave up (a follower left out, a granted sample not
    waited for): what to look at first when a flight failed."""
    notes = []
    logs = os.path.join(run_dir, "logs")
    for name in sorted(os.listdir(logs)) if os.path.isdir(logs) else []:
        with open(os.path.join(logs, name), errors="replace") as f:
            notes += [f"{name}: {line.rstrip()}" for line in f
                      if "did not catch up" in line or "did not arrive" in line]
    return notes


@pytest.fixture(scope="session")
def stack(request):
    # The motion controller, and the EKF the demo mission localizes with.
    stack = Stack(["drone1", "drone2"], ["quadrotor_motion_with_pid_control", "multi_sensor_fusion"])
    yield stack
    print(stack.stop())
    if request.session.testsfailed:
        # Kept for the failure's logs, and said past pytest's capture (a
        # session fixture's teardown output is shown for no test).
        capture = request.config.pluginmanager.getplugin("capturemanager")
        with capture.global_and_fixture_disabled():
            print(f"\nrun directory kept: {stack.run_dir}")
            print("\n".join(barrier_notes(stack.run_dir)) or "no bounded wait gave up")
    else:
        shutil.rmtree(stack.run_dir, ignore_errors=True)


@pytest.fixture(scope="session")
def coordinator(stack):
    return stack.coordinator
