"""The layers of docs/architecture.md, checked on the sources.

CMake enforces that a header is reachable only through a linked target (each
target has its own include root). This test enforces the direction: which
layer's headers each layer's code may include, and that deploy/ never uses
tests/. It reads every C++ file under services/, coordinator/, simulator/ and
console/ and every Python file under deploy/.

  layers_test.py [--repo DIR]
"""

import argparse
import os
import re
import sys
import unittest

REPO = os.path.abspath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", ".."))

INCLUDE = re.compile(r'^\s*#\s*include\s+[<"]([^>"]+)[>"]', re.M)

CORE_HEADERS = {"behavior_execution_manager.h", "behavior_host.h", "clock.h", "documentation.h",
                "event_log.h", "parameters.h", "process_supervisor.h"}
ALGORITHMS = {"image_codec", "motion_control", "navigation", "sensor_fusion", "visual_markers"}
SHARED = {"flight_common", "motion_behaviors", "platform"}
# Header-only helpers beneath every layer (they include nothing of ours):
# the order of gRPC's callbacks for TSan, used by every reactor, reflection's
# too.
BASE_HEADERS = {"behaviorlib/server_kit/reactor_order.h"}


def component_of(include):
    """The component a project header belongs to ("core", "server",
    "server_kit", "reflection", "channel", "proto", an algorithm, a shared
    helper or a system), "simulator", "coordinator", or None for a header
    outside the project."""
    if include in BASE_HEADERS:
        return "base"
    parts = include.split("/")
    if parts[0] in ("simulator", "coordinator"):
        return parts[0]
    if parts[0] != "behaviorlib":
        return None
    if len(parts) == 2:
        if parts[1] in CORE_HEADERS:
            return "core"
        return "proto"  # embedded_descriptors.h
    # behaviorlib/v1/*.pb.h, and behaviorlib/durable/v1/journal.pb.h (the
    # coordinator's journal records, generated beside the API).
    if parts[1] == "v1" or parts[1:3] == ["durable", "v1"]:
        return "proto"
    return parts[1]


def layer_of(path):
    """The layer of a source file (its path relative to the repository)."""
    parts = path.split(os.sep)
    if parts[0] == "services":
        if parts[1] == "behaviorlib":
            return parts[2]  # core | server
        if parts[1] == "server_kit":
            return "reflection" if parts[2] == "reflection" else "server_kit"
        if parts[1] == "channel":
            return "channel"
        if parts[1] in ("algorithms", "shared", "systems"):
            return parts[1] + ":" + parts[2]
    if parts[0] == "coordinator" and parts[1] == "cli":
        return "cli"
    return parts[0]  # coordinator | simulator | console


def allowed(layer, component):
    """Whether code of `layer` may include a header of `component`."""
    if component is None or component in ("proto", "base"):
        return True
    name = layer.split(":")[-1]
    if component == name:
        return True
    if layer.startswith("algorithms:"):
        return False  # transport-free: only their own headers
    rules = {
        "core": set(),
        "reflection": set(),
        "server_kit": {"reflection"},
        "channel": {"core", "server_kit"},
        "server": {"core", "server_kit", "channel"},
        "coordinator": {"core", "server_kit", "channel", "platform", "flight_common"},
        # behaviorctl: a client, which records and replays flights with the
        # console's client libraries.
        "cli": {"core", "server_kit", "channel", "platform", "flight_common", "coordinator",
                "console", "recorder"},
        # The console and the flight recorder: clients of the coordinator and
        # the channel over gRPC; the console draws the simulator's world file.
        "console": {"server_kit", "recorder", "simulator"},
        "simulator": {"server_kit", "channel", "core"} | ALGORITHMS,
    }
    if layer.startswith("shared:"):
        return component in {"core", "server", "server_kit", "channel"} | ALGORITHMS | SHARED
    if layer.startswith("systems:"):
        return component in {"core", "server", "server_kit", "channel"} | ALGORITHMS | SHARED
    return component in rules.get(layer, set())


def sources(root, suffixes):
    for base, _, files in os.walk(root):
        for name in files:
            if name.endswith(suffixes):
                yield os.path.join(base, name)


class LayersTest(unittest.TestCase):
    def test_every_include_goes_down_the_layers(self):
        violations = []
        checked = 0
        for top in ("services", "coordinator", "simulator", "console"):
            for path in sources(os.path.join(REPO, top), (".h", ".cc")):
                rel = os.path.relpath(path, REPO)
                layer = layer_of(rel)
                with open(path, encoding="utf-8") as f:
                    text = f.read()
                for include in INCLUDE.findall(text):
                    checked += 1
                    component = component_of(include)
                    if not allowed(layer, component):
                        violations.append(f"{rel} ({layer}) includes {include} ({component})")
        self.assertGreater(checked, 1000)
        self.assertEqual(violations, [])

    def test_the_coordinator_uses_only_the_pose_topics_of_flight_common(self):
        for path in sources(os.path.join(REPO, "coordinator"), (".h", ".cc")):
            with open(path, encoding="utf-8") as f:
                for include in INCLUDE.findall(f.read()):
                    if component_of(include) == "flight_common":
                        self.assertEqual(include, "behaviorlib/flight_common/topics.h", path)

    def test_deploy_never_uses_tests(self):
        for path in sources(os.path.join(REPO, "deploy"), (".py",)):
            with open(path, encoding="utf-8") as f:
                text = f.read()
            # No import path into tests/ (a path component "tests", or a
            # sys.path entry naming it).
            self.assertIsNone(re.search(r'["\']tests["\']', text), path)
            self.assertIsNone(re.search(r"sys\.path\.\w+\([^\n]*tests", text), path)

    def test_the_rules_catch_a_wrong_include(self):
        # The checker itself: a few includes that must be refused.
        self.assertFalse(allowed("algorithms:navigation", "channel"))
        self.assertFalse(allowed("algorithms:navigation", "simulator"))
        self.assertFalse(allowed("core", "server"))
        self.assertFalse(allowed("core", "channel"))
        self.assertFalse(allowed("systems:navigation_with_lidar", "simulator"))
        self.assertFalse(allowed("server_kit", "core"))
        self.assertFalse(allowed("coordinator", "basic_quadrotor_behaviors"))
        self.assertTrue(allowed("systems:basic_quadrotor_behaviors", "flight_common"))
        self.assertEqual(component_of("behaviorlib/v1/behavior.pb.h"), "proto")
        self.assertEqual(component_of("behaviorlib/durable/v1/journal.pb.h"), "proto")
        self.assertEqual(component_of("behaviorlib/clock.h"), "core")
        self.assertEqual(layer_of(os.path.join("services", "systems", "x", "main.cc")),
                         "systems:x")


def main():
    global REPO  # pylint: disable=global-statement
    parser = argparse.ArgumentParser()
    parser.add_argument("--repo", default=REPO)
    args, rest = parser.parse_known_args()
    REPO = args.repo
    unittest.main(argv=[sys.argv[0]] + rest, verbosity=2)


if __name__ == "__main__":
    main()
