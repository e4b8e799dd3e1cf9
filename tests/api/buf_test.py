"""The public API (proto/) under buf: `npm ci` installs buf at the version
pinned by tests/api/buf/package-lock.json into --work-dir (the build tree),
then:

- `buf lint` passes with buf.yaml's exceptions;
- the exceptions for v1's published names (SERVICE_SUFFIX and the RPC_*
  naming rules) do not grow: with them lifted, buf finds exactly the
  problems recorded in tests/api/v1_names.txt, so a new service or RPC in
  an old file must be named by the rules too;
- `buf breaking` finds nothing against the API of the commit recorded in
  proto/BASELINE;
- and both checks can fail: a copy of the API with a deleted field and a
  renamed RPC is refused by `buf breaking`, a new file with a badly named
  service by `buf lint`.

Exits 77 (skipped) when npm is not installed or its registry cannot be
reached, which the first `npm ci` of a work directory needs.

    /usr/bin/python3 tests/api/buf_test.py --work-dir build/tests/api/buf
"""

import argparse
import collections
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import unittest

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "deploy"))
import deploy_support as ds  # noqa: E402

SOURCE = os.path.join(HERE, "buf")
V1_NAMES = os.path.join(HERE, "v1_names.txt")
BASELINE = os.path.join(ds.REPO, "proto", "BASELINE")
# The rules whose exceptions cover v1's published names.
NAME_RULES = ("SERVICE_SUFFIX", "RPC_REQUEST_STANDARD_NAME", "RPC_RESPONSE_STANDARD_NAME",
              "RPC_REQUEST_RESPONSE_UNIQUE")
WORK_DIR = None  # set in main


def buf(*args, cwd=ds.REPO):
    """Runs buf; returns (exit code, output)."""
    result = subprocess.run([os.path.join(WORK_DIR, "node_modules", ".bin", "buf"), *args],
                            cwd=cwd, capture_output=True, text=True, timeout=180)
    return result.returncode, result.stdout + result.stderr


def problems(output):
    """buf's --error-format json lines as "RULE path: message" strings."""
    found = []
    for line in output.splitlines():
        if line.strip():
            p = json.loads(line)
            found.append(f"{p['type']} {p['path']}: {p['message']}")
    return sorted(found)


def baseline_commit():
    with open(BASELINE) as f:
        lines = [line.strip() for line in f if line.strip() and not line.startswith("#")]
    assert len(lines) == 1 and re.fullmatch(r"[0-9a-f]{40}", lines[0]), \
        f"{BASELINE}: one full commit id expected, got {lines}"
    return lines[0]


class BufTest(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        code, version = buf("--version")
        assert code == 0, version
        print(f"buf {version.strip()}", flush=True)

    def test_lint(self):
        code, output = buf("lint")
        self.assertEqual((code, output), (0, ""))

    def test_v1_name_exceptions_do_not_grow(self):
        config = ds.read_yaml(os.path.join(ds.REPO, "buf.yaml"))
        ignored = config["lint"]["ignore_only"]
        self.assertEqual(sorted(set(NAME_RULES) & set(ignored)), sorted(NAME_RULES))
        for rule in NAME_RULES:
            del ignored[rule]
        code, output = buf("lint", "--config", json.dumps(config), "--error-format", "json")
        self.assertNotEqual(code, 0, "the v1 name exceptions cover nothing: drop them")
        with open(V1_NAMES) as f:
            recorded = sorted(line.rstrip("\n") for line in f
                              if line.strip() and not line.startswith("#"))
        # As multisets: an RPC that reuses a request type repeats a line.
        found = collections.Counter(problems(output))
        recorded = collections.Counter(recorded)
        self.assertEqual(sorted((found - recorded).elements()), [],
                         "new names that break buf's rules: name the RPC's messages "
                         "<Rpc>Request and <Rpc>Response, and services <Name>Service")
        self.assertEqual(sorted((recorded - found).elements()), [],
                         f"fixed: remove these lines from {V1_NAMES}")

    def test_no_breaking_change_since_the_baseline(self):
        commit = baseline_commit()
        known = subprocess.run(["git", "cat-file", "-e", f"{commit}^{{commit}}"], cwd=ds.REPO,
                               capture_output=True)
        if known.returncode != 0:
            self.skipTest(f"the baseline {commit} is not in this clone's history "
                          "(a shallow clone?): git fetch --unshallow")
        code, output = buf("breaking", "--against", f".git#ref={commit},subdir=proto")
        self.assertEqual((code, output), (0, ""))

    def test_the_checks_can_fail(self):
        with tempfile.TemporaryDirectory(prefix="buf-test-") as tmp:
            shutil.copy(os.path.join(ds.REPO, "buf.yaml"), tmp)
            shutil.copytree(os.path.join(ds.REPO, "proto"), os.path.join(tmp, "proto"),
                            ignore=shutil.ignore_patterns("*.txt", "*.cc", "*.h", "*.py"))
            coordinator = os.path.join(tmp, "proto", "behaviorlib", "v1", "coordinator.proto")
            with open(coordinator) as f:
                text = f.read()
            # A deleted field (GetMissionRequest.mission_id) and a renamed RPC.
            broken = re.sub(r"(message GetMissionRequest \{.*?)string mission_id = 1;", r"\1",
                            text, count=1, flags=re.S)
            broken = broken.replace("rpc GetMission(", "rpc FetchMission(", 1)
            self.assertNotEqual(broken, text)
            with open(coordinator, "w") as f:
                f.write(broken)
            code, output = buf("breaking", "--against", ds.REPO, "--error-format", "json",
                               cwd=tmp)
            self.assertNotEqual(code, 0, output)
            rules = {p.split(" ")[0] for p in problems(output)}
            self.assertIn("FIELD_NO_DELETE", rules, output)
            self.assertIn("RPC_NO_DELETE", rules, output)

            # A new file gets every rule.
            with open(os.path.join(tmp, "proto", "behaviorlib", "v1", "fleet_extra.proto"),
                      "w") as f:
                f.write('syntax = "proto3";\npackage behaviorlib.v1;\n'
                        'message Thing { string name = 1; }\n'
                        "service Things { rpc Get(Thing) returns (Thing); }\n")
            code, output = buf("lint", "--error-format", "json", cwd=tmp)
            self.assertNotEqual(code, 0, output)
            rules = {p.split(" ")[0] for p in problems(output)}
            self.assertGreaterEqual(rules, {"SERVICE_SUFFIX", "RPC_REQUEST_STANDARD_NAME",
                                            "RPC_RESPONSE_STANDARD_NAME"}, output)


if __name__ == "__main__":
    parser = argparse.ArgumentParser()
    parser.add_argument("--work-dir", required=True,
                        help="where npm installs buf (a build directory)")
    args, rest = parser.parse_known_args()
    WORK_DIR = os.path.abspath(args.work_dir)
    if not shutil.which("npm"):
        print("SKIPPED: npm is not installed, so buf cannot be installed (apt-get install npm)")
        sys.exit(ds.SKIP)
    try:
        ds.npm_ci(SOURCE, WORK_DIR)
    except ds.RegistryUnreachable as error:
        print(f"SKIPPED: {error}")
        sys.exit(ds.SKIP)
    unittest.main(argv=[sys.argv[0], *rest], verbosity=2)
