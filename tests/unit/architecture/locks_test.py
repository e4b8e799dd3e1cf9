"""The library's shared state uses one kind of lock and one kind of wait.

docs/architecture.md ("Threads") says that shared state in services/,
coordinator/, console/ and clients/ is guarded by an absl::Mutex that clang's
thread-safety analysis can see, and that every wait is Mutex::Await (or
AwaitWithTimeout, AwaitWithDeadline) on that mutex. This test keeps it true:
it finds every std::mutex, std::recursive_mutex, std::shared_mutex,
std::condition_variable and absl::CondVar in those folders' C++ files.
The simulator keeps its own (decision 18 moves its waits).

  locks_test.py --repo DIR
"""

import argparse
import os
import re
import sys
import unittest

ARGS = None
FOLDERS = ("services", "coordinator", "console", "clients")
FORBIDDEN = re.compile(
    r"\b(std::(?:recursive_|shared_|timed_)?mutex|std::condition_variable(?:_any)?|absl::CondVar)\b")
COMMENT = re.compile(r"//.*?$|/\*.*?\*/", re.S | re.M)


def forbidden_uses(text):
    """(line, name) of each forbidden lock or wait in C++ `text`, comments
    left out (a comment may name what the code no longer uses)."""
    code = COMMENT.sub(lambda m: "\n" * m.group(0).count("\n"), text)
    return [(code.count("\n", 0, m.start()) + 1, m.group(1)) for m in FORBIDDEN.finditer(code)]


def cpp_files(repo):
    for folder in FOLDERS:
        for base, dirs, files in os.walk(os.path.join(repo, folder)):
            dirs[:] = [d for d in dirs if not d.startswith((".", "build")) and d != "node_modules"]
            for name in files:
                if name.endswith((".h", ".cc", ".hpp", ".cpp")):
                    yield os.path.join(base, name)


class LocksTest(unittest.TestCase):
    def test_the_scanner_finds_each_kind_and_skips_comments(self):
        text = ("std::mutex a;\n"
                "// std::mutex in a comment\n"
                "std::recursive_mutex b; std::condition_variable c;\n"
                "/* absl::CondVar\n   spans */ absl::CondVar d;\n"
                "absl::Mutex fine;\n")
        self.assertEqual(forbidden_uses(text),
                         [(1, "std::mutex"), (3, "std::recursive_mutex"),
                          (3, "std::condition_variable"), (5, "absl::CondVar")])

    def test_no_library_folder_uses_another_lock_or_a_condition_variable(self):
        found = []
        count = 0
        for path in cpp_files(ARGS.repo):
            count += 1
            with open(path, encoding="utf-8") as f:
                for line, name in forbidden_uses(f.read()):
                    found.append(f"{os.path.relpath(path, ARGS.repo)}:{line}: {name}")
        self.assertGreater(count, 200)  # the folders were found
        self.assertEqual(found, [], "use absl::Mutex with ABSL_GUARDED_BY, and Mutex::Await "
                         "for waits (docs/architecture.md, Threads)")


def main():
    global ARGS
    parser = argparse.ArgumentParser()
    parser.add_argument("--repo", required=True)
    ARGS, rest = parser.parse_known_args()
    unittest.main(argv=[sys.argv[0]] + rest)


if __name__ == "__main__":
    main()
