"""A small campaign (deploy/local/campaign.py) against the real processes:
the demo mission over seeds 1-3, two stacks at once in the deterministic
mode, seed 2 with motor 0 stopped 3 simulated seconds into its take-off (the
vehicle, at 1.5 m, drops and TAKE_OFF ends WRONG_PROGRESS 0.7 s later), and
seed 2 flown once more (--check-determinism). Then, in the campaign's
report:

- seed 2 failed at step take_off with WRONG_PROGRESS, its fault injected at
  3.00 s of the step; seeds 1 and 3 succeeded; 2 of 3 with the Wilson
  interval; the causes per step counted, fly_square "not reached" once;
- seed 2 is the worst run: its directory is kept (the flight recording, its
  own report, its logs) and its command line names the seed and the fault;
  the other runs' directories are gone (--keep-worst 1);
- seed 2 flown twice gives the same result (the same causes, the same
  step times);
- bad fault arguments are refused (exit 2) before anything starts.

    /usr/bin/python3 tests/deploy/campaign_test.py --build-dir build
"""

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
import unittest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import deploy_support as ds  # noqa: E402

CAMPAIGN = os.path.join(ds.REPO, "deploy", "local", "campaign.py")
BUILD_DIR = ds.DEFAULT_BUILD_DIR
FAULT = "take_off+3:motor_off:motor=0"
FAILING_SEED = 2


class CampaignTest(unittest.TestCase):
    def setUp(self):
        self.started = time.monotonic()
        self.tmp = tempfile.mkdtemp(prefix="campaign-test-")

    def tearDown(self):
        shutil.rmtree(self.tmp, ignore_errors=True)

    def say(self, text):
        print(f"[{time.monotonic() - self.started:5.1f} s] {text}", flush=True)

    def sayFailedRuns(self, out):
        """Each failed run's message and its failed step's, from the report: the
        campaign's summary names the cause only."""
        try:
            with open(os.path.join(out, "report.json")) as f:
                runs = json.load(f)["runs"]
        except (OSError, ValueError, KeyError) as e:
            self.say(f"no report to read ({e})")
            return
        for run in runs:
            if run.get("state") != "MISSION_STATE_SUCCEEDED":
                self.say(f"seed {run.get('seed')}: {run.get('message')}")

    def campaign(self, *argv, timeout_s=150):
        return subprocess.run([sys.executable, CAMPAIGN, "--build-dir", BUILD_DIR, *argv],
                              stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                              stderr=subprocess.STDOUT, text=True, timeout=timeout_s)

    def test_bad_faults_are_refused_before_anything_starts(self):
        for fault, why in (("3:motor_gone", "no fault kind"),
                           ("landing+3:motor_off", "has no step landing"),
                           ("3:motor_off:motor=4", "not within 0..3"),
                           ("3:gps_noisy", "needs intensity"),
                           ("3:motor_off@seeds=x", "not a seed list")):
            result = self.campaign("--seeds", "1", "--fault", fault,
                                   "--out", os.path.join(self.tmp, "refused"), timeout_s=30)
            self.assertEqual(result.returncode, 2, result.stdout)
            self.assertIn(why, result.stdout)
        self.assertFalse(os.path.exists(os.path.join(self.tmp, "refused")))

    def test_a_small_campaign_names_the_failed_seed_and_flies_it_again_alike(self):
        out = os.path.join(self.tmp, "campaign")
        result = self.campaign("--seed-list", "1-3", "--jobs", "2",
                               "--fault", f"{FAULT}@seeds={FAILING_SEED}",
                               "--check-determinism", str(FAILING_SEED), "--keep-worst", "1",
                               "--min-success-rate", "0.5", "--out", out)
        self.say(f"campaign exited with {result.returncode}:\n{result.stdout}")
        if result.returncode != 0:
            self.sayFailedRuns(out)
        self.assertEqual(result.returncode, 0, result.stdout)
        with open(os.path.join(out, "report.json")) as f:
            report = json.load(f)

        runs = {run["seed"]: run for run in report["runs"]}
        self.assertEqual(sorted(runs), [1, 2, 3])
        for seed in (1, 3):
            self.assertEqual(runs[seed]["state"], "MISSION_STATE_SUCCEEDED", runs[seed])
            self.assertIsNone(runs[seed]["failed_step"])
            self.assertEqual(runs[seed]["injected"], [])
        failed = runs[FAILING_SEED]
        self.assertEqual(failed["state"], "MISSION_STATE_FAILED", failed)
        self.assertEqual(failed["failed_step"]["name"], "take_off", failed)
        self.assertEqual(failed["failed_step"]["behavior"], "TAKE_OFF")
        self.assertEqual(failed["failed_step"]["cause"], "WRONG_PROGRESS", failed)
        self.assertEqual(failed["faults"], [FAULT])
        [injected] = failed["injected"]
        self.assertEqual((injected["fault"], injected["injected_at_s"], injected["late"],
                          injected["error"]), (FAULT, 3.0, False, ""), injected)
        # WRONG_PROGRESS 0.7 s after the motor stopped (the progress check's
        # window), in every run so far.
        take_off = [s for s in failed["steps"] if s["name"] == "take_off"]
        self.assertEqual([s["cause"] for s in take_off], ["WRONG_PROGRESS"])
        self.assertAlmostEqual(take_off[0]["duration_s"], 3.7, delta=0.05)

        success = report["success"]
        self.assertEqual((success["succeeded"], success["runs"]), (2, 3))
        low, high = success["wilson95"]
        self.assertAlmostEqual(low, 0.2077, places=3)
        self.assertAlmostEqual(high, 0.9385, places=3)
        causes = {row["step"]: row["causes"] for row in report["step_causes"]}
        self.assertEqual(causes["settle"], {"GOAL_ACHIEVED": 3})
        self.assertEqual(causes["take_off"], {"GOAL_ACHIEVED": 2, "WRONG_PROGRESS": 1})
        self.assertEqual(causes["fly_square"].get("not reached"), 1, causes)
        self.assertEqual(causes["land"].get("not reached"), 1, causes)
        durations = {row["step"]: row for row in report["step_durations_s"]}
        self.assertEqual(durations["settle"]["attempts"], 3)
        self.assertAlmostEqual(durations["settle"]["median_s"], 2.0, delta=0.02)
        self.assertEqual(durations["fly_square"]["attempts"], 2)

        # The worst run is the failed one, kept with its recording and its
        # command line; the others are gone.
        worst = report["worst"][0]
        self.assertEqual(worst["seed"], FAILING_SEED)
        self.assertEqual(worst["run_dir"], os.path.join(out, "runs", f"seed-{FAILING_SEED}"))
        recording = os.path.join(worst["run_dir"], "recordings", "flight.mcap")
        self.assertGreater(os.path.getsize(recording), 1000)
        with open(recording, "rb") as f:
            self.assertEqual(f.read(8), b"\x89MCAP0\r\n")
        for name in ("report.md", "report.json", "trajectory.png", "timeline.png",
                     os.path.join("logs", "simulator.log")):
            self.assertTrue(os.path.exists(os.path.join(worst["run_dir"], name)), name)
        self.assertIn(f"--seed-list {FAILING_SEED} ", worst["reproduce"])
        self.assertIn(f"--fault {FAULT} ", worst["reproduce"])
        self.assertNotIn("@seeds", worst["reproduce"])
        self.assertEqual(sorted(os.listdir(os.path.join(out, "runs"))), [f"seed-{FAILING_SEED}"])
        self.assertFalse(os.path.exists(os.path.join(out, "stacks")))

        # The same seed and fault, flown again on a new stack: the same result.
        check = report["determinism"]
        self.assertEqual(check["seed"], FAILING_SEED)
        self.assertTrue(check["same"], check)
        self.assertTrue(check["same_causes"])
        self.assertLessEqual(check["duration_diff_s"], 0.05)
        first, again = check["runs"]
        # (Not its message: the altitude when the check fired differs by a few
        # centimetres from run to run, the climb starting a quantum or two
        # earlier or later after the activation.)
        for key in ("name", "behavior", "attempt", "cause"):
            self.assertEqual(again["failed_step"][key], first["failed_step"][key])

        with open(os.path.join(out, "report.md")) as f:
            markdown = f.read()
        for text in (f"seed **{FAILING_SEED}**: FAILED at step `take_off`", "**WRONG_PROGRESS**",
                     "Wilson score interval 20.8 - 93.8 %", "**the same result**",
                     worst["reproduce"]):
            self.assertIn(text, markdown)
        self.say("done")


if __name__ == "__main__":
    parser = argparse.ArgumentParser()
    parser.add_argument("--build-dir", default=BUILD_DIR)
    args, rest = parser.parse_known_args()
    BUILD_DIR = os.path.abspath(args.build_dir)
    unittest.main(argv=[sys.argv[0], *rest], verbosity=2)
