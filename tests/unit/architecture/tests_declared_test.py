"""Every test goes through one helper, with its label and its timeout.

The CMake files of the repository declare tests only through
behaviorlib_add_test (cmake/BehaviorlibTesting.cmake): no other file calls
add_test or set_tests_properties. And ctest, asked for the tests of the build
directory, reports a label and a timeout for every one.

  tests_declared_test.py --repo DIR --build-dir DIR
"""

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import unittest

ARGS = None
HELPER = os.path.join("cmake", "BehaviorlibTesting.cmake")
CALL = re.compile(r"^\s*(add_test|set_tests_properties)\s*\(", re.M)
LABELS = {"unit", "integration", "e2e", "bench", "fuzz", "container", "fleet"}


def cmake_files(repo):
    for base, dirs, files in os.walk(repo):
        dirs[:] = [d for d in dirs if not d.startswith((".", "build")) and d != "node_modules"]
        for name in files:
            if name == "CMakeLists.txt" or name.endswith(".cmake"):
                yield os.path.relpath(os.path.join(base, name), repo)


def bare_calls(repo, files):
    """(file, line, call) of each add_test or set_tests_properties outside
    the helper's file."""
    found = []
    for rel in files:
        if rel == HELPER:
            continue
        with open(os.path.join(repo, rel), encoding="utf-8") as f:
            text = f.read()
        for match in CALL.finditer(text):
            found.append((rel, text.count("\n", 0, match.start()) + 1, match.group(1)))
    return found


class TestsDeclaredTest(unittest.TestCase):
    def test_no_cmake_file_declares_a_test_but_the_helper(self):
        files = list(cmake_files(ARGS.repo))
        self.assertIn(HELPER, files)
        self.assertGreater(len(files), 50)
        self.assertEqual(bare_calls(ARGS.repo, files), [])

    def test_ctest_has_a_label_and_a_timeout_for_every_test(self):
        listed = subprocess.run(["ctest", "--show-only=json-v1"], cwd=ARGS.build_dir,
                                capture_output=True, text=True, check=True)
        tests = json.loads(listed.stdout)["tests"]
        self.assertGreater(len(tests), 100)
        missing = []
        for test in tests:
            properties = {p["name"]: p["value"] for p in test.get("properties", [])}
            labels = properties.get("LABELS") or []
            if not LABELS.intersection(labels) or not properties.get("TIMEOUT"):
                missing.append((test["name"], labels, properties.get("TIMEOUT")))
        self.assertEqual(missing, [])

    def test_the_check_finds_a_bare_call(self):
        # The checker itself, on a file written here.
        with tempfile.TemporaryDirectory() as repo:
            os.makedirs(os.path.join(repo, "cmake"))
            with open(os.path.join(repo, HELPER), "w") as f:
                f.write("function(behaviorlib_add_test)\n  add_test(NAME x COMMAND x)\n")
            with open(os.path.join(repo, "CMakeLists.txt"), "w") as f:
                f.write("behaviorlib_add_test(NAME a LABEL unit TIMEOUT 1 COMMAND a)\n"
                        "  add_test(NAME b COMMAND b)\n")
            found = bare_calls(repo, list(cmake_files(repo)))
            self.assertEqual(found, [("CMakeLists.txt", 2, "add_test")])


def main():
    global ARGS  # pylint: disable=global-statement
    parser = argparse.ArgumentParser()
    parser.add_argument("--repo", required=True)
    parser.add_argument("--build-dir", required=True)
    ARGS, rest = parser.parse_known_args()
    unittest.main(argv=[sys.argv[0]] + rest, verbosity=2)


if __name__ == "__main__":
    main()
