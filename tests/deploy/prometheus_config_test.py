"""promtool (Debian's prometheus package) accepts the Prometheus
configurations of deploy/prometheus (Compose and local launcher) and the
alert rules, and the rules pass their unit tests (tests/*.yml, promtool
test rules). Every alert has a test case in which it fires.

    /usr/bin/python3 tests/deploy/prometheus_config_test.py
"""

import glob
import os
import shutil
import subprocess
import sys
import unittest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import deploy_support as ds  # noqa: E402

PROMTOOL = shutil.which("promtool") or "/usr/bin/promtool"
RULE_FILES = sorted(glob.glob(os.path.join(ds.PROMETHEUS_DIR, "rules", "*.yml")))
TEST_FILES = sorted(glob.glob(os.path.join(ds.PROMETHEUS_DIR, "tests", "*.yml")))


class PromtoolTest(unittest.TestCase):
    def promtool(self, *args):
        result = subprocess.run([PROMTOOL, *args], capture_output=True, text=True, timeout=60,
                                cwd=ds.PROMETHEUS_DIR)
        output = result.stdout + result.stderr
        self.assertEqual(result.returncode, 0, f"promtool {' '.join(args)}:\n{output}")
        return output

    def test_promtool_is_installed(self):
        self.assertTrue(os.access(PROMTOOL, os.X_OK),
                        "promtool not found: install Debian's prometheus (scripts/install-deps.sh)")

    def test_check_config(self):
        for config in ("prometheus.yml", "prometheus-local.yml"):
            with self.subTest(config=config):
                output = self.promtool("check", "config", config)
                self.assertIn("SUCCESS", output)
                # The rules are found through the configuration's rule_files.
                self.assertIn("rules found", output)

    def test_check_rules(self):
        self.assertTrue(RULE_FILES)
        output = self.promtool("check", "rules", *RULE_FILES)
        self.assertNotIn("FAILED", output)

    def test_rule_unit_tests(self):
        self.assertTrue(TEST_FILES)
        output = self.promtool("test", "rules", *TEST_FILES)
        self.assertIn("SUCCESS", output)

    def test_every_alert_has_a_firing_test_case(self):
        alerts = {rule["alert"] for path in RULE_FILES for group in ds.read_yaml(path)["groups"]
                  for rule in group["rules"] if "alert" in rule}
        self.assertGreaterEqual(alerts, {"BehaviorSystemDown", "BehaviorProcessFailure",
                                         "BehaviorTimeOutRateRising", "SimulatorBehindRealTime",
                                         "BehaviorActivationSlow", "MissionFailed",
                                         "SafetyActionTaken", "VehicleCrashed",
                                         "GrpcServerErrors"})
        fired = set()
        for path in TEST_FILES:
            for case in ds.read_yaml(path)["tests"]:
                for check in case.get("alert_rule_test", []):
                    if check.get("exp_alerts"):
                        fired.add(check["alertname"])
        self.assertEqual(alerts - fired, set(), "alerts without a test case where they fire")


if __name__ == "__main__":
    unittest.main(verbosity=2)
