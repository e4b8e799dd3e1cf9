"""End to end: the local launcher's supervision (deploy/local/launch.py
--restart, on-failure by default) against the real binaries, kill -9 at the
worst moments.

    /usr/bin/python3 tests/e2e/local_restart_test.py --build-dir build

test_motion_system_killed_in_flight: a light stack (--systems
quadrotor_motion_with_pid_control,multi_sensor_fusion) serving; the test flies
deploy/missions/demo.yaml through the coordinator (demo.run_mission, as
--demo does) and, while FOLLOW_PATH flies the vehicle, SIGKILLs
quadrotor_motion_with_pid_control. Then the motion controller
(QUADROTOR_PID_MOTION_CONTROL) finished PROCESS_FAILURE, the coordinator's
safety rule fired (hover, then land: on that failure or on the lease
failsafe it causes, whichever it saw first) and the vehicle is LANDED
(ground truth), the mission did not succeed; the launcher restarted the
process (its line, a new pid in pids.json) and the new process registered
with the coordinator again (UP, a new incarnation, the same address: it kept
its port); the rest of the stack kept running (same pids); Ctrl-C stops
everything, and the launcher prints the restart.

The launcher serves (no --demo) because the demo ends with the mission,
which the safety rule aborts at once: the launcher would then stop the stack
before the vehicle is down and perhaps before the new process registered.

test_motion_system_killed_during_demo: the same kill under --demo: the
launcher starts the restart while the demo runs, the mission ends without
success (exit code 1), and the report is written with the restart counted
(report.json and report.md) and the PROCESS_FAILURE in its timeline.

test_coordinator_killed: the coordinator SIGKILLed comes back on its port
(the systems dial it there), and the behavior systems register with it
again.

test_restart_no: with --restart no a killed process stops the stack (exit
code 1, the reason on stderr), as before the supervision existed.
"""

import argparse
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
import unittest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from local_demo_test import (BUILD_DIR, LAUNCHER, REPO, alive, kill_launched,  # noqa: E402
                             launched_pids)

sys.path.insert(0, os.path.dirname(LAUNCHER))
import demo  # noqa: E402
import rpc  # noqa: E402
from stack import read_ports  # noqa: E402

sys.path.insert(0, os.path.join(REPO, "tests", "deploy"))
from deploy_support import wait_for  # noqa: E402

ROBOT = "drone1"
MOTION_SYSTEM = "quadrotor_motion_with_pid_control"
MOTION_CONTROLLER = "QUADROTOR_PID_MOTION_CONTROL"
# The demo mission's EKF.
FUSION_SYSTEM = "multi_sensor_fusion"
SYSTEMS = ["basic_quadrotor_behaviors", MOTION_SYSTEM, FUSION_SYSTEM]
DEMO_MISSION = os.path.join(REPO, "deploy", "missions", "demo.yaml")
# As local_demo_test.py: the deterministic mode, where a loaded machine slows
# the mission instead of failing it.
TIME_SCALE = "max"
# How long FOLLOW_PATH flies before the kill (wall seconds): the vehicle is
# then well under way along the square.
FLY_BEFORE_KILL_S = 1.0
STACK_SERVING = "Ctrl-C stops everything."
AIRBORNE = ("FLIGHT_STATE_TAKING_OFF", "FLIGHT_STATE_FLYING", "FLIGHT_STATE_HOVERING")


def restarting_line(name):
    """The launcher's line (a regex) when it restarts `name` after a SIGKILL."""
    return (rf"^  {name} exited with signal 9 \(SIGKILL\); restarting in [0-9.]+ s "
            r"\(restart 1\)$")


class Launcher:
    """The launcher running, its output (stdout and stderr) read on a
    thread."""

    def __init__(self, argv):
        self.process = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                        text=True)
        self._lock = threading.Lock()
        self._lines = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self):
        for line in self.process.stdout:
            with self._lock:
                self._lines.append(line)

    def output(self):
        with self._lock:
            return "".join(self._lines)

    def wait_for(self, pattern, timeout_s, what):
        """The first match of `pattern` (lines) in the output within
        timeout_s; AssertionError naming `what` otherwise, at once when the
        launcher has exited."""
        def seen():
            exited = self.process.poll() is not None
            if exited:
                self._reader.join(timeout=5)  # its last lines
            match = re.search(pattern, self.output(), re.MULTILINE)
            if exited and not match:
                raise AssertionError(f"{what}: the launcher exited with code "
                                     f"{self.process.returncode} (its output is in the test log)")
            return match

        return wait_for(seen, timeout_s, f"{what} (the launcher's output is in the test log)")

    def wait_exit(self, timeout_s):
        """The exit code; the output read to its end."""
        code = self.process.wait(timeout=timeout_s)
        self._reader.join(timeout=5)
        self.process.stdout.close()
        return code

    def interrupt(self, timeout_s=30):
        """Ctrl-C: the exit code once every process is stopped."""
        self.process.send_signal(signal.SIGINT)
        return self.wait_exit(timeout_s)

    def kill(self):
        """SIGKILL (after a failure), unless it has exited."""
        if self.process.poll() is None:
            self.process.kill()
        self.wait_exit(10)


class MissionThread(threading.Thread):
    """demo.run_mission on a thread: `statuses` as they come, `final` (or
    `error`) at the end."""

    def __init__(self, coordinator, mission_path, mission_id, timeout_s):
        super().__init__(name="mission", daemon=True)
        self._args = (coordinator, mission_path, ROBOT, mission_id, timeout_s)
        self.progress = []
        self.statuses = []
        self.final = None
        self.error = None

    def run(self):
        try:
            self.final = demo.run_mission(*self._args, self.progress.append,
                                          self.statuses.append)
        except rpc.grpc.RpcError as error:
            self.error = f"{error.code().name}: {error.details()}"

    def step_running(self, behavior):
        """True while the latest status has a step of `behavior` running."""
        steps = self.statuses[-1].get("steps", []) if self.statuses else []
        return any(s.get("behavior") == behavior and s.get("state") == "MISSION_STEP_STATE_RUNNING"
                   for s in steps)


class LocalRestartTest(unittest.TestCase):
    def setUp(self):
        self.run_dir = tempfile.mkdtemp(prefix="local-restart-e2e-")
        self.launcher = None
        self.clients = []
        self.recorders = []
        self.passed = False

    def tearDown(self):
        for recorder in self.recorders:
            recorder.stop()
        for client in self.clients:
            client.close()
        if self.launcher is not None:
            self.launcher.kill()
            print(self.launcher.output())
        kill_launched(self.run_dir)
        if self.passed:
            shutil.rmtree(self.run_dir, ignore_errors=True)
        else:
            print(f"run directory kept: {self.run_dir}", file=sys.stderr)

    # --- helpers ----------------------------------------------------------------

    def _argv(self, *extra):
        """The launcher's command line for the light stack."""
        return [sys.executable, LAUNCHER, "--build-dir", BUILD_DIR, "--run-dir", self.run_dir,
                "--time-scale", TIME_SCALE, "--systems", f"{MOTION_SYSTEM},{FUSION_SYSTEM}",
                *extra]

    def _serve(self, *extra):
        """Starts the launcher serving the light stack; returns once it does."""
        self.launcher = Launcher(self._argv(*extra))
        self.launcher.wait_for(re.escape(STACK_SERVING), 40, "the launcher serving")

    def _client(self, process, service):
        ports = read_ports(os.path.join(self.run_dir, "ports", process + ".ports"))
        client = rpc.Client(f"127.0.0.1:{ports['grpc_port']}", [service])
        self.clients.append(client)
        return client

    def _recorder(self, recorder):
        recorder.start()
        self.recorders.append(recorder)
        return recorder

    def _kill(self, name):
        """SIGKILLs a process of the stack; its pid."""
        pid = launched_pids(self.run_dir)[name]
        os.kill(pid, signal.SIGKILL)
        return pid

    def _wait_restarted(self, name, old_pid, timeout_s=20):
        """The new pid of `name` once pids.json names one that runs, and the
        launcher printed the restart; asserts both."""
        def new_pid():
            pid = launched_pids(self.run_dir).get(name)
            return pid if pid not in (None, old_pid) and alive(pid) else None

        pid = wait_for(new_pid, timeout_s, f"a new {name} process in pids.json")
        self.launcher.wait_for(restarting_line(name), 5, f"the launcher saying it restarts {name}")
        self.launcher.wait_for(rf"^  {name} restarted: pid {pid}, ", timeout_s,
                               f"the launcher saying {name} restarted")
        return pid

    def _system(self, coordinator, name):
        """The coordinator's SystemInfo of `name` (dict), {} when it has none."""
        reply = coordinator.call(demo.COORDINATOR, "ListSystems", {"robot_id": ROBOT})
        return next((s for s in reply.get("systems", []) if s.get("system") == name), {})

    def _stop(self, restarted):
        """Ctrl-C; asserts that every process stopped, each restarted one
        said so."""
        code = self.launcher.interrupt()
        output = self.launcher.output()
        self.assertEqual(code, 130, "the launcher's exit code after Ctrl-C")
        for name in restarted:
            self.assertRegex(output, rf"{name} +exited with code 0; restarted 1 time\n")
        self._assert_all_stopped()

    def _assert_all_stopped(self):
        left = {name: pid for name, pid in launched_pids(self.run_dir).items() if alive(pid)}
        self.assertEqual(left, {}, "processes left running after the launcher exited")

    # --- tests ------------------------------------------------------------------

    def test_motion_system_killed_in_flight(self):
        started = time.monotonic()
        self._serve()
        coordinator = self._client("coordinator", demo.COORDINATOR)
        simulator = self._client("simulator", demo.SIMULATOR)
        events = self._recorder(demo.EventRecorder(coordinator, ROBOT))
        trajectory = self._recorder(demo.TrajectoryRecorder(simulator, ROBOT))
        demo.wait_for_systems(coordinator, ROBOT, SYSTEMS)
        before = self._system(coordinator, MOTION_SYSTEM)
        others = {name: pid for name, pid in launched_pids(self.run_dir).items()
                  if name != MOTION_SYSTEM}

        mission = MissionThread(coordinator, DEMO_MISSION, "restart-e2e", 60)
        mission.start()
        wait_for(lambda: mission.step_running("FOLLOW_PATH"), 30, "FOLLOW_PATH running")
        time.sleep(FLY_BEFORE_KILL_S)
        self.assertTrue(mission.step_running("FOLLOW_PATH"), mission.progress)
        flown_before_kill = len(trajectory.snapshot())
        self.assertIn(trajectory.snapshot()[-1][4], AIRBORNE)
        old_pid = self._kill(MOTION_SYSTEM)

        # The coordinator: the controller failed, the safety rule landed the
        # vehicle, the mission ended without success.
        mission.join(30)
        print("".join(line + "\n" for line in mission.progress))
        self.assertFalse(mission.is_alive(), "the mission did not end")
        self.assertIsNone(mission.error)
        self.assertIn(mission.final["state"], ("MISSION_STATE_ABORTED", "MISSION_STATE_FAILED"))
        wait_for(lambda: trajectory.snapshot()[-1][4] == "FLIGHT_STATE_LANDED", 30,
                 "the vehicle LANDED")
        after_kill = trajectory.snapshot()[flown_before_kill:]
        self.assertGreater(max(z for _, _, _, z, _ in after_kill), 1.0, "it was flying")
        self.assertLess(after_kill[-1][3], 0.3)
        # The controller's PROCESS_FAILURE comes once the coordinator's
        # grace period (wall time) has passed; the mission may have ended
        # before, by the platform's lease failsafe (simulated time, which the
        # deterministic mode runs fast).
        def failures():
            return [e for e in events.behavior_events()
                    if e.get("behavior") == MOTION_CONTROLLER
                    and e.get("finished", {}).get("cause") == "TERMINATION_CAUSE_PROCESS_FAILURE"]
        wait_for(failures, 15, f"{MOTION_CONTROLLER} ended PROCESS_FAILURE")
        self.assertEqual(len(failures()), 1, events.behavior_events())
        with open(os.path.join(self.run_dir, "logs", "coordinator.log")) as f:
            self.assertRegex(f.read(), rf"coordinator: safety: {ROBOT}: .*hover, then land")

        # The launcher: restarted on its port, registered again; the rest
        # ran on.
        new_pid = self._wait_restarted(MOTION_SYSTEM, old_pid)

        def registered_again():
            system = self._system(coordinator, MOTION_SYSTEM)
            return system if (system.get("state") == "SYSTEM_STATE_UP"
                              and system.get("incarnation") != before["incarnation"]) else None

        after = wait_for(registered_again, 20, f"{MOTION_SYSTEM} registered again")
        self.assertEqual(after["address"], before["address"], "the port changed")
        pids = launched_pids(self.run_dir)
        self.assertEqual(pids[MOTION_SYSTEM], new_pid)
        self.assertEqual({name: pids[name] for name in others}, others)
        self.assertTrue(all(alive(pid) for pid in others.values()))
        with open(os.path.join(self.run_dir, "logs", MOTION_SYSTEM + ".log")) as f:
            log = f.read()
        self.assertEqual(log.count("\n$ "), 1, "one restart appended to the log")
        self.assertIn(f"launch.py: {MOTION_SYSTEM} exited with signal 9", log)

        self._stop([MOTION_SYSTEM])
        print(f"test_motion_system_killed_in_flight: {time.monotonic() - started:.1f} s wall")
        self.passed = True

    def test_motion_system_killed_during_demo(self):
        started = time.monotonic()
        self.launcher = Launcher(self._argv("--demo"))
        self.launcher.wait_for(r"fly_square \(FOLLOW_PATH\): running$", 40, "FOLLOW_PATH running")
        time.sleep(FLY_BEFORE_KILL_S)
        self._kill(MOTION_SYSTEM)
        code = self.launcher.wait_exit(60)
        output = self.launcher.output()
        # The demo ends with the aborted mission and stops the stack, maybe
        # before the restart is done (stopping cancels it): only its start
        # is certain.
        self.assertRegex(output, re.compile(restarting_line(MOTION_SYSTEM), re.MULTILINE))
        self.assertNotIn("Traceback", output)
        self.assertEqual(code, 1, "the mission cannot have succeeded")
        self._assert_all_stopped()

        with open(os.path.join(self.run_dir, "report.json")) as f:
            report = json.load(f)
        self.assertIn(report["mission"]["state"], ("MISSION_STATE_ABORTED",
                                                   "MISSION_STATE_FAILED"))
        processes = {p["name"]: p for p in report["processes"]}
        self.assertEqual(processes.pop(MOTION_SYSTEM)["restarts"], 1)
        self.assertEqual({(p["restarts"], p["exit_code"]) for p in processes.values()}, {(0, 0)})
        self.assertIn(("finished", "PROCESS_FAILURE"),
                      {(r["event"], r.get("cause")) for r in report["timeline"]
                       if r["behavior"] == MOTION_CONTROLLER})
        with open(os.path.join(self.run_dir, "report.md")) as f:
            self.assertRegex(f.read(), rf"\n\| {MOTION_SYSTEM} \| [^\n]* \| 1 \|\n")
        print(f"test_motion_system_killed_during_demo: {time.monotonic() - started:.1f} s wall")
        self.passed = True

    def test_coordinator_killed(self):
        started = time.monotonic()
        self._serve()
        coordinator = self._client("coordinator", demo.COORDINATOR)
        demo.wait_for_systems(coordinator, ROBOT, SYSTEMS)

        old_pid = self._kill("coordinator")
        self._wait_restarted("coordinator", old_pid)
        # The new process listens where the systems (and the client) dial.
        ports = read_ports(os.path.join(self.run_dir, "ports", "coordinator.ports"))
        self.assertEqual(f"127.0.0.1:{ports['grpc_port']}", coordinator.address,
                         "the port changed")

        def systems_up():
            try:
                demo.wait_for_systems(coordinator, ROBOT, SYSTEMS)
                return True
            except rpc.grpc.RpcError:  # a call on the killed process's connection
                return False

        wait_for(systems_up, 20, "the systems UP at the restarted coordinator")

        self._stop(["coordinator"])
        print(f"test_coordinator_killed: {time.monotonic() - started:.1f} s wall")
        self.passed = True

    def test_restart_no(self):
        self._serve("--restart", "no")
        self._kill(MOTION_SYSTEM)
        code = self.launcher.wait_exit(30)
        self.assertEqual(code, 1)
        self.assertRegex(self.launcher.output(),
                         rf"launch.py: {MOTION_SYSTEM} exited with signal 9 \(SIGKILL\); not "
                         r"restarted \(--restart no\)")
        self._assert_all_stopped()
        self.passed = True


if __name__ == "__main__":
    parser = argparse.ArgumentParser()
    parser.add_argument("--build-dir", default=BUILD_DIR)
    args, rest = parser.parse_known_args()
    BUILD_DIR = os.path.abspath(args.build_dir)
    unittest.main(argv=[sys.argv[0], *rest], verbosity=2)
