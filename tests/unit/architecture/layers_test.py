"""The layers of docs/architecture.md, checked on the sources.

CMake enforces that a header is reachable only through a linked target (each
target has its own include root). This test enforces the direction: which
layer's headers each layer's code may include, and that deploy/ never uses
tests/. It reads every C++ file under services/, formats/, coordinator/,
simulator/, console/ and clients/ and every Python file under deploy/.

  layers_test.py [--repo DIR]
"""

import argparse
import os
import re
import sys
import unittest

REPO = os.path.abspath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", ".."))

INCLUDE = re.compile(r'^\s*#\s*include\s+[<"]([^>"]+)[>"]', re.M)

ALGORITHMS = {"image_codec", "motion_control", "navigation", "sensor_fusion", "visual_markers"}
SHARED = {"flight_common", "motion_behaviors", "platform"}
# Header-only helpers beneath every layer (they include nothing of ours):
# the order of gRPC's callbacks for TSan, used by every reactor, reflection's
# too.
BASE_HEADERS = {"services/server_kit/include/behaviorlib/server_kit/reactor_order.h"}
# The folders whose code is classified (and whose headers may be included).
TOPS = ("services", "proto", "formats", "coordinator", "simulator", "console", "clients")
# The folders of C++ code: the servers, the formats both sides read, the
# clients (which call the servers and are never called by them).
CODE = ("services", "formats", "coordinator", "simulator", "console", "clients")
SERVERS = ("services", "coordinator", "simulator")
CLIENTS = ("console", "clients")
# Headers that the build generates, by the rule that makes them: the
# messages ("proto", protobuf only), the gRPC stubs and typed services
# ("stubs", which need gRPC), and reflection's. Each must come from a .proto
# of the repository (or googleapis', or gRPC's reflection).
GENERATED = (
    (re.compile(r"^behaviorlib/((?:durable/|config/)?v1/.+)\.grpc\.pb\.h$"), "stubs", "proto/behaviorlib"),
    (re.compile(r"^behaviorlib/(v1/.+)\.behaviors\.h$"), "stubs", "proto/behaviorlib"),
    (re.compile(r"^behaviorlib/((?:durable/|config/)?v1/.+)\.pb\.h$"), "proto", "proto/behaviorlib"),
    (re.compile(r"^google/rpc/(status|error_details)\.pb\.h$"), "proto", None),
    (re.compile(r"^grpc/reflection/(v1|v1alpha)/reflection\.grpc\.pb\.h$"), "reflection", None),
    (re.compile(r"^behaviorlib/(embedded_descriptors)\.h$"), "proto", None),
)
_HEADERS = {}  # include path -> repository-relative file, built on first use
# The coordinator's folders, bottom up (docs/architecture.md, "The
# coordinator's folders"): a folder's code includes only folders listed
# before it, and every folder of coordinator/ is listed.
COORDINATOR_FOLDERS = ("common", "durable", "belief", "catalog", "mission", "events", "metrics",
                       "registry", "control", "safety", "telemetry", "api", "process")
# What of the coordinator a client may include: the gRPC health check (it
# sits in coordinator/registry/, beside the links that use it).
CLIENT_VISIBLE = {os.path.join("coordinator", "registry", "health_check.h")}


def header_index():
    """{include path: repository-relative header} for every header under an
    `include` folder of the repository, and every header of formats/,
    coordinator/, simulator/, console/ and clients/ by its path from the root
    (their include roots are the repository's root, through
    behaviorlib_own_include_root)."""
    if not _HEADERS:
        for top in TOPS:
            for path in sources(os.path.join(REPO, top), (".h",)):
                rel = os.path.relpath(path, REPO)
                parts = rel.split(os.sep)
                if "include" in parts:
                    at = parts.index("include")
                    _HEADERS.setdefault("/".join(parts[at + 1:]), rel)
                if top in ("formats", "coordinator", "simulator", "console", "clients"):
                    _HEADERS.setdefault("/".join(parts), rel)
    return _HEADERS


def resolve(include, including=None):
    """The repository-relative file of an included header: beside the
    including file (relative to the repository) first, then by the index;
    None for a header that is no file of the repository."""
    if including is not None:
        local = os.path.normpath(os.path.join(os.path.dirname(including), include))
        if os.path.isfile(os.path.join(REPO, local)):
            return local
    return header_index().get(include)


def component_of(include, including=None):
    """The component of an included header, by the folder its file is in: a
    layer_of() name ("core", "server", "server_kit", "errors", "channel", an
    algorithm, a shared helper or a system, "formats", "simulator",
    "coordinator", "console", "clients"), "proto" or "stubs" for a generated header, "base", or
    None for a header outside the project. `including` (the including file,
    relative to the repository) resolves an include relative to its folder.
    Raises LookupError for a header in the project's namespaces that is no
    file of the repository and no generated header: nothing is guessed."""
    found = resolve(include, including)
    if found is not None:
        return component_of_file(found)
    for pattern, component, proto_root in GENERATED:
        match = pattern.match(include)
        if match:
            if proto_root and not os.path.isfile(
                    os.path.join(REPO, proto_root, match.group(1) + ".proto")):
                raise LookupError(f"{include}: generated from no .proto of {proto_root}")
            return component
    if include.split("/")[0] in ("behaviorlib",) + TOPS:
        raise LookupError(f"{include}: no header of the repository and none generated")
    return None


def component_of_file(rel):
    """The component of a header of the repository, by its folder."""
    if rel in BASE_HEADERS:
        return "base"
    if rel.split(os.sep)[0] == "proto":
        return "proto"
    return layer_of(rel).split(":")[-1]


def layer_of(path):
    """The layer of a source file (its path relative to the repository)."""
    parts = path.split(os.sep)
    if parts[0] == "services":
        if parts[1] == "behaviorlib":
            return parts[2]  # core | server
        if parts[1] == "server_kit":
            return "reflection" if parts[2] == "reflection" else "server_kit"
        if parts[1] in ("channel", "errors"):
            return parts[1]
        if parts[1] in ("algorithms", "shared", "systems"):
            return parts[1] + ":" + parts[2]
    return parts[0]  # formats | coordinator | simulator | console | clients


def allowed(layer, component):
    """Whether code of `layer` may include a header of `component`."""
    if component is None or component in ("proto", "base", "errors"):
        return True
    name = layer.split(":")[-1]
    if component == name:
        return True
    if layer.startswith("algorithms:"):
        return False  # transport-free: only their own headers
    if component == "stubs":  # gRPC: every layer but the core and the algorithms
        return layer not in ("core", "errors")
    rules = {
        "core": set(),
        "errors": set(),
        "reflection": set(),
        "server_kit": {"reflection"},
        "channel": {"core", "server_kit"},
        "server": {"core", "server_kit", "channel"},
        "coordinator": {"core", "server_kit", "channel", "platform", "flight_common"},
        # The world files and MCAP: read by servers and clients alike; they
        # use the server kit's confined, capped file reading only.
        "formats": {"server_kit"},
        # The clients: behaviorctl, the fleet follower and the flight
        # recorder (clients/), and the console, which draws the world file
        # and serves the recordings. They call the servers over gRPC and
        # may use the coordinator's health-check client.
        "clients": {"core", "server_kit", "channel", "coordinator", "formats"},
        "console": {"server_kit", "clients", "formats"},
        "simulator": {"server_kit", "channel", "core", "formats"} | ALGORITHMS,
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


def folder_of(rel):
    """The unit of the folder graph: a layer, or for the coordinator, the
    simulator and the console their sub-folder (coordinator/belief)."""
    parts = rel.split(os.sep)
    if parts[0] in ("formats", "coordinator", "simulator", "console", "clients") and len(parts) > 2:
        return "/".join(parts[:2])
    return layer_of(rel)


def folder_graph():
    """{folder: {folders its code includes}}, generated headers left out."""
    graph = {}
    for top in CODE:
        for path in sources(os.path.join(REPO, top), (".h", ".cc")):
            rel = os.path.relpath(path, REPO)
            here = folder_of(rel)
            graph.setdefault(here, set())
            with open(path, encoding="utf-8") as f:
                for include in INCLUDE.findall(f.read()):
                    found = resolve(include, rel)
                    if (found is not None and found not in BASE_HEADERS
                            and folder_of(found) != here):
                        graph[here].add(folder_of(found))
    return graph


def coordinator_order_violations(graph):
    """Includes between the coordinator's folders that go up (or across)
    COORDINATOR_FOLDERS, and folders of coordinator/ it does not list."""
    order = {"coordinator/" + name: at for at, name in enumerate(COORDINATOR_FOLDERS)}
    found = []
    for folder, used in sorted(graph.items()):
        if not folder.startswith("coordinator/"):
            continue
        if folder not in order:
            found.append(f"{folder}: not in COORDINATOR_FOLDERS")
            continue
        for other in sorted(used):
            if other.startswith("coordinator/") and order.get(other, len(order)) >= order[folder]:
                found.append(f"{folder} includes {other}")
    return found


def cycles(graph):
    """Every strongly connected set of more than one folder (Tarjan)."""
    index, low, stack, on_stack, found = {}, {}, [], set(), []

    def visit(node):
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for nxt in sorted(graph.get(node, ())):
            if nxt not in index:
                visit(nxt)
                low[node] = min(low[node], low[nxt])
            elif nxt in on_stack:
                low[node] = min(low[node], index[nxt])
        if low[node] == index[node]:
            group = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                group.append(member)
                if member == node:
                    break
            if len(group) > 1:
                found.append(sorted(group))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return found


class LayersTest(unittest.TestCase):
    def test_every_include_goes_down_the_layers(self):
        violations = []
        checked = 0
        for top in CODE:
            for path in sources(os.path.join(REPO, top), (".h", ".cc")):
                rel = os.path.relpath(path, REPO)
                layer = layer_of(rel)
                with open(path, encoding="utf-8") as f:
                    text = f.read()
                for include in INCLUDE.findall(text):
                    checked += 1
                    try:
                        component = component_of(include, rel)
                    except LookupError as error:
                        violations.append(f"{rel} ({layer}): {error}")
                        continue
                    if not allowed(layer, component):
                        violations.append(f"{rel} ({layer}) includes {include} ({component})")
        self.assertGreater(checked, 1000)
        self.assertEqual(violations, [])

    def test_the_coordinator_uses_only_the_pose_topics_of_flight_common(self):
        for path in sources(os.path.join(REPO, "coordinator"), (".h", ".cc")):
            with open(path, encoding="utf-8") as f:
                for include in INCLUDE.findall(f.read()):
                    if component_of(include, os.path.relpath(path, REPO)) == "flight_common":
                        self.assertEqual(include, "behaviorlib/flight_common/topics.h", path)

    def test_no_two_folders_include_each_other(self):
        graph = folder_graph()
        self.assertIn("coordinator/belief", graph)
        self.assertEqual(cycles(graph), [])

    def test_the_coordinator_folders_include_down_their_order(self):
        graph = folder_graph()
        for name in COORDINATOR_FOLDERS:
            self.assertIn("coordinator/" + name, graph)
        self.assertEqual(coordinator_order_violations(graph), [])

    def test_clients_use_only_the_health_check_of_the_coordinator(self):
        found = []
        for top in CLIENTS:
            for path in sources(os.path.join(REPO, top), (".h", ".cc")):
                rel = os.path.relpath(path, REPO)
                with open(path, encoding="utf-8") as f:
                    for include in INCLUDE.findall(f.read()):
                        header = resolve(include, rel)
                        if (header is not None and header.split(os.sep)[0] == "coordinator"
                                and header not in CLIENT_VISIBLE):
                            found.append(f"{rel} includes {include}")
        self.assertEqual(found, [])

    def test_no_server_includes_a_client(self):
        # Clients stand above the servers: nothing in services/, coordinator/
        # or simulator/ includes a header of console/ or clients/, nor links
        # one of their targets.
        found = []
        for top in SERVERS:
            for path in sources(os.path.join(REPO, top), (".h", ".cc", "CMakeLists.txt")):
                rel = os.path.relpath(path, REPO)
                with open(path, encoding="utf-8") as f:
                    text = f.read()
                if path.endswith("CMakeLists.txt"):
                    found += [f"{rel} links {name}" for name in re.findall(
                        r"behaviorlib::(fleet_follower|recorder|console_gateway|behaviorctl)\b",
                        text)]
                    continue
                for include in INCLUDE.findall(text):
                    header = resolve(include, rel)
                    if header is not None and header.split(os.sep)[0] in CLIENTS:
                        found.append(f"{rel} includes {include}")
        self.assertEqual(found, [])

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
        for server in ("core", "server", "server_kit", "channel", "coordinator", "simulator",
                       "systems:x", "shared:platform", "algorithms:navigation", "formats"):
            self.assertFalse(allowed(server, "clients"), server)
            self.assertFalse(allowed(server, "console"), server)
        self.assertFalse(allowed("console", "simulator"))
        self.assertFalse(allowed("formats", "simulator"))
        self.assertTrue(allowed("simulator", "formats"))
        self.assertEqual(component_of("formats/world/world.h"), "formats")
        self.assertEqual(component_of("behaviorlib/recorder/recorder.h"), "clients")
        self.assertTrue(allowed("systems:basic_quadrotor_behaviors", "flight_common"))
        self.assertEqual(component_of("behaviorlib/v1/behavior.pb.h"), "proto")
        self.assertEqual(component_of("behaviorlib/durable/v1/journal.pb.h"), "proto")
        self.assertEqual(component_of("behaviorlib/clock.h"), "core")
        self.assertEqual(component_of("behaviorlib/error_details.h"), "server_kit")
        self.assertEqual(component_of("behaviorlib/errors/status_details.h"), "errors")
        self.assertEqual(component_of("behaviorlib/v1/coordinator.grpc.pb.h"), "stubs")
        self.assertFalse(allowed("core", "stubs"))
        self.assertFalse(allowed("core", "server_kit"))
        with self.assertRaises(LookupError):
            component_of("behaviorlib/no_such_header.h")
        with self.assertRaises(LookupError):
            component_of("behaviorlib/v1/no_such.pb.h")
        self.assertEqual(cycles({"a": {"b"}, "b": {"a", "c"}, "c": set()}), [["a", "b"]])
        self.assertEqual(coordinator_order_violations(
            {"coordinator/registry": {"coordinator/api", "coordinator/events"},
             "coordinator/service": set()}),
            ["coordinator/registry includes coordinator/api",
             "coordinator/service: not in COORDINATOR_FOLDERS"])
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
