"""Roles (issue: security and hardening, goal 2): an access policy maps
certificate names and bearer tokens to roles, and every server enforces it.

    /usr/bin/python3 roles_test.py --build-dir build

Starts the real channel broker, simulator and coordinator on loopback with
mutual TLS and one policy. Then each identity (viewer, operator, safety,
system, admin, a certificate the policy does not know, a bearer token) calls
one method of each kind (viewer, operator, safety, system, admin): allowed
exactly when it has the role, otherwise PERMISSION_DENIED naming the role.
A system certificate cannot register as another system (the hijack), nor
command another robot (its vehicle, its behaviors, its missions, its topics:
ROBOT_NOT_PERMITTED); the
coordinator's audit log and metric record control calls and refusals.
Needs python3-grpcio and openssl.
"""

import argparse
import hashlib
import json
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
import reflection_client as rc  # noqa: E402

BUILD_DIR = os.path.join(REPO, "build")
TOKEN = "dashboard-token-0123456789"
ROLES = {
    "viewer": ["viewer"],
    "operator": ["viewer", "operator"],
    "safety": ["viewer", "safety"],
    "system": ["viewer", "operator", "system"],
    "admin": ["viewer", "admin"],
}
POLICY = f"""identities:
  - certificate: behaviorlib:viewer
    roles: [viewer]
  - certificate: behaviorlib:operator
    roles: [viewer, operator]
  - certificate: behaviorlib:safety
    roles: [viewer, safety]
  - certificate: behaviorlib:system
    roles: [viewer, operator, system]
    system: {{robot: drone1, name: basic_quadrotor_behaviors}}
  - certificate: behaviorlib:drone2-system
    roles: [viewer, operator, system]
    system: {{robot: drone2, name: basic_quadrotor_behaviors}}
  - certificate: behaviorlib:admin
    roles: [viewer, admin]
  - certificate: behaviorlib:coordinator
    roles: [viewer, operator, safety]
  - certificate: behaviorlib:simulator
    roles: [viewer, operator]
  - certificate: behaviorlib:channel_broker
    roles: [viewer]
  - token_sha256: {hashlib.sha256(TOKEN.encode()).hexdigest()}
    name: dashboard
    roles: [viewer]
"""


def has_reason(error, reason):
    """Whether a gRPC error's google.rpc.Status details name `reason` (the
    ErrorInfo's reason is a string field: its bytes appear as they are)."""
    for key, value in error.trailing_metadata() or ():
        if key == "grpc-status-details-bin" and reason.encode() in value:
            return True
    return False


def read(path):
    with open(path, "rb") as f:
        return f.read()


class Process:
    def __init__(self, program, argv, run_dir, name=None):
        self.name = name = name or program
        self.port_file = os.path.join(run_dir, f"{name}.ports")
        self.log_path = os.path.join(run_dir, f"{name}.log")
        with open(self.log_path, "w") as log:
            self.process = subprocess.Popen(
                [os.path.join(BUILD_DIR, "bin", program), "--port-file", self.port_file, *argv],
                stdout=log, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + 30
        while not os.path.exists(self.port_file):
            if self.process.poll() is not None or time.monotonic() > deadline:
                raise AssertionError(f"{name} did not start:\n{open(self.log_path).read()}")
            time.sleep(0.05)
        with open(self.port_file) as f:
            ports = dict(line.strip().split("=", 1) for line in f if "=" in line)
        self.address = f"127.0.0.1:{ports['grpc_port']}"
        self.metrics = f"127.0.0.1:{ports['metrics_port']}"

    def stop(self):
        if self.process.poll() is None:
            self.process.terminate()
            self.process.wait(timeout=20)


class RolesTest(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        cls.dir = tempfile.mkdtemp(prefix="roles-test-")
        cls.certs = os.path.join(cls.dir, "certs")
        names = [*ROLES, "stranger", "coordinator", "simulator", "channel_broker",
                 "drone2-system"]
        subprocess.run([os.path.join(REPO, "scripts", "make-dev-certs.sh"), "--out", cls.certs,
                        *names], check=True, capture_output=True)
        policy = os.path.join(cls.dir, "policy.yaml")
        with open(policy, "w") as f:
            f.write(POLICY)
        cls.state_dir = os.path.join(cls.dir, "state")

        def flags(name):
            return ["--listen", "127.0.0.1:0", "--metrics-listen", "127.0.0.1:0",
                    "--tls-cert", os.path.join(cls.certs, f"{name}.pem"),
                    "--tls-key", os.path.join(cls.certs, f"{name}.key"),
                    "--tls-ca", os.path.join(cls.certs, "ca.pem"), "--access-policy", policy]

        cls.processes = []
        try:
            broker = Process("channel_broker", flags("channel_broker"), cls.dir)
            cls.processes.append(broker)
            simulator = Process("simulator", [*flags("simulator"), "--channel", broker.address,
                                              "--vehicles", "drone1,drone2"], cls.dir)
            cls.processes.append(simulator)
            cls.coordinator = Process("coordinator", [*flags("coordinator"), "--state-dir",
                                                      cls.state_dir, "--flight-controller",
                                                      f"drone1={simulator.address}"], cls.dir)
            cls.processes.append(cls.coordinator)
            # drone2's behavior system, under its own certificate (bound to drone2).
            cls.drone2_system = Process("basic_quadrotor_behaviors",
                                        [*flags("drone2-system"), "--robot-id", "drone2",
                                         "--clock", "steady"], cls.dir)
            cls.processes.append(cls.drone2_system)
            # A deterministic simulator, whose time the systems follow.
            cls.stepped = Process("simulator", [*flags("simulator"), "--time-scale", "max",
                                                "--vehicles", "drone1,drone2"], cls.dir,
                                  name="stepped_simulator")
            cls.processes.append(cls.stepped)
        except Exception:
            cls.tearDownClass()
            raise
        cls.simulator = simulator
        cls.broker = broker
        rc.use_tls(os.path.join(cls.certs, "viewer.pem"), os.path.join(cls.certs, "viewer.key"),
                   os.path.join(cls.certs, "ca.pem"))
        cls.pools = {
            "coordinator": rc.pool_for_symbols(cls.coordinator.address,
                                               ["behaviorlib.v1.Coordinator"]),
            "simulator": rc.pool_for_symbols(
                simulator.address, ["behaviorlib.v1.Simulator", "behaviorlib.v1.FlightController"]),
            "broker": rc.pool_for_symbols(broker.address, ["behaviorlib.v1.DataChannel"]),
            "system": rc.pool_for_symbols(cls.drone2_system.address,
                                          ["behaviorlib.v1.BehaviorSystem"]),
        }

    @classmethod
    def tearDownClass(cls):
        for p in reversed(cls.processes):
            p.stop()
        shutil.rmtree(cls.dir, ignore_errors=True)

    def channel(self, name, server):
        creds = grpc.ssl_channel_credentials(
            root_certificates=read(os.path.join(self.certs, "ca.pem")),
            private_key=read(os.path.join(self.certs, f"{name}.key")),
            certificate_chain=read(os.path.join(self.certs, f"{name}.pem")))
        return grpc.secure_channel(server.address, creds)

    def call(self, identity, server, service, method, fields, token=None, reason=None):
        """The gRPC code of one call (OK or the error's) and its message. With
        `reason`, also whether the error's details carry that ErrorInfo reason."""
        pool = self.pools[{"behaviorlib.v1.Simulator": "simulator",
                           "behaviorlib.v1.FlightController": "simulator",
                           "behaviorlib.v1.BehaviorSystem": "system"}.get(service,
                                                                          "coordinator")]
        desc = pool.FindServiceByName(service).methods_by_name[method]
        request = rc.message_class(pool, desc.input_type.full_name)(**fields)
        response_class = rc.message_class(pool, desc.output_type.full_name)
        with self.channel(identity, server) as channel:
            stub = channel.unary_unary(f"/{service}/{method}",
                                       request_serializer=lambda m: m.SerializeToString(),
                                       response_deserializer=response_class.FromString)
            metadata = [("authorization", f"Bearer {token}")] if token else None
            try:
                stub(request, timeout=10, metadata=metadata)
                return grpc.StatusCode.OK, ""
            except grpc.RpcError as error:
                if reason is None:
                    return error.code(), error.details()
                return error.code(), error.details(), has_reason(error, reason)

    def kinds(self):
        """One method of each kind: (role it needs, server, service, method, request)."""
        coordinator = "behaviorlib.v1.Coordinator"
        return [
            ("viewer", self.coordinator, coordinator, "ListMissions", {}),
            ("operator", self.coordinator, coordinator, "WriteBelief",
             {"key": "drone1/note", "writer": "test"}),
            ("safety", self.coordinator, coordinator, "EmergencyLand",
             {"robot_id": "nobody", "reason": "test"}),
            ("system", self.coordinator, coordinator, "Heartbeat",
             {"robot_id": "drone1", "system": "basic_quadrotor_behaviors",
              "incarnation": "x"}),
            ("admin", self.simulator, "behaviorlib.v1.Simulator", "SetTimeScale",
             {"time_scale": 1.0}),
        ]

    def test_each_role_against_each_kind_of_rpc(self):
        for identity, roles in ROLES.items():
            for needed, server, service, method, fields in self.kinds():
                with self.subTest(identity=identity, method=method):
                    code, details = self.call(identity, server, service, method, fields)
                    if needed in roles:
                        self.assertNotEqual(code, grpc.StatusCode.PERMISSION_DENIED, details)
                    else:
                        self.assertEqual(code, grpc.StatusCode.PERMISSION_DENIED)
                        self.assertIn(f"needs the role {needed}", details)

    def test_a_certificate_the_policy_does_not_know_may_call_nothing(self):
        for needed, server, service, method, fields in self.kinds():
            with self.subTest(method=method):
                code, details = self.call("stranger", server, service, method, fields)
                self.assertEqual(code, grpc.StatusCode.PERMISSION_DENIED)
                self.assertIn("is not in the access policy", details)

    def test_a_bearer_token_names_its_identity(self):
        code, _ = self.call("stranger", self.coordinator, "behaviorlib.v1.Coordinator",
                            "ListMissions", {}, token=TOKEN)
        self.assertEqual(code, grpc.StatusCode.OK)
        code, details = self.call("operator", self.coordinator, "behaviorlib.v1.Coordinator",
                                  "WriteBelief", {"key": "drone1/x", "writer": "t"}, token=TOKEN)
        self.assertEqual(code, grpc.StatusCode.PERMISSION_DENIED)
        self.assertIn("'dashboard' has viewer", details)
        # A wrong token is not made good by the certificate.
        code, details = self.call("operator", self.coordinator, "behaviorlib.v1.Coordinator",
                                  "ListMissions", {}, token="wrong")
        self.assertEqual(code, grpc.StatusCode.PERMISSION_DENIED)

    def test_a_hijacking_register_system_is_refused(self):
        request = {"robot_id": "drone1", "system": "navigation_with_lidar",
                   "address": "127.0.0.1:1", "incarnation": "evil"}
        code, details = self.call("system", self.coordinator, "behaviorlib.v1.Coordinator",
                                  "RegisterSystem", request)
        self.assertEqual(code, grpc.StatusCode.PERMISSION_DENIED)
        self.assertIn("may register only as system basic_quadrotor_behaviors of robot drone1",
                      details)
        code, details = self.call("operator", self.coordinator, "behaviorlib.v1.Coordinator",
                                  "RegisterSystem", request)
        self.assertEqual(code, grpc.StatusCode.PERMISSION_DENIED)
        self.assertIn("needs the role system", details)
        # As itself it passes the check (and fails further on: no such server).
        request.update(system="basic_quadrotor_behaviors")
        code, details = self.call("system", self.coordinator, "behaviorlib.v1.Coordinator",
                                  "RegisterSystem", request)
        self.assertNotEqual(code, grpc.StatusCode.PERMISSION_DENIED, details)

    def publish(self, identity, topic):
        """Publishes one sample on the broker as `identity`: (code, message)."""
        pool = self.pools["broker"]
        request_class = rc.message_class(pool, "behaviorlib.v1.PublishRequest")
        response_class = rc.message_class(pool, "behaviorlib.v1.PublishResponse")
        any_class = rc.message_class(pool, "google.protobuf.Any")
        request = request_class(topic=topic, sample=any_class(
            type_url="type.googleapis.com/behaviorlib.v1.PublishResponse", value=b""))
        with self.channel(identity, self.broker) as channel:
            stub = channel.stream_unary("/behaviorlib.v1.DataChannel/Publish",
                                        request_serializer=lambda m: m.SerializeToString(),
                                        response_deserializer=response_class.FromString)
            try:
                response = stub(iter([request]), timeout=10)
                return grpc.StatusCode.OK, str(response.accepted_count)
            except grpc.RpcError as error:
                return error.code(), error.details(), has_reason(error, "ROBOT_NOT_PERMITTED")

    def test_a_system_commands_only_its_own_robot(self):
        # "system" is drone1's basic_quadrotor_behaviors: bound to drone1.
        coordinator, flight = "behaviorlib.v1.Coordinator", "behaviorlib.v1.FlightController"
        cases = [
            (self.coordinator, coordinator, "ActivateBehavior",
             lambda robot: {"robot_id": robot, "behavior": "TAKE_OFF"}, "activate behaviors"),
            (self.coordinator, coordinator, "StartMission",
             lambda robot: {"robot_id": robot, "text": "steps: []"}, "start missions"),
            (self.simulator, flight, "ExecuteFlightAction",
             lambda robot: {"robot_id": robot, "lease_id": "x"}, "command the vehicle"),
        ]
        for server, service, method, fields, what in cases:
            with self.subTest(method=method):
                code, details, reason = self.call("system", server, service, method,
                                                  fields("drone2"), reason="ROBOT_NOT_PERMITTED")
                self.assertEqual(code, grpc.StatusCode.PERMISSION_DENIED, details)
                self.assertIn(f"may {what} only for robot drone1, not for robot 'drone2'",
                              details)
                self.assertTrue(reason, "the details carry ROBOT_NOT_PERMITTED")
                # Its own robot passes the check (and may fail further on).
                code, details = self.call("system", server, service, method, fields("drone1"))
                self.assertNotEqual(code, grpc.StatusCode.PERMISSION_DENIED, details)
                # An operator bound to no robot commands any.
                code, details = self.call("operator", server, service, method, fields("drone2"))
                self.assertNotEqual(code, grpc.StatusCode.PERMISSION_DENIED, details)

    def test_a_system_commands_no_behavior_of_another_robot(self):
        request = {"behavior": "WAIT"}
        code, details, reason = self.call("system", self.drone2_system,
                                          "behaviorlib.v1.BehaviorSystem", "ActivateBehavior",
                                          request, reason="ROBOT_NOT_PERMITTED")
        self.assertEqual(code, grpc.StatusCode.PERMISSION_DENIED, details)
        self.assertIn("may activate behaviors only for robot drone1, not for robot 'drone2'",
                      details)
        self.assertTrue(reason)
        code, details = self.call("drone2-system", self.drone2_system,
                                  "behaviorlib.v1.BehaviorSystem", "ActivateBehavior", request)
        self.assertNotEqual(code, grpc.StatusCode.PERMISSION_DENIED, details)

    def follow_time(self, identity, robot):
        """Reports once on FollowTime as `identity` for `robot`: the first
        grant's code (OK) or the refusal's (code, message, has the reason)."""
        pool = self.pools["simulator"]
        request_class = rc.message_class(pool, "behaviorlib.v1.FollowTimeRequest")
        response_class = rc.message_class(pool, "behaviorlib.v1.FollowTimeResponse")
        with self.channel(identity, self.stepped) as channel:
            call = channel.stream_stream("/behaviorlib.v1.Simulator/FollowTime",
                                         request_serializer=lambda m: m.SerializeToString(),
                                         response_deserializer=response_class.FromString)
            replies = call(iter([request_class(participant="roles_test", robot_id=robot,
                                               wake=True)]), timeout=10)
            try:
                next(replies)
                return grpc.StatusCode.OK, "", False
            except grpc.RpcError as error:
                return error.code(), error.details(), has_reason(error, "ROBOT_NOT_PERMITTED")

    def test_a_system_follows_the_time_only_for_its_own_robot(self):
        code, details, reason = self.follow_time("system", "drone2")
        self.assertEqual(code, grpc.StatusCode.PERMISSION_DENIED, details)
        self.assertIn("may follow the time only for robot drone1, not for robot 'drone2'",
                      details)
        self.assertTrue(reason)
        code, details, _ = self.follow_time("system", "drone1")
        self.assertEqual(code, grpc.StatusCode.OK, details)

    def test_a_system_publishes_only_its_own_robots_topics(self):
        code, details, reason = self.publish("system", "robots/drone2/pose")
        self.assertEqual(code, grpc.StatusCode.PERMISSION_DENIED, details)
        self.assertIn("may publish only under robots/drone1/ or robots/swarm/", details)
        self.assertTrue(reason)
        self.assertEqual(self.publish("system", "robots/drone1/roles_test"),
                         (grpc.StatusCode.OK, "1"))
        # The swarm's shared topics, and any topic for an unbound publisher.
        self.assertEqual(self.publish("system", "robots/swarm/roles_test"),
                         (grpc.StatusCode.OK, "1"))
        self.assertEqual(self.publish("operator", "robots/drone2/roles_test"),
                         (grpc.StatusCode.OK, "1"))
        with urllib.request.urlopen(f"http://{self.broker.metrics}/metrics", timeout=10) as page:
            text = page.read().decode()
        self.assertIn('behaviorlib_channel_rejected_samples_total{reason="not_permitted"} 1',
                      text)

    def unary(self, identity, method, fields):
        """The response of one Coordinator call that must succeed."""
        pool = self.pools["coordinator"]
        desc = pool.FindServiceByName("behaviorlib.v1.Coordinator").methods_by_name[method]
        request = rc.message_class(pool, desc.input_type.full_name)(**fields)
        response_class = rc.message_class(pool, desc.output_type.full_name)
        with self.channel(identity, self.coordinator) as channel:
            stub = channel.unary_unary(f"/behaviorlib.v1.Coordinator/{method}",
                                       request_serializer=lambda m: m.SerializeToString(),
                                       response_deserializer=response_class.FromString)
            return stub(request, timeout=10)

    def test_a_belief_keeps_who_really_wrote_it(self):
        # The writer says it is the navigation system; its certificate says
        # it is the operator, and the belief records both.
        written = self.unary("operator", "WriteBelief",
                             {"key": "drone1/forged", "writer": "drone1/GENERATE_PATH"})
        self.assertEqual(written.belief.writer, "drone1/GENERATE_PATH")
        self.assertEqual(written.belief.authenticated_writer, "behaviorlib:operator")
        read = self.unary("viewer", "ReadBelief", {"key": "drone1/forged"})
        self.assertEqual(read.belief.authenticated_writer, "behaviorlib:operator")

    def test_control_calls_and_refusals_are_audited(self):
        self.call("operator", self.coordinator, "behaviorlib.v1.Coordinator", "WriteBelief",
                  {"key": "drone1/audited", "writer": "t"})
        self.call("viewer", self.coordinator, "behaviorlib.v1.Coordinator", "Kill",
                  {"robot_id": "drone1", "confirm": True})
        with open(os.path.join(self.state_dir, "audit.jsonl")) as f:
            records = [json.loads(line) for line in f]
        self.assertIn({"identity": "behaviorlib:operator",
                       "method": "/behaviorlib.v1.Coordinator/WriteBelief", "outcome": "OK"},
                      [{k: r[k] for k in ("identity", "method", "outcome")} for r in records])
        refused = [r for r in records if r["method"] == "/behaviorlib.v1.Coordinator/Kill"
                   and r["identity"] == "behaviorlib:viewer"]
        self.assertTrue(refused)
        self.assertEqual(refused[-1]["outcome"], "PERMISSION_DENIED")
        self.assertFalse(any(r["method"].endswith("/ListMissions") and r["outcome"] == "OK"
                             for r in records), "reads are not audited (refusals are)")
        with urllib.request.urlopen(f"http://{self.coordinator.metrics}/metrics",
                                    timeout=10) as page:
            text = page.read().decode()
        self.assertIn('behaviorlib_audited_calls_total{identity="behaviorlib:viewer",'
                      'method="/behaviorlib.v1.Coordinator/Kill",outcome="PERMISSION_DENIED"}',
                      text)


if __name__ == "__main__":
    parser = argparse.ArgumentParser()
    parser.add_argument("--build-dir", default=BUILD_DIR)
    args, rest = parser.parse_known_args()
    BUILD_DIR = os.path.abspath(args.build_dir)
    unittest.main(argv=[sys.argv[0], "-v", *rest])
