#!/usr/bin/env python3
"""Every behavior system's --config, typed (decision 45), through its binary.

For each system: its shipped config.yaml is accepted (the process starts and
prints its start line); --help-config lists the keys of every behavior it
hosts, with the library's; a misspelled key, a value out of range and a section
of a behavior it does not host stop it with exit code 2 and the file's line.

  system_config_test.py --bin-dir build/bin --source-dir .
"""

import argparse
import os
import signal
import subprocess
import sys
import tempfile
import unittest

ARGS = None

# A key of each system's own, a behavior of it and a value out of its range.
SYSTEMS = {
    "basic_quadrotor_behaviors": ("TAKE_OFF", "altitude_tolerance_m", "-1"),
    "quadrotor_motion_with_pid_control": ("FOLLOW_PATH", "max_lag_m", "0.01"),
    "quadrotor_motion_with_mpc_control": ("QUADROTOR_MPC_MOTION_CONTROL", "horizon_steps", "1"),
    "quadrotor_motion_with_platform_control": ("ROTATE_WITH_PLATFORM_CONTROL",
                                               "max_yaw_lag_rad", "8"),
    "multi_sensor_fusion": ("SELF_LOCALIZE_WITH_EKF_SENSOR_FUSION", "gps_window", "0"),
    "navigation_with_lidar": ("SELF_LOCALIZE_AND_MAP_WITH_LIDAR", "resolution_m", "2"),
    "attention_to_visual_markers": ("PAY_ATTENTION_TO_QR_CODES", "pose_timeout_s", "0"),
    "swarm_interaction": ("PAY_ATTENTION_TO_ROBOT_MESSAGES", "write_period_s", "100"),
    "operator_interaction": ("REQUEST_OPERATOR_ASSISTANCE", "poll_period_s", "11"),
}


def binary(system):
    return os.path.join(ARGS.bin_dir, system)


def run(system, *flags, timeout=20):
    return subprocess.run([binary(system), "--listen", "127.0.0.1:0", "--metrics-listen", "",
                           *flags], capture_output=True, text=True, timeout=timeout)


def start_and_stop(system, config):
    """Starts the system with `config`, waits for its start line, stops it."""
    proc = subprocess.Popen([binary(system), "--listen", "127.0.0.1:0", "--metrics-listen", "",
                             "--config", config], stderr=subprocess.PIPE, text=True)
    try:
        line = proc.stderr.readline()
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        proc.stderr.close()
    return line


class SystemConfigTest(unittest.TestCase):
    def write(self, text):
        f = tempfile.NamedTemporaryFile("w", suffix=".yaml", delete=False)
        f.write(text)
        f.close()
        self.addCleanup(os.remove, f.name)
        return f.name

    def test_shipped_configs_start(self):
        for system in SYSTEMS:
            config = os.path.join(ARGS.source_dir, "services", "systems", system, "config.yaml")
            if not os.path.exists(config):
                continue
            with self.subTest(system=system):
                line = start_and_stop(system, config)
                self.assertIn(f"{system}: robot drone1, behaviors [", line)

    def test_help_config_lists_every_behavior_and_key(self):
        for system, (behavior, key, _) in SYSTEMS.items():
            with self.subTest(system=system):
                done = run(system, "--help-config")
                self.assertEqual(done.returncode, 0, done.stderr)
                self.assertIn(f"--config of {system}", done.stdout)
                self.assertIn("frequency_hz (number, Hz)", done.stdout)
                self.assertIn(f"  {behavior}:\n", done.stdout)
                self.assertIn(f"    {key} (", done.stdout)

    def test_bad_keys_stop_the_system_with_their_line(self):
        for system, (behavior, key, bad) in SYSTEMS.items():
            with self.subTest(system=system):
                misspelled = self.write(f"behaviors:\n  {behavior}:\n    {key}x: 1\n")
                done = run(system, "--config", misspelled)
                self.assertEqual(done.returncode, 2, done.stderr)
                self.assertIn(f"{misspelled}:3:5: behaviors.{behavior}: unknown key '{key}x'",
                              done.stderr)
                self.assertIn(key, done.stderr.split("known keys:")[1])

                out_of_range = self.write(f"behaviors:\n  {behavior}:\n    {key}: {bad}\n")
                done = run(system, "--config", out_of_range)
                self.assertEqual(done.returncode, 2, done.stderr)
                self.assertIn(f"{out_of_range}:3:", done.stderr)
                self.assertIn("out of range", done.stderr)

                unhosted = self.write("behaviors:\n  NOT_A_BEHAVIOR: {}\n")
                done = run(system, "--config", unhosted)
                self.assertEqual(done.returncode, 2, done.stderr)
                self.assertIn(f"{unhosted}:2:3: behaviors: no behavior 'NOT_A_BEHAVIOR'",
                              done.stderr)


def main():
    global ARGS
    parser = argparse.ArgumentParser()
    parser.add_argument("--bin-dir", required=True)
    parser.add_argument("--source-dir", required=True)
    ARGS, rest = parser.parse_known_args()
    unittest.main(argv=[sys.argv[0]] + rest, verbosity=2)


if __name__ == "__main__":
    main()
