"""Checks reflection_client.py against reflection_demo_server.

    /usr/bin/python3 reflection_test.py --server build/tests/integration/reflection_demo_server

(or set REFLECTION_DEMO_SERVER). Needs python3-grpcio and python3-protobuf.
"""

import argparse
import os
import subprocess
import sys
import unittest

import grpc
from google.protobuf import json_format

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..",
                                "deploy", "local"))
import reflection_client as rc  # noqa: E402

SERVER = os.environ.get("REFLECTION_DEMO_SERVER", "")


class ReflectionClientTest(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        if not SERVER:
            raise unittest.SkipTest("no --server / REFLECTION_DEMO_SERVER given")
        cls.process = subprocess.Popen([SERVER, "127.0.0.1:0"], stdout=subprocess.PIPE, text=True)
        line = cls.process.stdout.readline().strip()
        if not line.startswith("port="):
            cls.process.kill()
            raise RuntimeError(f"demo server printed {line!r}")
        cls.address = f"127.0.0.1:{line.split('=', 1)[1]}"

    @classmethod
    def tearDownClass(cls):
        cls.process.terminate()
        cls.process.wait(timeout=10)

    def test_list_services(self):
        for version in (None, "v1", "v1alpha"):
            services = rc.list_services(self.address, version=version)
            for name in ("behaviorlib.v1.BehaviorSystem", "grpc.health.v1.Health",
                         "grpc.reflection.v1.ServerReflection",
                         "grpc.reflection.v1alpha.ServerReflection"):
                self.assertIn(name, services)

    def test_file_containing_symbol_has_comments_and_dependencies(self):
        files = rc.file_containing_symbol(self.address, "behaviorlib.v1.BehaviorSystem")
        self.assertEqual(files[0].name, "behaviorlib/v1/behavior.proto")
        names = {f.name for f in files}
        self.assertTrue({"behaviorlib/v1/options.proto", "google/protobuf/struct.proto",
                         "google/protobuf/descriptor.proto"} <= names)
        self.assertIn("Served by every behavior-system process",
                      rc.leading_comments(files, "behaviorlib.v1.BehaviorSystem"))
        self.assertIn("Describes every hosted behavior",
                      rc.leading_comments(files, "behaviorlib.v1.BehaviorSystem.ListBehaviors"))

    def test_unknown_symbol_is_not_found(self):
        with self.assertRaises(rc.ReflectionError) as caught:
            rc.file_containing_symbol(self.address, "behaviorlib.v1.NoSuchService")
        self.assertEqual(caught.exception.code, grpc.StatusCode.NOT_FOUND)

    def test_extensions(self):
        files = rc.file_containing_extension(self.address, "google.protobuf.FieldOptions", 51234)
        self.assertEqual(files[0].name, "behaviorlib/v1/options.proto")
        self.assertIn(51234,
                      rc.all_extension_numbers_of_type(self.address, "google.protobuf.FieldOptions"))

    def test_file_by_filename(self):
        files = rc.file_by_filename(self.address, "grpc/health/v1/health.proto", version="v1alpha")
        self.assertEqual([f.name for f in files], ["grpc/health/v1/health.proto"])

    def test_pool_builds_messages_and_calls_methods(self):
        pool = rc.pool_for_symbol(self.address, "behaviorlib.v1.BehaviorSystem")
        request_class = rc.message_class(pool, "behaviorlib.v1.ActivateBehaviorRequest")
        request = json_format.ParseDict(
            {"behavior": "WAIT", "parameters": {"duration": 1.5}}, request_class(),
            descriptor_pool=pool)
        self.assertEqual(request.behavior, "WAIT")
        self.assertEqual(request_class.FromString(request.SerializeToString()), request)
        self.assertEqual(json_format.MessageToDict(request, descriptor_pool=pool)["parameters"],
                         {"duration": 1.5})
        with grpc.insecure_channel(self.address) as channel:
            # The demo server's BehaviorSystem has no overrides.
            with self.assertRaises(grpc.RpcError) as caught:
                rc.unary_call(channel, pool, "behaviorlib.v1.BehaviorSystem", "ListBehaviors", {})
            self.assertEqual(caught.exception.code(), grpc.StatusCode.UNIMPLEMENTED)
            # The health service through a pool built by reflection.
            health = rc.pool_for_symbol(self.address, "grpc.health.v1.Health")
            reply = rc.unary_call(channel, health, "grpc.health.v1.Health", "Check",
                                  {"service": ""})
            self.assertEqual(reply.status, 1)  # SERVING


if __name__ == "__main__":
    parser = argparse.ArgumentParser()
    parser.add_argument("--server", default=SERVER)
    args, rest = parser.parse_known_args()
    SERVER = args.server
    unittest.main(argv=[sys.argv[0]] + rest)
