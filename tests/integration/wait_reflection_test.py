"""Drives a real basic_quadrotor_behaviors process through server reflection
only, as a grpcurl user would: no generated stubs, every message class comes
from the descriptors the server sends (reflection_client.py).

    /usr/bin/python3 wait_reflection_test.py \
        --binary build/bin/basic_quadrotor_behaviors

(or set BASIC_QUADROTOR_BEHAVIORS). Needs python3-grpcio and python3-protobuf.
The tests run in name order against one process; the last one stops it.
"""

import argparse
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import unittest

import grpc
from google.protobuf import json_format

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..",
                                "deploy", "local"))
import reflection_client as rc  # noqa: E402

BINARY = os.environ.get("BASIC_QUADROTOR_BEHAVIORS", "")
TIMEOUT_S = 10.0


def read_ports(path):
    ports = {}
    with open(path) as f:
        for line in f:
            key, _, value = line.strip().partition("=")
            if value:
                ports[key] = int(value)
    return ports


class WaitThroughReflectionTest(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        if not BINARY:
            raise unittest.SkipTest("no --binary / BASIC_QUADROTOR_BEHAVIORS given")
        cls.tmp = tempfile.mkdtemp(prefix="wait-reflection-")
        port_file = os.path.join(cls.tmp, "ports")
        cls.process = subprocess.Popen([
            BINARY, "--listen", "127.0.0.1:0", "--metrics-listen", "127.0.0.1:0",
            "--port-file", port_file, "--robot-id", "refl-drone"])
        deadline = time.monotonic() + TIMEOUT_S
        while not os.path.exists(port_file):
            if cls.process.poll() is not None:
                raise RuntimeError(f"{BINARY} exited with {cls.process.returncode} before serving")
            if time.monotonic() > deadline:
                cls.process.kill()
                cls.process.wait(timeout=TIMEOUT_S)
                raise RuntimeError(f"{BINARY} did not write its port file in time")
            time.sleep(0.01)
        cls.address = f"127.0.0.1:{read_ports(port_file)['grpc_port']}"
        cls.channel = grpc.insecure_channel(cls.address)

    @classmethod
    def tearDownClass(cls):
        cls.channel.close()
        if cls.process.poll() is None:
            cls.process.kill()
            cls.process.wait(timeout=TIMEOUT_S)
        shutil.rmtree(cls.tmp, ignore_errors=True)

    # -- like `grpcurl ADDRESS list` -----------------------------------------
    def test_1_lists_services(self):
        services = rc.list_services(self.address)
        for name in ("behaviorlib.v1.Wait", "behaviorlib.v1.BehaviorSystem",
                     "grpc.health.v1.Health", "grpc.reflection.v1alpha.ServerReflection"):
            self.assertIn(name, services)

    # -- like `grpcurl ADDRESS describe behaviorlib.v1.Wait` ------------------
    def test_2_describes_wait_with_comments(self):
        files = rc.file_containing_symbol(self.address, "behaviorlib.v1.Wait")
        # The service is generated from WAIT's declaration (decision 21): its
        # file imports the declaring file, which reflection serves with it.
        self.assertEqual(files[0].name,
                         "behaviorlib/v1/behaviors/basic_quadrotor_behaviors_services.proto")
        self.assertIn("behaviorlib/v1/behaviors/basic_quadrotor_behaviors.proto",
                      [f.name for f in files])
        service_comment = rc.leading_comments(files, "behaviorlib.v1.Wait")
        self.assertIn("WAIT: stays active", service_comment)
        self.assertIn("GOAL_ACHIEVED", service_comment)
        self.assertIn("Activates WAIT", rc.leading_comments(files, "behaviorlib.v1.Wait.Activate"))
        field_comment = rc.leading_comments(files, "behaviorlib.v1.WaitParameters.duration_s")
        self.assertIn("How long to wait, in seconds", field_comment)

        pool = rc.pool_from_files(files)
        service = pool.FindServiceByName("behaviorlib.v1.Wait")
        self.assertEqual(
            {m.name for m in service.methods},
            {"Activate", "Deactivate", "CheckActivation", "CheckSituation", "Pause", "Resume",
             "Modify"})
        activate = service.methods_by_name["Activate"]
        self.assertEqual(activate.input_type.full_name, "behaviorlib.v1.WaitActivateRequest")
        self.assertEqual(activate.output_type.full_name, "behaviorlib.v1.ActivateResponse")

    # -- like `grpcurl -d '{"service": "..."}' ADDRESS grpc.health.v1.Health/Check`
    def test_3_health_is_serving(self):
        pool = rc.pool_for_symbol(self.address, "grpc.health.v1.Health")
        for service in ("", "behaviorlib.v1.Wait", "behaviorlib.v1.BehaviorSystem"):
            reply = rc.unary_call(self.channel, pool, "grpc.health.v1.Health", "Check",
                                  {"service": service})
            self.assertEqual(json_format.MessageToDict(reply).get("status"), "SERVING", service)

    # -- WatchEvents + typed Activate from JSON --------------------------------
    def test_4_activates_wait_from_json_and_watches_it_finish(self):
        pool = rc.pool_for_symbols(self.address,
                                   ["behaviorlib.v1.BehaviorSystem", "behaviorlib.v1.Wait"])
        watch_request = rc.message_class(pool, "behaviorlib.v1.WatchEventsRequest")
        watch_response = rc.message_class(pool, "behaviorlib.v1.WatchEventsResponse")
        activate_request = rc.message_class(pool, "behaviorlib.v1.WaitActivateRequest")
        activate_response = rc.message_class(pool, "behaviorlib.v1.ActivateResponse")

        watch = self.channel.unary_stream(
            "/behaviorlib.v1.BehaviorSystem/WatchEvents",
            request_serializer=watch_request.SerializeToString,
            response_deserializer=watch_response.FromString)
        stream = watch(watch_request(), timeout=20)
        try:
            first = next(stream)
            self.assertEqual(first.WhichOneof("kind"), "start")
            incarnation = first.start.incarnation
            self.assertTrue(incarnation)

            request = json_format.ParseDict({"parameters": {"duration_s": 0.1}},
                                            activate_request(), descriptor_pool=pool)
            activate = self.channel.unary_unary(
                "/behaviorlib.v1.Wait/Activate",
                request_serializer=activate_request.SerializeToString,
                response_deserializer=activate_response.FromString)
            reply = activate(request, timeout=TIMEOUT_S)
            activation_id = reply.activation_id
            self.assertTrue(activation_id.startswith("WAIT-"), activation_id)
            self.assertEqual(json_format.MessageToDict(reply)["parameters"], {"duration_s": 0.1})

            kinds = []
            finished = None
            for message in stream:
                self.assertEqual(message.WhichOneof("kind"), "event")
                event = json_format.MessageToDict(message.event, descriptor_pool=pool)
                if event.get("activationId") != activation_id:
                    continue
                self.assertEqual(event["incarnation"], incarnation)
                self.assertEqual(event["robotId"], "refl-drone")
                self.assertEqual(event["behavior"], "WAIT")
                kinds.append(message.event.WhichOneof("kind"))
                if "finished" in event:
                    finished = event["finished"]
                    break
            self.assertEqual(kinds, ["activated", "finished"])
            self.assertEqual(finished["cause"], "TERMINATION_CAUSE_GOAL_ACHIEVED")
            self.assertGreaterEqual(float(finished["activeDuration"].rstrip("s")), 0.1)
        finally:
            stream.cancel()

    # -- last: orderly shutdown -----------------------------------------------
    def test_9_sigterm_exits_zero(self):
        self.process.send_signal(signal.SIGTERM)
        self.assertEqual(self.process.wait(timeout=15), 0)


def main():
    global BINARY
    parser = argparse.ArgumentParser()
    parser.add_argument("--binary", default=BINARY,
                        help="path of the basic_quadrotor_behaviors executable")
    args, rest = parser.parse_known_args()
    BINARY = args.binary
    unittest.main(argv=[sys.argv[0]] + rest, verbosity=2)


if __name__ == "__main__":
    main()
