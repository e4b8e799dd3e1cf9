"""A behavior system built outside this repository, against the installed
behaviorlib (issue 15 goal 6; docs/writing-a-behavior.md).

Installs the build tree (`cmake --install`) into a temporary prefix, builds
examples/out_of_tree_behavior against it with find_package(behaviorlib), and
runs its `greeter` system with the real coordinator (on loopback, ports
chosen free): the coordinator's catalog plan activates KEEP_COUNTING for
SAY_HELLO, SAY_HELLO ends GOAL_ACHIEVED, a bad parameter is refused naming
it, and reflection shows the generated typed services. Every code block of
docs/writing-a-behavior.md is a file of the example (so it is compiled
here) or a command this test runs.

  out_of_tree_test.py --build-dir build
"""

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
import unittest

REPO = os.path.abspath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", ".."))
sys.path.insert(0, os.path.join(REPO, "deploy", "local"))

import grpc  # noqa: E402

import demo  # noqa: E402
import reflection_client as rc  # noqa: E402
import rpc  # noqa: E402

EXAMPLE = os.path.join(REPO, "examples", "out_of_tree_behavior")
TUTORIAL = os.path.join(REPO, "docs", "writing-a-behavior.md")
COORDINATOR = "behaviorlib.v1.Coordinator"
BUILD_DIR = None
TIMEOUT_S = 30


def run(command, cwd, env=None, timeout=600):
    result = subprocess.run(command, cwd=cwd, env=env, shell=True, capture_output=True,
                            text=True, timeout=timeout, check=False)
    if result.returncode != 0:
        raise AssertionError(f"`{command}` failed ({result.returncode}):\n"
                             f"{result.stdout[-3000:]}\n{result.stderr[-3000:]}")
    return result.stdout


def tutorial_blocks():
    """[(language, label, text)] of the tutorial's code blocks; label is the
    `<!-- file: PATH -->` or `<!-- run -->` comment right above the block."""
    with open(TUTORIAL, encoding="utf-8") as f:
        text = f.read()
    return [(m.group(2), m.group(1), m.group(3)) for m in re.finditer(
        r"<!-- (file: \S+|run) -->\n```(\w*)\n(.*?)```", text, re.S)]


def start(argv, log_path):
    with open(log_path, "w", encoding="utf-8") as log:
        return subprocess.Popen(argv, stdout=log, stderr=subprocess.STDOUT)


def grpc_port(port_file, process):
    deadline = time.monotonic() + TIMEOUT_S
    while time.monotonic() < deadline:
        if process.poll() is not None:
            raise AssertionError(f"{process.args[0]} exited with {process.returncode}")
        if os.path.exists(port_file):
            with open(port_file, encoding="utf-8") as f:
                ports = dict(line.strip().split("=", 1) for line in f if "=" in line)
            if "grpc_port" in ports:
                return int(ports["grpc_port"])
        time.sleep(0.05)
    raise AssertionError(f"no port file {port_file}")


class OutOfTreeTest(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        cls.tmp = tempfile.mkdtemp(prefix="behaviorlib-out-of-tree-")
        cls.processes = []
        env = dict(os.environ, BEHAVIORLIB_BUILD=BUILD_DIR,
                   PREFIX=os.path.join(cls.tmp, "prefix"), BUILD=os.path.join(cls.tmp, "build"))
        # The tutorial's commands, in order: install, configure, build.
        cls.commands = [text for lang, label, text in tutorial_blocks() if label == "run"]
        for command in cls.commands:
            run(command, cwd=EXAMPLE, env=env)
        cls.greeter = os.path.join(cls.tmp, "build", "greeter")

        coordinator_ports = os.path.join(cls.tmp, "coordinator.ports")
        coordinator = start([os.path.join(BUILD_DIR, "bin", "coordinator"),
                             "--listen", "127.0.0.1:0", "--metrics-listen", "",
                             "--port-file", coordinator_ports,
                             "--catalog", os.path.join(EXAMPLE, "catalog.yaml")],
                            os.path.join(cls.tmp, "coordinator.log"))
        cls.processes.append(coordinator)
        cls.coordinator_address = f"127.0.0.1:{grpc_port(coordinator_ports, coordinator)}"
        greeter_ports = os.path.join(cls.tmp, "greeter.ports")
        greeter = start([cls.greeter, "--robot-id", "robot1", "--listen", "127.0.0.1:0",
                         "--metrics-listen", "", "--port-file", greeter_ports,
                         "--coordinator", cls.coordinator_address],
                        os.path.join(cls.tmp, "greeter.log"))
        cls.processes.append(greeter)
        cls.greeter_address = f"127.0.0.1:{grpc_port(greeter_ports, greeter)}"
        cls.coordinator = rpc.Client(cls.coordinator_address, [COORDINATOR])
        demo.wait_for_systems(cls.coordinator, "robot1", ["greeter"], timeout_s=TIMEOUT_S)

    @classmethod
    def tearDownClass(cls):
        for process in reversed(cls.processes):
            if process.poll() is None:
                process.terminate()
                try:
                    process.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    process.kill()
                    process.wait()
        shutil.rmtree(cls.tmp, ignore_errors=True)

    def test_the_tutorial_is_the_example(self):
        blocks = tutorial_blocks()
        files = [(label[len("file: "):], text) for _, label, text in blocks if label != "run"]
        self.assertGreaterEqual(len(files), 4)
        self.assertGreaterEqual(len(self.commands), 2)
        # Each block is a whole file of the example, and each file is shown once.
        self.assertEqual(len({path for path, _ in files}), len(files), files)
        for path, text in files:
            with open(os.path.join(EXAMPLE, path), encoding="utf-8") as f:
                self.assertEqual(text.strip(), f.read().strip(), path)

    def test_the_generated_typed_services_are_served(self):
        services = rc.list_services(self.greeter_address)
        self.assertIn("acme.v1.SayHello", services)
        self.assertIn("acme.v1.KeepCounting", services)
        self.assertIn("behaviorlib.v1.BehaviorSystem", services)

    def test_say_hello_through_the_coordinator_with_the_catalog_plan(self):
        recorder = demo.EventRecorder(self.coordinator, "robot1")
        recorder.start()
        try:
            reply = self.coordinator.call(COORDINATOR, "ActivateBehavior", {
                "robot_id": "robot1", "behavior": "SAY_HELLO",
                "parameters": {"name": "world", "times": 5}})
            steps = [(s.get("kind", ""), s.get("behavior", "")) for s in reply["plan"]]
            self.assertIn("KEEP_COUNTING", [b for _, b in steps], reply)
            activation = reply["activation"]["activation_id"]
            finished = recorder.wait_finished(activation, TIMEOUT_S)
            self.assertIsNotNone(finished, "SAY_HELLO did not finish")
            self.assertEqual(finished["behavior"], "SAY_HELLO")
            self.assertEqual(finished["finished"]["cause"], "TERMINATION_CAUSE_GOAL_ACHIEVED")
            self.assertEqual(finished["finished"]["message"], "said hello to world 5 times")
            activated = [e["behavior"] for e in recorder.behavior_events() if "activated" in e]
            self.assertIn("KEEP_COUNTING", activated)
        finally:
            recorder.stop()

    def test_a_bad_parameter_is_refused_naming_it(self):
        with self.assertRaises(grpc.RpcError) as raised:
            self.coordinator.call(COORDINATOR, "ActivateBehavior", {
                "robot_id": "robot1", "behavior": "SAY_HELLO",
                "parameters": {"name": "world", "times": 0}})
        self.assertEqual(raised.exception.code(), grpc.StatusCode.INVALID_ARGUMENT)
        self.assertIn("times", raised.exception.details())


def main():
    global BUILD_DIR  # pylint: disable=global-statement
    parser = argparse.ArgumentParser()
    parser.add_argument("--build-dir", required=True)
    args, rest = parser.parse_known_args()
    BUILD_DIR = os.path.abspath(args.build_dir)
    unittest.main(argv=[sys.argv[0]] + rest, verbosity=2)


if __name__ == "__main__":
    main()
