"""The operator's console in a real browser (issue 19, goal 2): Debian's
chromium, driven by npm's puppeteer-core (console_browser.js), against the
whole stack the launcher starts in the deterministic mode, while a real
mission flies.

    /usr/bin/python3 tests/browser/console_browser_test.py --build-dir build \\
        --work-dir build/tests/browser/npm

The page must load without a console error, show the systems, advance the
mission started from its form step by step, show its step records as a tree
(its loop's iterations nested, updated as the mission goes on, and a fleet
mission's interleaved branches apart), show a terminated behavior's cause,
move the vehicle's marker, and land the vehicle when "Emergency land" is
pressed. The screenshot is saved in the run directory, beside the logs,
and copied to the work directory's parent (build/tests/browser/console.png).

Exits 77 (skipped) when chromium or npm is not installed, or the npm
registry cannot be reached.
"""

import argparse
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "deploy"))
import deploy_support as ds  # noqa: E402

LAUNCHER = os.path.join(ds.REPO, "deploy", "local", "launch.py")
ROBOT = "drone1"
MISSION = "browser_patrol.yaml"
# Bounds for what must happen, never measures of speed.
START_TIMEOUT_S = 120
DRIVE_TIMEOUT_S = 600


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--build-dir", default=ds.DEFAULT_BUILD_DIR)
    parser.add_argument("--work-dir", required=True,
                        help="where npm installs puppeteer-core (a build directory)")
    parser.add_argument("--keep", action="store_true", help="keep the run directory")
    args = parser.parse_args()
    chromium = shutil.which("chromium")
    if not chromium:
        print("SKIPPED: Debian's chromium is not installed (scripts/install-deps.sh)")
        return ds.SKIP
    if not shutil.which("npm") or not shutil.which("node"):
        print("SKIPPED: npm is not installed (scripts/install-deps.sh)")
        return ds.SKIP
    work = os.path.abspath(args.work_dir)
    try:
        ds.npm_ci(os.path.join(HERE, "npm"), work)
    except ds.RegistryUnreachable as error:
        print(f"SKIPPED: {error}")
        return ds.SKIP

    tmp = tempfile.mkdtemp(prefix="console-browser-")
    run_dir = os.path.join(tmp, "run")
    launcher_log = os.path.join(tmp, "launcher.log")
    with open(launcher_log, "wb") as log:
        launcher = subprocess.Popen(
            [sys.executable, LAUNCHER, "--build-dir", os.path.abspath(args.build_dir),
             "--run-dir", run_dir, "--time-scale", "max", "--robot-id", ROBOT, "--world", "rooms",
             "--mission-dir", os.path.join(HERE, "missions"),
             "--console-listen", "127.0.0.1:0", "--record"],
            stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT)
    status = 1
    try:
        def console_url():
            if launcher.poll() is not None:
                raise AssertionError(f"the launcher exited with code {launcher.returncode}:\n"
                                     f"{ds.log_tail(launcher_log, 40)}")
            with open(launcher_log, errors="replace") as f:
                text = f.read()
            if "Ctrl-C stops everything." not in text:
                return None
            return re.search(r"console: (http://127\.0\.0\.1:\d+/)", text).group(1)

        url = ds.wait_for(console_url, START_TIMEOUT_S, "the stack serving", interval_s=0.2)
        screenshot = os.path.join(run_dir, "console.png")
        env = dict(os.environ, NODE_PATH=os.path.join(work, "node_modules"), CHROMIUM=chromium)
        drive = subprocess.run(["node", os.path.join(HERE, "console_browser.js"), url, ROBOT,
                                MISSION, screenshot], env=env, timeout=DRIVE_TIMEOUT_S)
        if drive.returncode != 0:
            print(f"console_browser.js failed; the launcher's output:\n"
                  f"{ds.log_tail(launcher_log, 30)}\nlogs: {run_dir}/logs", flush=True)
            args.keep = True
        elif not os.path.getsize(screenshot) > 10000:
            print(f"the screenshot {screenshot} is missing or empty")
        else:
            # Kept beside the build's test output, past the run directory.
            shutil.copyfile(screenshot, os.path.join(os.path.dirname(work), "console.png"))
            status = 0
    finally:
        if launcher.poll() is None:
            launcher.send_signal(signal.SIGINT)  # stops the stack in order
            try:
                launcher.wait(timeout=60)
            except subprocess.TimeoutExpired:
                launcher.kill()
                launcher.wait()
        if args.keep:
            print(f"run directory kept: {tmp}")
        else:
            shutil.rmtree(tmp, ignore_errors=True)
    return status


if __name__ == "__main__":
    sys.exit(main())
