"""End to end with mutual TLS: `deploy/local/launch.py --tls` runs the whole
stack (broker, simulator, coordinator, behavior systems), each process with
its own certificate from a fresh CA. While it serves:
- every behavior system is registered at the coordinator: each dialed the
  coordinator and was dialed back over mTLS;
- behaviorctl with the operator's certificate flies the demo mission to
  SUCCEEDED (coordinator -> systems -> simulator and broker, all over TLS);
- plaintext and a client without a certificate are refused by every server;
- the run's access policy holds (the operator may not drive the simulator);
- the console serves HTTPS, and its own identity only views: without a token
  it lists the systems but its controls are refused (403, PERMISSION_DENIED
  naming the role), a wrong token is refused even for viewing, and the run's
  operator token (certs/console-token, in the URL the launcher printed)
  passes the policy.
Then SIGINT stops it cleanly.

    /usr/bin/python3 tests/e2e/local_tls_test.py --build-dir build
"""

import argparse
import http.client
import json
import os
import re
import shutil
import signal
import ssl
import subprocess
import sys
import tempfile
import time
import unittest
import urllib.parse

import grpc

REPO = os.path.abspath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", ".."))
sys.path.insert(0, os.path.join(REPO, "deploy", "local"))
import rpc  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from local_demo_test import kill_launched  # noqa: E402

LAUNCHER = os.path.join(REPO, "deploy", "local", "launch.py")
BUILD_DIR = os.path.join(REPO, "build")
SERVING = re.compile(r"^\s+(\S+)\s+gRPC (127\.0\.0\.1:\d+)")
CONSOLE = re.compile(r"^\s+console: (https://127\.0\.0\.1:\d+/\S*)$", re.MULTILINE)


class LocalTlsTest(unittest.TestCase):
    def setUp(self):
        self.run_dir = tempfile.mkdtemp(prefix="local-tls-e2e-")
        self.log = open(os.path.join(self.run_dir, "launcher.log"), "w+")
        self.launcher = subprocess.Popen(
            [sys.executable, LAUNCHER, "--build-dir", BUILD_DIR, "--run-dir", self.run_dir,
             "--time-scale", "max", "--tls",
             "--systems", "quadrotor_motion_with_pid_control,multi_sensor_fusion"],
            stdout=self.log, stderr=subprocess.STDOUT, text=True)

    def tearDown(self):
        # After a failed assertion: the launcher stops its stack (SIGINT),
        # and whatever is left of it is killed. Its processes run in sessions
        # of their own, so killing the launcher alone would leave them running.
        if self.launcher.poll() is None:
            self.launcher.send_signal(signal.SIGINT)
            try:
                self.launcher.wait(timeout=60)
            except subprocess.TimeoutExpired:
                self.launcher.kill()
                self.launcher.wait()
        kill_launched(self.run_dir)
        self.log.close()
        shutil.rmtree(self.run_dir, ignore_errors=True)

    def output(self):
        self.log.flush()
        with open(self.log.name) as f:
            return f.read()

    def wait_serving(self, timeout_s=60.0):
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            text = self.output()
            if "Ctrl-C stops everything." in text:
                return {m.group(1): m.group(2)
                        for m in map(SERVING.match, text.splitlines()) if m}
            self.assertIsNone(self.launcher.poll(), f"the launcher exited:\n{text}")
            time.sleep(0.2)
        self.fail(f"the stack did not start:\n{self.output()}")

    def ctl(self, *args, timeout=90):
        certs = os.path.join(self.run_dir, "certs")
        return subprocess.run(
            [os.path.join(BUILD_DIR, "bin", "behaviorctl"),
             "--tls-cert", os.path.join(certs, "operator.pem"),
             "--tls-key", os.path.join(certs, "operator.key"),
             "--tls-ca", os.path.join(certs, "ca.pem"), *args],
            capture_output=True, text=True, timeout=timeout)

    def console_call(self, url, name, request, token=None):
        """POST /api/coordinator/NAME to the console over HTTPS (checked
        against the run's CA): (HTTP status, the JSON reply)."""
        context = ssl.create_default_context(
            cafile=os.path.join(self.run_dir, "certs", "ca.pem"))
        parsed = urllib.parse.urlparse(url)
        connection = http.client.HTTPSConnection(parsed.hostname, parsed.port, timeout=30,
                                                 context=context)
        headers = {"Content-Type": "application/json"}
        if token is not None:
            headers["Authorization"] = "Bearer " + token
        try:
            connection.request("POST", f"/api/coordinator/{name}", json.dumps(request), headers)
            reply = connection.getresponse()
            return reply.status, json.loads(reply.read())
        finally:
            connection.close()

    def check_the_console_acts_with_the_browsers_token(self):
        found = CONSOLE.search(self.output())
        self.assertIsNotNone(found, self.output())
        url = found.group(1)
        query = urllib.parse.parse_qs(urllib.parse.urlparse(url).query)
        with open(os.path.join(self.run_dir, "certs", "console-token")) as f:
            token = f.read().strip()
        self.assertEqual(query.get("token"), [token], "the printed URL carries the run's token")
        self.assertEqual(os.stat(os.path.join(self.run_dir, "certs", "console-token")).st_mode
                         & 0o077, 0, "the token file is its owner's alone")
        # Without a token: the console's own identity, a viewer.
        status, reply = self.console_call(url, "ListSystems", {})
        self.assertEqual(status, 200, reply)
        for name, request, role in (
                ("EmergencyLand", {"robot_id": "drone1", "reason": "test"}, "safety"),
                ("PauseMission", {"mission_id": "no-such-mission"}, "operator")):
            status, reply = self.console_call(url, name, request)
            self.assertEqual(status, 403, (name, reply))
            self.assertIn(f"needs the role {role}", reply.get("message", ""), (name, reply))
        # A wrong token is refused, even for what the console alone may do.
        status, reply = self.console_call(url, "ListSystems", {}, token="not-the-token")
        self.assertIn(status, (401, 403), reply)
        # The run's operator token passes the policy: the mission is then
        # looked for (and not found).
        status, reply = self.console_call(url, "PauseMission", {"mission_id": "no-such-mission"},
                                          token=token)
        self.assertEqual(status, 404, reply)

    def test_the_stack_runs_and_flies_over_mutual_tls(self):
        servers = self.wait_serving()
        for name in ("channel_broker", "simulator", "coordinator", "basic_quadrotor_behaviors",
                     "quadrotor_motion_with_pid_control"):
            self.assertIn(name, servers)
        coordinator = servers["coordinator"]
        # Plaintext and a client without a certificate: refused everywhere.
        with open(os.path.join(self.run_dir, "certs", "ca.pem"), "rb") as f:
            ca_only = grpc.ssl_channel_credentials(root_certificates=f.read())
        for name, address in servers.items():
            with self.assertRaises(grpc.RpcError, msg=name):
                rpc.health_status(address, timeout=5.0)
            with grpc.secure_channel(address, ca_only) as channel:
                check = channel.unary_unary("/grpc.health.v1.Health/Check",
                                            request_serializer=rpc._encode_health_request,
                                            response_deserializer=rpc._decode_health_response)
                with self.assertRaises(grpc.RpcError, msg=name):
                    check("", timeout=5.0)
        # The run's access policy: the operator may not drive the simulator.
        certs = os.path.join(self.run_dir, "certs")
        operator = grpc.ssl_channel_credentials(
            root_certificates=open(os.path.join(certs, "ca.pem"), "rb").read(),
            private_key=open(os.path.join(certs, "operator.key"), "rb").read(),
            certificate_chain=open(os.path.join(certs, "operator.pem"), "rb").read())
        with grpc.secure_channel(servers["simulator"], operator) as channel:
            reset = channel.unary_unary("/behaviorlib.v1.Simulator/SetTimeScale")
            with self.assertRaises(grpc.RpcError) as refused:
                reset(b"", timeout=5.0)
            self.assertEqual(refused.exception.code(), grpc.StatusCode.PERMISSION_DENIED)
            self.assertIn("needs the role admin", refused.exception.details())
        self.check_the_console_acts_with_the_browsers_token()
        # The systems registered over mTLS (as themselves) and are up.
        deadline = time.monotonic() + 30
        while True:
            systems = self.ctl("--coordinator", coordinator, "systems", "-o", "json", timeout=20)
            self.assertEqual(systems.returncode, 0, systems.stderr)
            if systems.stdout.count("SYSTEM_STATE_UP") >= 2 or time.monotonic() > deadline:
                break
            time.sleep(0.5)
        self.assertGreaterEqual(systems.stdout.count("SYSTEM_STATE_UP"), 2, systems.stdout)
        # The demo mission, sent by behaviorctl as text.
        flown = self.ctl("--coordinator", coordinator, "mission", "run",
                         os.path.join(REPO, "deploy", "missions", "demo.yaml"))
        self.assertEqual(flown.returncode, 0, flown.stdout + flown.stderr)
        self.assertIn("MISSION_STATE_SUCCEEDED", flown.stdout + flown.stderr)
        self.launcher.send_signal(signal.SIGINT)
        self.assertEqual(self.launcher.wait(timeout=60), 128 + signal.SIGINT, self.output())
        self.assertNotIn("exited with code -", self.output())


if __name__ == "__main__":
    parser = argparse.ArgumentParser()
    parser.add_argument("--build-dir", default=BUILD_DIR)
    args, rest = parser.parse_known_args()
    BUILD_DIR = os.path.abspath(args.build_dir)
    unittest.main(argv=[sys.argv[0], "-v", *rest])
