"""Mutual TLS of the servers (issue: security and hardening, goal 1).

    /usr/bin/python3 tls_test.py --build-dir build

Starts the real coordinator on loopback with --tls-cert/--tls-key/--tls-ca
from scripts/make-dev-certs.sh and checks that a client with a certificate
from the CA is served, and that plaintext, no client certificate, a
certificate from another CA, an expired certificate and a server from
another CA are each refused; /metrics stays plain HTTP. Also: binding a
non-loopback address without TLS needs --insecure, and partial TLS flags
stop the start. Needs python3-grpcio and openssl.
"""

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
import unittest
import urllib.request

import grpc

REPO = os.path.abspath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", ".."))
sys.path.insert(0, os.path.join(REPO, "deploy", "local"))
import rpc  # noqa: E402

BUILD_DIR = "build"
MAKE_CERTS = os.path.join(REPO, "scripts", "make-dev-certs.sh")


def make_certs(out, *names, expired=False):
    argv = [MAKE_CERTS, "--out", out, *names] + (["--expired"] if expired else [])
    subprocess.run(argv, check=True, capture_output=True)


def read(path):
    with open(path, "rb") as f:
        return f.read()


def credentials(certs, name=None, ca=None):
    """TLS credentials trusting `ca` (default certs/ca.pem), with the client
    certificate `name` from `certs`, or none."""
    root = read(ca or os.path.join(certs, "ca.pem"))
    if name is None:
        return grpc.ssl_channel_credentials(root_certificates=root)
    return grpc.ssl_channel_credentials(root_certificates=root,
                                        private_key=read(os.path.join(certs, f"{name}.key")),
                                        certificate_chain=read(os.path.join(certs, f"{name}.pem")))


def health(address, creds, timeout=5.0):
    """Health/Check over a channel with `creds` (None: plaintext)."""
    channel = (grpc.secure_channel(address, creds) if creds is not None
               else grpc.insecure_channel(address))
    with channel:
        check = channel.unary_unary("/grpc.health.v1.Health/Check",
                                    request_serializer=rpc._encode_health_request,
                                    response_deserializer=rpc._decode_health_response)
        return check("", timeout=timeout)


class Server:
    """A coordinator process; its ports from --port-file."""

    def __init__(self, argv, run_dir):
        self.port_file = os.path.join(run_dir, f"ports-{time.monotonic_ns()}")
        self.log = open(os.path.join(run_dir, "coordinator.log"), "a+")
        self.process = subprocess.Popen(
            [os.path.join(BUILD_DIR, "bin", "coordinator"), "--port-file", self.port_file,
             *argv], stdout=self.log, stderr=subprocess.STDOUT)
        self.ports = {}

    def wait_ports(self, timeout_s=20.0):
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                return False
            if os.path.exists(self.port_file):
                with open(self.port_file) as f:
                    self.ports = dict(line.strip().split("=", 1) for line in f if "=" in line)
                return True
            time.sleep(0.05)
        raise AssertionError("the coordinator wrote no port file")

    def output(self):
        self.log.seek(0)
        return self.log.read()

    def stop(self):
        if self.process.poll() is None:
            self.process.terminate()
            self.process.wait(timeout=15)
        self.log.close()


class TlsTest(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        cls.dir = tempfile.mkdtemp(prefix="tls-test-")
        cls.certs = os.path.join(cls.dir, "certs")
        make_certs(cls.certs, "coordinator", "operator")
        # Another CA, and an expired certificate from the right CA.
        cls.other = os.path.join(cls.dir, "other")
        make_certs(cls.other, "operator", "coordinator")
        cls.expired = os.path.join(cls.dir, "expired")
        os.makedirs(cls.expired, mode=0o700)
        for f in ("ca.pem", "ca.key"):
            shutil.copy(os.path.join(cls.certs, f), cls.expired)
        make_certs(cls.expired, "operator", expired=True)
        cls.server = Server(["--listen", "127.0.0.1:0", "--metrics-listen", "127.0.0.1:0",
                             *cls.tls_flags(cls.certs, "coordinator")], cls.dir)
        if not cls.server.wait_ports():
            raise AssertionError(f"the coordinator did not start:\n{cls.server.output()}")
        cls.address = f"127.0.0.1:{cls.server.ports['grpc_port']}"
        cls.metrics = f"127.0.0.1:{cls.server.ports['metrics_port']}"

    @classmethod
    def tearDownClass(cls):
        cls.server.stop()
        shutil.rmtree(cls.dir, ignore_errors=True)

    @staticmethod
    def tls_flags(certs, name):
        return ["--tls-cert", os.path.join(certs, f"{name}.pem"),
                "--tls-key", os.path.join(certs, f"{name}.key"),
                "--tls-ca", os.path.join(certs, "ca.pem")]

    def assert_refused(self, creds):
        with self.assertRaises(grpc.RpcError) as raised:
            health(self.address, creds)
        self.assertEqual(raised.exception.code(), grpc.StatusCode.UNAVAILABLE)

    def test_a_client_certificate_from_the_ca_is_served(self):
        self.assertEqual(health(self.address, credentials(self.certs, "operator")), "SERVING")
        # Reflection and a Coordinator call through the launcher's client.
        rpc.rc.use_tls(os.path.join(self.certs, "operator.pem"),
                       os.path.join(self.certs, "operator.key"),
                       os.path.join(self.certs, "ca.pem"))
        try:
            client = rpc.Client(self.address, ["behaviorlib.v1.Coordinator"])
            reply = client.call("behaviorlib.v1.Coordinator", "ListMissions", {})
            self.assertEqual(reply.get("missions", []), [])
            client.close()
        finally:
            rpc.rc._CREDENTIALS = None

    def test_plaintext_is_refused(self):
        self.assert_refused(None)

    def test_no_client_certificate_is_refused(self):
        self.assert_refused(credentials(self.certs))

    def test_a_certificate_from_another_ca_is_refused(self):
        self.assert_refused(credentials(self.other, "operator",
                                        ca=os.path.join(self.certs, "ca.pem")))

    def test_an_expired_certificate_is_refused(self):
        self.assert_refused(credentials(self.expired, "operator",
                                        ca=os.path.join(self.certs, "ca.pem")))

    def test_a_server_from_another_ca_is_not_trusted(self):
        self.assert_refused(credentials(self.other, "operator"))

    def test_metrics_stay_plain_http_on_loopback(self):
        # Debian's civetweb crashes serving HTTPS with OpenSSL 3 (decision
        # 23): /metrics is plain HTTP, bound to loopback here (the private
        # network in compose).
        with urllib.request.urlopen(f"http://{self.metrics}/metrics", timeout=10) as page:
            self.assertIn("# TYPE", page.read().decode())

    def test_a_public_address_without_tls_needs_insecure(self):
        refused = Server(["--listen", "0.0.0.0:0", "--metrics-listen", ""], self.dir)
        try:
            self.assertFalse(refused.wait_ports())
            self.assertNotEqual(refused.process.wait(timeout=15), 0)
            self.assertIn("--insecure", refused.output())
        finally:
            refused.stop()
        accepted = Server(["--listen", "0.0.0.0:0", "--metrics-listen", "", "--insecure"],
                          self.dir)
        try:
            self.assertTrue(accepted.wait_ports())
            port = accepted.ports["grpc_port"]
            self.assertEqual(health(f"127.0.0.1:{port}", None), "SERVING")
            self.assertIn("without TLS (--insecure)", accepted.output())
        finally:
            accepted.stop()

    def test_missing_or_partial_tls_files_are_refused_at_start(self):
        server = Server(["--listen", "127.0.0.1:0", "--metrics-listen", "",
                         "--tls-cert", os.path.join(self.certs, "coordinator.pem")], self.dir)
        try:
            self.assertFalse(server.wait_ports())
            self.assertIn("--tls-key is missing", server.output())
        finally:
            server.stop()


if __name__ == "__main__":
    parser = argparse.ArgumentParser()
    parser.add_argument("--build-dir", default="build")
    args, rest = parser.parse_known_args()
    BUILD_DIR = os.path.abspath(args.build_dir)
    unittest.main(argv=[sys.argv[0], "-v", *rest])
