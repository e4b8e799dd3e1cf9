#!/usr/bin/env python3
"""The README's main job on a fresh Debian 12 machine, timed (issue 37 goal 5).

A fresh machine is a container of the minbase Debian 12 image that
scripts/container-tests.sh makes from Debian's packages (debian:12): no
compiler, no library, no apt cache, no build tree. Into it goes a clean clone
of the repository's committed HEAD, and in it runs the README's command,
`scripts/run-demo.sh`, unchanged: the packages' download and installation,
the configure, the build of what the demo needs, the whole stack and the demo
mission. Every line of its output is stamped on arrival, so the phases are
told apart by their first lines:

  packages   from the command to the configure's first line ("-- ...")
  build      from there to the build's last step ("[N/N] ...")
  demo       from there to the end (the stack, the mission, the report)

    scripts/container-tests.sh --run /usr/bin/python3 tests/bench/stack/first_run_bench.py
    /usr/bin/python3 tests/bench/stack/first_run_bench.py    # the same: it wraps itself

With no engine answering (DOCKER_HOST or the default socket) it runs itself
again under `scripts/container-tests.sh --run`, which starts Debian's dockerd
with the project's data root and stops it at the end. Prints the machine, the
command, the phases, the packages' download size and count, and the mission's
outcome; exits 1 unless the demo's mission SUCCEEDED. --keep leaves the
container and its log for a look.
"""

import argparse
import os
import re
import subprocess
import sys
import tempfile
import time

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", "..", ".."))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import main_job_bench  # noqa: E402


def engine_answers():
    try:
        return subprocess.run(["docker", "version"], stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL, timeout=20).returncode == 0
    except (OSError, subprocess.TimeoutExpired):
        return False


def phases(stamped):
    """(packages_s, build_s, demo_s) from [(seconds since start, line)]."""
    configure = next((t for t, line in stamped if line.startswith("-- ")), None)
    build_end = None
    for t, line in stamped:
        m = re.match(r"^\[(\d+)/(\d+)\]", line)
        if m and m.group(1) == m.group(2):
            build_end = t
    end = stamped[-1][0] if stamped else 0.0
    if configure is None or build_end is None:
        return None
    return configure, build_end - configure, end - build_end


def apt_figures(lines):
    """The packages' download size and count, as apt-get install said them."""
    size, newly = "?", "?"
    for line in lines:
        m = re.match(r"^Need to get (.+?) of archives", line)
        if m:
            size = m.group(1)
        m = re.match(r"^\d+ upgraded, (\d+) newly installed", line)
        if m:
            newly = m.group(1)
    return size, newly


def main():
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--image", default="debian:12",
                        help="the fresh machine's image (default debian:12, minbase)")
    parser.add_argument("--timeout-s", type=float, default=3600,
                        help="give up after this long (default 3600)")
    parser.add_argument("--keep", action="store_true",
                        help="leave the container (stopped) and the clone for a look")
    parser.add_argument("launcher_args", nargs="*",
                        help="extra arguments for scripts/run-demo.sh (after --)")
    args = parser.parse_args()

    if not engine_answers():
        if os.environ.get("BEHAVIORLIB_FIRST_RUN_WRAPPED"):
            print("first_run_bench: no Docker engine answers", file=sys.stderr)
            return 1
        env = dict(os.environ, BEHAVIORLIB_FIRST_RUN_WRAPPED="1")
        return subprocess.call([os.path.join(REPO, "scripts", "container-tests.sh"), "--run",
                                sys.executable, os.path.abspath(__file__), *sys.argv[1:]],
                               env=env)

    work = tempfile.mkdtemp(prefix="behaviorlib-first-run-")
    clone = os.path.join(work, "behaviorlib")
    subprocess.run(["git", "clone", "--quiet", "--no-hardlinks", REPO, clone], check=True)
    head = subprocess.run(["git", "-C", clone, "rev-parse", "--short", "HEAD"], check=True,
                          capture_output=True, text=True).stdout.strip()
    name = f"behaviorlib-first-run-{os.getpid()}"
    command = ["scripts/run-demo.sh", *args.launcher_args]
    docker = ["docker", "run", "--name", name, "-v", f"{clone}:/behaviorlib", "-w",
              "/behaviorlib", args.image, *command]
    print(f"# machine: {main_job_bench.machine()}")
    print(f"# date: {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}")
    print(f"# a clean clone of {head} in a container of {args.image}: {' '.join(command)}")
    log_path = os.path.join(work, "first-run.log")
    stamped = []
    started = time.monotonic()
    timed_out = False
    with open(log_path, "w") as log, subprocess.Popen(
            docker, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
            errors="replace") as proc:
        for line in proc.stdout:
            t = time.monotonic() - started
            line = line.rstrip("\n")
            stamped.append((t, line))
            log.write(f"{t:9.2f} {line}\n")
            if t > args.timeout_s:
                timed_out = True
                subprocess.run(["docker", "kill", name], stdout=subprocess.DEVNULL,
                               stderr=subprocess.DEVNULL)
                break
        rc = proc.wait()
    total = time.monotonic() - started
    if not args.keep:
        subprocess.run(["docker", "rm", "-f", name], stdout=subprocess.DEVNULL,
                       stderr=subprocess.DEVNULL)
    lines = [line for _, line in stamped]
    outcome = next((m.group(1) for line in reversed(lines)
                    for m in [re.match(r"^mission \S+: (\w+)", line)] if m), "no outcome")
    size, newly = apt_figures(lines)
    split = phases(stamped)
    print()
    print("| phase | wall time |")
    print("|---|---:|")
    if split:
        print(f"| packages (apt-get update and install, {newly} packages, {size}) "
              f"| {split[0]:.0f} s |")
        print(f"| configure and build of the `demo` target | {split[1]:.0f} s |")
        print(f"| the stack and the demo mission | {split[2]:.0f} s |")
    print(f"| **total, the command to its end** | **{total:.0f} s ({total / 60:.1f} min)** |")
    print()
    print(f"mission: {outcome}; exit code {rc}" + ("; TIMED OUT" if timed_out else ""))
    print(f"log: {log_path}" + (f"; container {name} and clone {clone} kept" if args.keep
                                 else ""))
    if not args.keep:
        subprocess.run(["rm", "-rf", clone])
    return 0 if outcome == "SUCCEEDED" and rc == 0 and not timed_out else 1


if __name__ == "__main__":
    sys.exit(main())
