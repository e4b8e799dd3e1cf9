"""Clang's thread-safety analysis over the library and the coordinator.

Compiles (syntax only) every translation unit of services/behaviorlib,
services/server_kit, services/channel, services/shared, the two behavior systems that keep
threads of their own (operator_interaction's AnswerWatch, navigation_with_lidar's
LidarMapper), coordinator/, console/ and clients/ with clang++-14
-Wthread-safety as errors, using the flags of the build's
compile_commands.json, so an access to a field marked ABSL_GUARDED_BY(mu)
without holding mu fails the run. GCC builds everything else; this only
checks. Exit code 0 when clean.

  thread_safety_check.py --build-dir build [--jobs 2] [--only PREFIX ...]
"""

import argparse
import concurrent.futures
import json
import os
import shlex
import subprocess
import sys

REPO = os.path.abspath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", ".."))
CHECKED = ("services/behaviorlib/", "services/server_kit/", "services/channel/",
           "services/shared/", "services/systems/operator_interaction/", "services/systems/navigation_with_lidar/",
           "coordinator/", "console/", "clients/")
CLANG = "clang++-14"
FLAGS = ["-fsyntax-only", "-Wthread-safety", "-Werror=thread-safety",
         "-Wno-unknown-warning-option"]


def clang_command(entry):
    """The entry's GCC command turned into a clang syntax check."""
    out, skip = [], False
    for arg in shlex.split(entry["command"])[1:]:
        if skip:
            skip = False
            continue
        if arg in ("-o", "-MT", "-MF"):
            skip = True
            continue
        # Only the analysis is checked here: GCC's warnings are GCC's job.
        if arg in ("-c", "-MD", "-Werror", "-Wall", "-Wextra"):
            continue
        out.append(arg)
    return [CLANG] + FLAGS + out


def check(entry):
    result = subprocess.run(clang_command(entry), cwd=entry["directory"], capture_output=True,
                            text=True, check=False)
    return entry["file"], result.returncode, result.stderr


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--build-dir", required=True)
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--only", nargs="*", default=[],
                        help="check only the translation units under these repository paths")
    args = parser.parse_args()
    with open(os.path.join(args.build_dir, "compile_commands.json"), encoding="utf-8") as f:
        database = json.load(f)
    entries = [e for e in database
               if os.path.relpath(e["file"], REPO).startswith(CHECKED)
               and (not args.only or os.path.relpath(e["file"], REPO).startswith(tuple(args.only)))]
    if not entries:
        print("thread_safety_check: no translation unit to check (build first)", file=sys.stderr)
        return 2
    failures = 0
    with concurrent.futures.ThreadPoolExecutor(max_workers=args.jobs) as pool:
        for path, code, errors in pool.map(check, entries):
            if code != 0:
                failures += 1
                print(f"--- {os.path.relpath(path, REPO)}\n{errors}", file=sys.stderr)
    print(f"thread_safety_check: {len(entries)} translation units, {failures} failing")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
