"""End to end: the local launcher (deploy/local/launch.py, the README's main
command) against the real binaries on free loopback ports.

    /usr/bin/python3 tests/e2e/local_demo_test.py --build-dir build

test_demo flies the demo mission (deploy/missions/demo.yaml) through the
coordinator with the simulator at 2x and checks the launcher's exit code,
the mission report (every step GOAL_ACHIEVED, the paper's columns, the
trajectory and behavior activity figures), the Prometheus targets, and that every process it started
is gone. test_interrupt stops a serving stack with SIGINT (Ctrl-C) and
checks that every process was stopped. With BEHAVIORLIB_KEEP_RUN_DIR=1 in
the environment, each test keeps its run directory (logs, report, figures)
and prints where it is.
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
import time
import unittest

from PIL import Image, ImageChops  # Debian's python3-pil

REPO = os.path.abspath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", ".."))
LAUNCHER = os.path.join(REPO, "deploy", "local", "launch.py")
BUILD_DIR = os.environ.get("BEHAVIORLIB_BUILD_DIR", os.path.join(REPO, "build"))
# The deterministic mode (decision 18): simulated time advances only as fast
# as every busy behavior system keeps up, so a loaded machine slows the
# mission instead of failing it (free running, the whole stack failed at 3x
# on a two-core machine with stale pose estimates). About 5x here.
TIME_SCALE = "max"
DEMO_TIMEOUT_S = 75

sys.path.insert(0, os.path.dirname(LAUNCHER))
import launch  # noqa: E402  (its list of behavior systems)
FLOWN_BEHAVIORS = ("TAKE_OFF", "FOLLOW_PATH", "ROTATE_WITH_PID_CONTROL", "LAND")
# The figures' colours (deploy/local/plot.py), RGB.
FLOWN_COLOR = (31, 119, 180)     # the first vehicle's line
START_COLOR = (44, 160, 44)
WALL_COLOR = (150, 150, 150)     # the world's walls
CELL_COLOR = (60, 60, 60)        # a saved map's occupied cells
CAUSE_COLORS = {"GOAL_ACHIEVED": (44, 160, 44), "INTERRUPTED": (150, 150, 150),
                "PROCESS_FAILURE": (214, 39, 40)}


def alive(pid):
    """True while `pid` exists and is not a zombie."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def launched_pids(run_dir):
    """The launcher's record of the processes it started ({name: pid}), {}
    before it wrote one."""
    try:
        with open(os.path.join(run_dir, "pids.json")) as f:
            return json.load(f)
    except (OSError, ValueError):
        return {}


def kill_launched(run_dir):
    """SIGKILLs every process of the run still alive: never leave a process
    behind, even when an assertion failed."""
    for pid in launched_pids(run_dir).values():
        if alive(pid):
            os.kill(pid, signal.SIGKILL)


def read_png(path):
    """The PNG at `path` as an RGB Pillow image; fails when it is not a
    PNG (Pillow checks the chunks' CRCs as it decodes)."""
    with Image.open(path) as image:
        assert image.format == "PNG", f"{path}: not a PNG ({image.format})"
        image.load()
        return image.convert("RGB")


def _mask(image, color, tolerance):
    """An "L" image: 255 where every channel of `image` is within
    `tolerance` of `color`, 0 elsewhere."""
    bands = [band.point(lambda v, c=c: 255 if abs(v - c) <= tolerance else 0)
             for band, c in zip(image.split(), color)]
    return ImageChops.multiply(ImageChops.multiply(bands[0], bands[1]), bands[2])


def pixels_near(rows_or_image, color, tolerance=24):
    """How many pixels are within `tolerance` of the RGB `color` in every
    channel (antialiasing blends a line's edges with what is under it), in
    a Pillow image or in rows of (r, g, b) pixels."""
    if isinstance(rows_or_image, Image.Image):
        return _mask(rows_or_image.convert("RGB"), color, tolerance).histogram()[255]
    return sum(all(abs(a - b) <= tolerance for a, b in zip(pixel, color))
               for row in rows_or_image for pixel in row)


def plot_area(image):
    """The part of a plot inside its axes' frame: the crop of `image`
    between the outermost rows and columns that are mostly black (the
    spines), so that a legend's samples do not count; fails without a
    frame."""
    mask = _mask(image, (0, 0, 0), 40)
    width, height = mask.size
    data = mask.tobytes()
    rows = [y for y in range(height) if data[y * width:(y + 1) * width].count(255) > 0.3 * width]
    columns = [x for x in range(width) if data[x::width].count(255) > 0.3 * height]
    assert rows and columns, "no axes frame in the plot"
    return image.crop((min(columns) + 1, min(rows) + 1, max(columns), max(rows)))


class LocalDemoTest(unittest.TestCase):
    def setUp(self):
        self.run_dir = tempfile.mkdtemp(prefix="local-demo-e2e-")

    def tearDown(self):
        kill_launched(self.run_dir)
        if os.environ.get("BEHAVIORLIB_KEEP_RUN_DIR"):  # to look at the report
            print(f"run directory kept: {self.run_dir}", file=sys.stderr, flush=True)
        else:
            shutil.rmtree(self.run_dir, ignore_errors=True)

    def _pids(self):
        return launched_pids(self.run_dir)

    def _launcher(self, *extra):
        return [sys.executable, LAUNCHER, "--build-dir", BUILD_DIR, "--run-dir", self.run_dir,
                "--time-scale", TIME_SCALE, *extra]

    def _assert_all_stopped(self):
        pids = self._pids()
        self.assertIn("channel_broker", pids)
        self.assertIn("simulator", pids)
        self.assertIn("coordinator", pids)
        self.assertIn("basic_quadrotor_behaviors", pids)
        left = {name: pid for name, pid in pids.items() if alive(pid)}
        self.assertEqual(left, {}, "processes left running after the launcher exited")

    def test_demo(self):
        started = time.monotonic()
        result = subprocess.run(self._launcher("--demo"), capture_output=True, text=True,
                                timeout=DEMO_TIMEOUT_S)
        wall_s = time.monotonic() - started
        print(result.stdout)
        print(result.stderr, file=sys.stderr)
        print(f"launcher --demo: {wall_s:.1f} s wall")
        self.assertEqual(result.returncode, 0, "the launcher failed (output above)")
        self._assert_all_stopped()
        # The main job prints the console's URL, and the report names it.
        url = re.search(r"console: (http://127\.0\.0\.1:[1-9][0-9]*/)", result.stdout)
        self.assertIsNotNone(url, "no console URL printed")

        for name in ("report.md", "report.json", "trajectory.png", "timeline.png",
                     "prometheus_targets.json"):
            self.assertTrue(os.path.isfile(os.path.join(self.run_dir, name)), name)
        with open(os.path.join(self.run_dir, "report.json")) as f:
            report = json.load(f)
        with open(os.path.join(self.run_dir, "report.md")) as f:
            markdown = f.read()
        self.assertEqual(report["settings"]["console_url"], url.group(1))
        self.assertIn(f"The run's console was {url.group(1)}", markdown)
        # The flight recording (--demo records) and the console's screenshot
        # of the finished demo, beside the report, which names both.
        recording = os.path.join(self.run_dir, "recordings", "flight.mcap")
        self.assertEqual(report["settings"]["recording"], recording)
        self.assertIn(f"The flight recording is `{recording}`", markdown)
        self.assertGreater(os.path.getsize(recording), 10000)
        if launch.screenshot.chromium_binary() is not None:
            self.assertEqual(report["settings"]["console_screenshot"], "console.png")
            self.assertIn("![the operator's console](console.png)", markdown)
            shot = read_png(os.path.join(self.run_dir, "console.png"))
            self.assertGreater(shot.size[0] * shot.size[1], 1000 * 1000)
            self.assertNotIn("console screenshot: captured before", result.stdout)

        mission = report["mission"]
        self.assertEqual(mission["state"], "MISSION_STATE_SUCCEEDED")
        for behavior in FLOWN_BEHAVIORS:
            steps = [s for s in mission["steps"] if s.get("behavior") == behavior]
            # demo.yaml flies FOLLOW_PATH again once after WRONG_PROGRESS;
            # every other step runs once.
            retries = 1 if behavior == "FOLLOW_PATH" else 0
            self.assertIn(len(steps), range(1, 2 + retries), f"{behavior} steps: {steps}")
            self.assertEqual([s.get("cause") for s in steps[:-1]],
                             ["TERMINATION_CAUSE_WRONG_PROGRESS"] * (len(steps) - 1), behavior)
            self.assertEqual(steps[-1].get("cause"), "TERMINATION_CAUSE_GOAL_ACHIEVED", behavior)
            finished = [r for r in report["timeline"]
                        if r["behavior"] == behavior and r["event"] == "finished"]
            self.assertEqual([r["cause"] for r in finished],
                             ["WRONG_PROGRESS"] * (len(steps) - 1) + ["GOAL_ACHIEVED"], behavior)
            self.assertRegex(markdown, rf"\| {behavior} \| [^\n]*\| GOAL_ACHIEVED \|")
            figures = next((b for b in report["behaviors"] if b["behavior"] == behavior), None)
            self.assertIsNotNone(figures, f"{behavior} missing from the a/t1/t2/t3 table")
            self.assertEqual(figures["a"], len(steps), behavior)
            self.assertGreater(figures["monitoring_ticks"], 0, behavior)
            self.assertGreater(figures["t1_us"], 0, behavior)
            # On the thread's CPU clock too, and never above the wall time it took.
            self.assertGreater(figures["t1_cpu_us"], 0, behavior)
            self.assertLessEqual(figures["t1_cpu_us"], figures["t1_us"] * 1.01 + 1, behavior)
            self.assertGreater(figures["t2_ms"], 0, behavior)
            self.assertGreater(figures["t3_ms"], 0, behavior)
        # The recurrent localization ran through the whole mission and was
        # ended by it; the motion controller came from the catalog's plan.
        localization = [r for r in report["timeline"]
                        if r["behavior"].startswith("SELF_LOCALIZE_")]
        self.assertEqual({r["behavior"] for r in localization},
                         {"SELF_LOCALIZE_WITH_EKF_SENSOR_FUSION"}, "the demo flies on the EKF")
        self.assertEqual([r["event"] for r in localization], ["activated", "finished"])
        self.assertEqual(localization[-1]["cause"], "INTERRUPTED")
        self.assertIn("QUADROTOR_PID_MOTION_CONTROL",
                      {r["behavior"] for r in report["timeline"] if r["event"] == "activated"})

        processes = {p["name"]: p for p in report["processes"]}
        for name in ("channel_broker", "simulator", "coordinator", "basic_quadrotor_behaviors",
                     "quadrotor_motion_with_pid_control", "multi_sensor_fusion", "console"):
            self.assertGreater(processes[name]["rss_kib"], 0, name)
            self.assertGreater(processes[name]["cpu_user_s"] + processes[name]["cpu_system_s"],
                               0, name)
            self.assertEqual(processes[name]["exit_code"], 0, name)
        self.assertTrue(report["clean_shutdown"])

        # The trajectory: the square was flown (ground truth), and plotted.
        trajectory = report["trajectory"]
        self.assertGreater(trajectory["samples"], 100)
        self.assertGreater(trajectory["distance_flown_m"], 16.0)
        self.assertGreater(trajectory["max_altitude_m"], 1.3)
        self.assertEqual(len(trajectory["planned_path_m"]), 5, "start + 4 waypoints")
        self.assertLess(trajectory["follow_path_cross_track"]["max_m"], 0.5)
        png = os.path.join(self.run_dir, "trajectory.png")
        self.assertGreater(os.path.getsize(png), 2000)
        image = read_png(png)
        self.assertGreaterEqual(min(image.size), 200)
        inside = plot_area(image)
        self.assertGreater(pixels_near(inside, FLOWN_COLOR), 1000, "the flown path is not drawn")
        self.assertGreater(pixels_near(inside, START_COLOR), 30, "the start is not marked")

        # The behaviors' activity: a Gantt chart, a bar per activation
        # coloured by its termination cause.
        self.assertEqual(report["timeline_png"], "timeline.png")
        self.assertIn("## Behavior activity", markdown)
        self.assertIn("![behavior activity](timeline.png)", markdown)
        timeline = read_png(os.path.join(self.run_dir, "timeline.png"))
        self.assertGreaterEqual(timeline.size[0], 400)
        self.assertGreaterEqual(timeline.size[1], 200)
        bars = plot_area(timeline)  # not the legend, nor the labels' antialiased grey
        # GOAL_ACHIEVED: TAKE_OFF, FOLLOW_PATH, ROTATE, LAND, each bar a few
        # thousand pixels.
        self.assertGreater(pixels_near(bars, CAUSE_COLORS["GOAL_ACHIEVED"]), 1000,
                           "no GOAL_ACHIEVED bar")
        # The localization, ended by the mission.
        self.assertGreater(pixels_near(bars, CAUSE_COLORS["INTERRUPTED"]), 1000,
                           "no INTERRUPTED bar")
        self.assertEqual(pixels_near(bars, CAUSE_COLORS["PROCESS_FAILURE"]), 0,
                         "a PROCESS_FAILURE bar")

        with open(os.path.join(self.run_dir, "prometheus_targets.json")) as f:
            targets = json.load(f)
        jobs = {t["labels"]["system"]: t["labels"]["job"] for t in targets}
        self.assertEqual(jobs["coordinator"], "coordinator")
        self.assertEqual(jobs["simulator"], "simulator")
        self.assertEqual(jobs["basic_quadrotor_behaviors"], "behavior_system")
        for t in targets:
            self.assertEqual(len(t["targets"]), 1)
            self.assertRegex(t["targets"][0], r"^127\.0\.0\.1:[1-9][0-9]*$")
            if t["labels"]["job"] == "behavior_system":
                self.assertEqual(t["labels"]["robot"], "drone1")
        # Every process but the console (HTTP, no metrics) is a target.
        self.assertEqual(len({t["targets"][0] for t in targets}), len(processes) - 1,
                         "one target per process")
        promtool = shutil.which("promtool")
        if promtool:  # Debian's prometheus package; promtool reads file_sd files too
            config = os.path.join(self.run_dir, "prometheus.yml")
            targets_file = os.path.join(self.run_dir, "prometheus_targets.json")
            with open(config, "w") as f:
                f.write("scrape_configs:\n  - job_name: behaviorlib_local\n"
                        "    honor_labels: true\n    file_sd_configs:\n"
                        f"      - files: [{targets_file}]\n")
            check = subprocess.run([promtool, "check", "config", config], capture_output=True,
                                   text=True, timeout=30)
            self.assertEqual(check.returncode, 0, check.stdout + check.stderr)

    def test_interrupt(self):
        launcher = subprocess.Popen(self._launcher(), stdout=subprocess.PIPE,
                                    stderr=subprocess.STDOUT, text=True)
        output = []
        try:
            deadline = time.monotonic() + 30
            for line in launcher.stdout:
                output.append(line)
                if "Ctrl-C stops everything" in line or time.monotonic() > deadline:
                    break
            self.assertIn("Ctrl-C stops everything", "".join(output))
            running = {name for name, pid in self._pids().items() if alive(pid)}
            built = {name for name in launch.BEHAVIOR_SYSTEMS
                     if os.access(os.path.join(BUILD_DIR, "bin", name), os.X_OK)}
            self.assertIn("quadrotor_motion_with_pid_control", built)
            self.assertEqual(built - running, set(), "every built behavior system is started")
            launcher.send_signal(signal.SIGINT)
            output.append(launcher.communicate(timeout=30)[0])
        finally:
            if launcher.poll() is None:
                launcher.kill()
                launcher.wait()
        print("".join(output))
        self.assertEqual(launcher.returncode, 130)
        self._assert_all_stopped()
        text = "".join(output)
        for name in ("coordinator", "simulator", "channel_broker"):
            self.assertRegex(text, rf"{name} +exited with code 0")


if __name__ == "__main__":
    parser = argparse.ArgumentParser()
    parser.add_argument("--build-dir", default=BUILD_DIR)
    args, rest = parser.parse_known_args()
    BUILD_DIR = os.path.abspath(args.build_dir)
    unittest.main(argv=[sys.argv[0], *rest], verbosity=2)
