"""What "the same result" means for two runs of one seed
(deploy/local/determinism.py compare), without the built binaries: every
step's cause must agree, but a recurrent behavior ended by the mission
(INTERRUPTED) in one run and by itself in the other raced the mission's own
end and is the same result.

    /usr/bin/python3 tests/deploy/determinism_test.py
"""

import os
import sys
import unittest

REPO = os.path.abspath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", ".."))
sys.path.insert(0, os.path.join(REPO, "deploy", "local"))
import determinism  # noqa: E402


def run(take_off, localization):
    return {"steps": [
        {"name": "settle", "cause": "GOAL_ACHIEVED", "duration_s": 2.0, "kind": "step"},
        {"name": "take_off", "cause": take_off, "duration_s": 3.7, "kind": "step"},
        {"name": "SELF_LOCALIZE_WITH_EKF_SENSOR_FUSION", "cause": localization,
         "duration_s": 9.0, "kind": "recurrent"},
    ], "samples": []}


class CompareTest(unittest.TestCase):
    def test_a_recurrent_behavior_racing_the_missions_end_is_the_same_result(self):
        result = determinism.compare(run("WRONG_PROGRESS", "WRONG_PROGRESS"),
                                     run("WRONG_PROGRESS", "INTERRUPTED"))
        self.assertTrue(result["same"], result["differences"])
        self.assertTrue(result["same_causes"])

    def test_a_step_that_ended_otherwise_differs(self):
        result = determinism.compare(run("WRONG_PROGRESS", "INTERRUPTED"),
                                     run("GOAL_ACHIEVED", "INTERRUPTED"))
        self.assertFalse(result["same"])
        self.assertIn("step causes differ", result["differences"][0])

    def test_a_recurrent_behavior_that_failed_otherwise_differs(self):
        result = determinism.compare(run("WRONG_PROGRESS", "WRONG_PROGRESS"),
                                     run("WRONG_PROGRESS", "PROCESS_FAILURE"))
        self.assertFalse(result["same_causes"])

    def test_a_step_interrupted_in_one_run_only_differs(self):
        result = determinism.compare(run("INTERRUPTED", "INTERRUPTED"),
                                     run("WRONG_PROGRESS", "INTERRUPTED"))
        self.assertFalse(result["same_causes"])


if __name__ == "__main__":
    unittest.main(verbosity=2)
