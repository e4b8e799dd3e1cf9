"""A Python behavior system under mutual TLS, an access policy and an audit log (decisions 23
and 24), against real processes on loopback and beside the C++ system that hosts WAIT
(build/bin/basic_quadrotor_behaviors) under the same certificates and policy, so that what the
Python system accepts, refuses and logs is held to what the C++ one does.

    BEHAVIORLIB_BUILD_DIR=build venv/bin/python -m pytest -q \
        clients/python/tests/test_system_security.py

The certificates are made with scripts/make-dev-certs.sh in a temporary directory (as
tests/integration/tls_test.py and roles_test.py make theirs): a CA and one certificate per
identity of the policy, and another CA for a stranger. The system under test is this file run
as a program (WAIT in Python, as in test_system_service.py). Every process a test starts is
killed when the module ends, passed or failed; every wait is a bounded poll.
"""

import sys

from behaviorlib.system import run_system

from python_wait import Wait  # this directory, as the program runs

SYSTEM = "python_secure_behaviors"


if __name__ == "__main__":
    sys.exit(run_system([Wait()], system=SYSTEM))


import hashlib  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import re  # noqa: E402
import subprocess  # noqa: E402
import tempfile  # noqa: E402
import urllib.request  # noqa: E402

import grpc  # noqa: E402
import pytest  # noqa: E402
from google.protobuf import struct_pb2  # noqa: E402
from google.rpc import error_details_pb2, status_pb2  # noqa: E402

from behaviorlib.system.channel import DataChannel  # noqa: E402
from behaviorlib.v1 import (behavior_pb2, coordinator_pb2, coordinator_pb2_grpc,  # noqa: E402
                            types_pb2)

from test_system_service import BIN, CALL_S, REPO, WAIT_S, Stack, wait_for  # noqa: E402

CPP_SYSTEM = "basic_quadrotor_behaviors"
MAKE_CERTS = os.path.join(REPO, "scripts", "make-dev-certs.sh")
TOKEN = "dashboard-token-0123456789"
# The identities of the policy; "stranger" has a certificate from the CA that the policy does
# not know.
IDENTITIES = ["viewer", "operator", "safety", "admin", "coordinator", "simulator",
              "channel_broker", "drone1-python", "drone2-cpp", "drone1-tablet", "stranger"]
ROLES = {
    "viewer": {"viewer"},
    "operator": {"viewer", "operator"},
    "safety": {"viewer", "safety"},
    "admin": {"viewer", "admin"},
    "stranger": set(),
}
POLICY = f"""# Who may call what (access_policy.h).
identities:
  - certificate: behaviorlib:viewer
    roles: [viewer]
  - certificate: behaviorlib:operator
    roles: [viewer, operator]
  - certificate: behaviorlib:safety
    roles: [viewer, safety]
  - certificate: behaviorlib:admin
    roles: [viewer, admin]
  - certificate: behaviorlib:coordinator
    roles: [viewer, operator, safety]
  - certificate: behaviorlib:simulator
    roles: [viewer, operator]
  - certificate: behaviorlib:channel_broker
    roles: [viewer]
  - certificate: behaviorlib:drone1-python      # the Python system of drone1
    roles: [viewer, operator, system]
    system: {{robot: drone1, name: {SYSTEM}}}
  - certificate: behaviorlib:drone2-cpp         # the C++ system of drone2
    roles: [viewer, operator, system]
    system: {{robot: drone2, name: {CPP_SYSTEM}}}
  - certificate: "behaviorlib:drone1-tablet"    # an operator of drone1 only
    roles: [viewer, operator]
    robot: drone1
  - token_sha256: {hashlib.sha256(TOKEN.encode()).hexdigest()}
    name: dashboard
    roles: [viewer]
"""

pytestmark = pytest.mark.skipif(
    not all(os.path.exists(os.path.join(BIN, name))
            for name in ("coordinator", CPP_SYSTEM, "channel_broker", "simulator")),
    reason=f"needs the C++ binaries in {BIN} (build first, or set BEHAVIORLIB_BUILD_DIR)")


# ---- Certificates, processes and calls -----------------------------------------------------------

class Certs:
    """A CA with a certificate per identity, another CA, and the policy, in `directory`."""

    def __init__(self, directory):
        self.dir = os.path.join(directory, "certs")
        self.other = os.path.join(directory, "other-ca")
        subprocess.run([MAKE_CERTS, "--out", self.dir, *IDENTITIES], check=True,
                       capture_output=True, timeout=WAIT_S)
        subprocess.run([MAKE_CERTS, "--out", self.other, "operator"], check=True,
                       capture_output=True, timeout=WAIT_S)
        self.policy = os.path.join(directory, "policy.yaml")
        with open(self.policy, "w") as f:
            f.write(POLICY)
        self.ca = os.path.join(self.dir, "ca.pem")

    def flags(self, name, policy=True):
        """The TLS flags of a process with the certificate `name` (and the policy)."""
        return ["--tls-cert", os.path.join(self.dir, f"{name}.pem"),
                "--tls-key", os.path.join(self.dir, f"{name}.key"), "--tls-ca", self.ca,
                *(["--access-policy", self.policy] if policy else [])]

    def credentials(self, name=None, directory=None):
        """Client credentials trusting the CA, with the certificate `name` (from `directory`,
        default the CA's) or none."""
        directory = directory or self.dir
        if name is None:
            return grpc.ssl_channel_credentials(root_certificates=read(self.ca))
        return grpc.ssl_channel_credentials(
            root_certificates=read(self.ca),
            private_key=read(os.path.join(directory, f"{name}.key")),
            certificate_chain=read(os.path.join(directory, f"{name}.pem")))


def read(path):
    with open(path, "rb") as f:
        return f.read()


def error_info(error):
    """The ErrorInfo of a failed call's google.rpc.Status details, or None without one."""
    for key, value in error.trailing_metadata() or ():
        if key == "grpc-status-details-bin":
            for detail in status_pb2.Status.FromString(value).details:
                if detail.Is(error_details_pb2.ErrorInfo.DESCRIPTOR):
                    info = error_details_pb2.ErrorInfo()
                    detail.Unpack(info)
                    return info
    return None


def struct(values):
    out = struct_pb2.Struct()
    out.update(values)
    return out


def call(process, credentials, method, request=b"", token=None, streaming=False):
    """One call of `method` with raw bytes: (code, message, ErrorInfo or None); OK's message is
    "". `credentials` None: plaintext. A streaming call's outcome is its first response's."""
    channel = (grpc.secure_channel(process.address, credentials) if credentials is not None
               else grpc.insecure_channel(process.address))
    metadata = [("authorization", f"Bearer {token}")] if token else None
    with channel:
        try:
            if streaming:
                responses = channel.stream_stream(method)(iter([request]), timeout=CALL_S,
                                                          metadata=metadata)
                next(responses)
                responses.cancel()
            else:
                channel.unary_unary(method)(request, timeout=CALL_S, metadata=metadata)
            return grpc.StatusCode.OK, "", None
        except grpc.RpcError as error:
            return error.code(), error.details(), error_info(error)


def metrics_text(process):
    url = f"http://127.0.0.1:{process.ports['metrics_port']}/metrics"
    with urllib.request.urlopen(url, timeout=CALL_S) as response:
        return response.read().decode()


def audit_records(path):
    with open(path) as f:
        return [json.loads(line) for line in f]


# ---- The stack -----------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def directory():
    with tempfile.TemporaryDirectory(prefix="behaviorlib-python-security-") as path:
        yield path


@pytest.fixture(scope="module")
def stack(directory):
    processes = Stack(directory)
    try:
        yield processes
    finally:
        processes.kill_all()


@pytest.fixture(scope="module")
def certs(directory):
    return Certs(directory)


@pytest.fixture(scope="module")
def coordinator(stack, certs):
    return stack.start("coordinator", [os.path.join(BIN, "coordinator"), "--listen",
                                       "127.0.0.1:0", "--metrics-listen", "",
                                       *certs.flags("coordinator")])


def coordinator_stub(coordinator, certs, name="operator"):
    return coordinator_pb2_grpc.CoordinatorStub(
        grpc.secure_channel(coordinator.address, certs.credentials(name)))


def wait_up(coordinator, certs, robot, system):
    stub = coordinator_stub(coordinator, certs)

    def up():
        listed = stub.ListSystems(coordinator_pb2.ListSystemsRequest(robot_id=robot),
                                  timeout=CALL_S)
        return any(s.system == system and s.state == coordinator_pb2.SYSTEM_STATE_UP
                   for s in listed.systems)
    wait_for(up, f"{system} of {robot} UP at the TLS coordinator")


def python_system(stack, name, robot, certificate, *flags):
    return stack.start(name, [sys.executable, os.path.abspath(__file__), "--robot-id", robot,
                              "--listen", "127.0.0.1:0", "--metrics-listen", "127.0.0.1:0",
                              *certificate, *flags])


@pytest.fixture(scope="module")
def ours(stack, certs, directory, coordinator):
    """The Python system of drone1, under TLS and the policy, registered with the coordinator."""
    process = python_system(stack, SYSTEM, "drone1", certs.flags("drone1-python"),
                            "--coordinator", coordinator.address,
                            "--audit-log", os.path.join(directory, "python-audit.jsonl"))
    process.audit = os.path.join(directory, "python-audit.jsonl")
    wait_up(coordinator, certs, "drone1", SYSTEM)
    return process


@pytest.fixture(scope="module")
def theirs(stack, certs, directory, coordinator):
    """The C++ system of drone2 under the same policy."""
    audit = os.path.join(directory, "cpp-audit.jsonl")
    process = stack.start(CPP_SYSTEM, [
        os.path.join(BIN, CPP_SYSTEM), "--robot-id", "drone2", "--listen", "127.0.0.1:0",
        "--metrics-listen", "127.0.0.1:0", "--coordinator", coordinator.address,
        "--audit-log", audit, *certs.flags("drone2-cpp")])
    process.audit = audit
    wait_up(coordinator, certs, "drone2", CPP_SYSTEM)
    return process


# ---- Mutual TLS ----------------------------------------------------------------------------------

def test_registers_with_the_tls_coordinator_and_is_driven_through_it(coordinator, certs, ours):
    stub = coordinator_stub(coordinator, certs)
    activation = stub.ActivateBehavior(coordinator_pb2.ActivateFleetBehaviorRequest(
        robot_id="drone1", behavior="WAIT", parameters=struct({"duration_s": 0.2})),
        timeout=CALL_S).activation
    stream = stub.WatchEvents(coordinator_pb2.WatchFleetEventsRequest(robot_ids=["drone1"]),
                              timeout=WAIT_S)
    try:
        for message in stream:
            for fleet_event in ([message.event] if message.HasField("event")
                                else list(message.events.events)):
                event = fleet_event.behavior_event
                if event.activation_id == activation.activation_id and event.HasField("finished"):
                    break
            else:
                continue
            break
    finally:
        stream.cancel()
    assert event.finished.cause == behavior_pb2.TERMINATION_CAUSE_GOAL_ACHIEVED
    assert (event.system, event.finished.message) == (SYSTEM, "waited")
    assert "registered with the coordinator" in ours.log()


@pytest.mark.parametrize("client", ["plaintext", "no certificate", "another CA"])
def test_a_client_without_a_certificate_from_the_ca_is_refused(certs, ours, theirs, client):
    credentials = {
        "plaintext": None,
        "no certificate": certs.credentials(),
        "another CA": certs.credentials("operator", directory=certs.other),
    }[client]
    method = "/behaviorlib.v1.BehaviorSystem/ListBehaviors"
    assert call(ours, credentials, method)[0] == grpc.StatusCode.UNAVAILABLE
    assert call(theirs, credentials, method)[0] == grpc.StatusCode.UNAVAILABLE
    # The same call with a certificate from the CA is served.
    assert call(ours, certs.credentials("viewer"), method)[0] == grpc.StatusCode.OK


def test_metrics_stay_plain_http_under_tls(ours, theirs):
    for process in (ours, theirs):
        assert "# TYPE process_start_time_seconds gauge" in metrics_text(process)


# ---- Roles ---------------------------------------------------------------------------------------

def deactivate_request():
    return behavior_pb2.DeactivateBehaviorRequest(
        behavior="WAIT", activation_id="no-such-activation").SerializeToString()


# (method, the role it needs, request, streaming)
METHODS = [
    ("/behaviorlib.v1.BehaviorSystem/ListBehaviors", "viewer",
     behavior_pb2.ListBehaviorsRequest().SerializeToString(), False),
    ("/behaviorlib.v1.BehaviorSystem/CheckBehaviorActivation", "viewer",
     behavior_pb2.CheckBehaviorActivationRequest(behavior="WAIT").SerializeToString(), False),
    ("/behaviorlib.v1.BehaviorSystem/DeactivateBehavior", "operator", deactivate_request(), False),
    ("/behaviorlib.v1.Wait/Deactivate", "operator",
     behavior_pb2.DeactivateRequest(activation_id="no-such-activation").SerializeToString(),
     False),
    ("/grpc.health.v1.Health/Check", "viewer", b"", False),
    # list_services (field 7) on the reflection stream.
    ("/grpc.reflection.v1.ServerReflection/ServerReflectionInfo", "viewer", b"\x3a\x01*", True),
    # Methods a behavior system does not serve: the role first, then UNIMPLEMENTED.
    ("/behaviorlib.v1.Coordinator/Kill", "safety", b"", False),
    ("/behaviorlib.v1.Simulator/Reset", "admin", b"", False),
]


def test_each_role_is_given_and_refused_as_by_the_cpp_system(certs, ours, theirs):
    callers = [(name, name, None) for name in ROLES]
    # A bearer token names its identity; a wrong one is not made good by the certificate.
    callers += [("token", "stranger", TOKEN), ("wrong token", "operator", "wrong")]
    roles = dict(ROLES, token={"viewer"})
    table = []
    for caller, certificate, token in callers:
        for method, needed, request, streaming in METHODS:
            credentials = certs.credentials(certificate)
            python = call(ours, credentials, method, request, token, streaming)
            cpp = call(theirs, credentials, method, request, token, streaming)
            table.append((caller, method, needed, python, cpp))
    rows = "\n".join(f"{caller:12} {method:60} {python[0].name:18} {cpp[0].name:18} {python[1]}"
                     for caller, method, _, python, cpp in table)
    for caller, method, needed, python, cpp in table:
        where = f"{caller} calling {method}:\n{rows}"
        assert python[0] == cpp[0], where
        if needed in roles.get(caller, set()):
            assert python[0] != grpc.StatusCode.PERMISSION_DENIED, where
            continue
        # Refused by the policy: the C++ message, and the ErrorInfo that the C++ authorizer
        # builds (gRPC's auth filter does not hand it on to the C++ system's clients).
        assert python[0] == grpc.StatusCode.PERMISSION_DENIED, where
        assert python[1] == cpp[1], where
        who = {"token": "dashboard", "wrong token": "behaviorlib:operator"}.get(
            caller, f"behaviorlib:{caller}")
        has = ("is not in the access policy" if caller in ("stranger", "wrong token")
               else "has " + ", ".join(r for r in ("viewer", "operator", "safety", "admin")
                                       if r in roles[caller]))
        assert python[1] == f"{method} needs the role {needed}; '{who}' {has}", where
        assert (python[2].reason, python[2].domain, dict(python[2].metadata)) == \
            ("ROLE_REQUIRED", "behaviorlib.v1", {"role": needed, "identity": who}), where
        assert cpp[2] is None or cpp[2] == python[2], where
    served = [row for row in table if row[0] == "operator" and "Deactivate" in row[1]]
    assert served and all(row[3][0] == grpc.StatusCode.ABORTED for row in served)
    unserved = [row for row in table if row[0] in ("safety", "admin") and row[2] == row[0]]
    assert len(unserved) == 2
    assert all(row[3][:2] == row[4][:2] == (grpc.StatusCode.UNIMPLEMENTED, "")
               for row in unserved)


def test_a_caller_bound_to_one_robot_commands_no_behavior_of_another(certs, ours, theirs):
    method = "/behaviorlib.v1.BehaviorSystem/DeactivateBehavior"
    cases = [  # (system, its robot, a certificate bound to another robot, that robot)
        (ours, "drone1", "drone2-cpp", "drone2"),
        (theirs, "drone2", "drone1-python", "drone1"),
        (theirs, "drone2", "drone1-tablet", "drone1"),
    ]
    for process, robot, certificate, allowed in cases:
        code, message, info = call(process, certs.credentials(certificate), method,
                                   deactivate_request())
        assert code == grpc.StatusCode.PERMISSION_DENIED, message
        assert message == (f"'behaviorlib:{certificate}' may deactivate behaviors only for "
                           f"robot {allowed}, not for robot '{robot}'")
        assert (info.reason, dict(info.metadata)) == ("ROBOT_NOT_PERMITTED", {
            "identity": f"behaviorlib:{certificate}", "robot": robot, "allowed_robot": allowed})
    # Bound to its own robot, the same call passes the scope (and fails further on).
    for process, certificate in ((ours, "drone1-python"), (ours, "drone1-tablet"),
                                 (theirs, "drone2-cpp")):
        code, message, _ = call(process, certs.credentials(certificate), method,
                                deactivate_request())
        assert code == grpc.StatusCode.ABORTED, message  # no such activation
    # Reads stay open to a bound viewer.
    code, _, _ = call(ours, certs.credentials("drone2-cpp"),
                      "/behaviorlib.v1.BehaviorSystem/ListBehaviors")
    assert code == grpc.StatusCode.OK


# ---- The audit log -------------------------------------------------------------------------------

def without_time(record):
    return {key: value for key, value in record.items() if key != "time"}


def test_control_calls_and_refusals_are_audited_as_by_the_cpp_system(certs, ours, theirs):
    method = "/behaviorlib.v1.BehaviorSystem/DeactivateBehavior"
    odd = "/behaviorlib.v1.BehaviorSystem/Deactivate<\"odd\">"  # escaped as the C++ escapes it
    for process in (ours, theirs):
        call(process, certs.credentials("operator"), method, deactivate_request())
        call(process, certs.credentials("viewer"), method, deactivate_request())
        call(process, certs.credentials("viewer"), odd)
        call(process, certs.credentials("viewer"), "/behaviorlib.v1.BehaviorSystem/ListBehaviors")
        call(process, certs.credentials("stranger"),
             "/behaviorlib.v1.BehaviorSystem/ListBehaviors")
    records = {}
    for process in (ours, theirs):
        wait_for(lambda: len(audit_records(process.audit)) >= 3, "the audit records")
        with open(process.audit) as f:
            lines = f.read().splitlines()
        for line in lines:
            assert re.fullmatch(r'\{"time":"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}Z","identity":'
                                r'".*","method":".*","outcome":"[A-Z_]+","message":".*"\}', line)
        assert '"method":"/behaviorlib.v1.BehaviorSystem/Deactivate\\u003c\\"odd\\"\\u003e"' \
            in "\n".join(lines)
        records[process.name] = [without_time(json.loads(line)) for line in lines]
    python, cpp = records[SYSTEM], records[CPP_SYSTEM]
    control = next(r for r in python if r["identity"] == "behaviorlib:operator"
                   and r["method"] == method)
    assert control["outcome"] == "ABORTED"
    assert control["message"].startswith("cannot deactivate activation no-such-activation")
    refused = {"identity": "behaviorlib:viewer", "method": method,
               "outcome": "PERMISSION_DENIED",
               "message": f"{method} needs the role operator; 'behaviorlib:viewer' has viewer"}
    assert refused in python and refused in cpp
    assert [r for r in python if r["method"] == odd] == [r for r in cpp if r["method"] == odd]
    assert len([r for r in python if r["method"] == odd]) == 1
    # Reads are not audited (refusals are).
    reads = [r for r in python + cpp if r["method"].endswith("/ListBehaviors")]
    assert reads and all(r["outcome"] == "PERMISSION_DENIED" for r in reads)
    series = ('behaviorlib_audited_calls_total{identity="behaviorlib:viewer",'
              f'method="{method}",outcome="PERMISSION_DENIED"}} ')
    assert series in metrics_text(ours) and series in metrics_text(theirs)


def test_the_audit_log_rotates_as_the_cpp_one(stack, directory):
    """Plaintext, no policy: every control call is audited as "anonymous"; at 600 bytes the
    file rotates, and two rotated files are kept: of 18 records, 13 are kept."""
    logs = {}
    for name, program in ((f"{SYSTEM}-rotating", [sys.executable, os.path.abspath(__file__)]),
                          (f"{CPP_SYSTEM}-rotating", [os.path.join(BIN, CPP_SYSTEM)])):
        path = os.path.join(directory, f"{name}.jsonl")
        process = stack.start(name, [*program, "--robot-id", "drone7", "--listen",
                                     "127.0.0.1:0", "--metrics-listen", "", "--audit-log", path,
                                     "--audit-log-max-bytes", "600", "--audit-log-keep", "2"])
        for _ in range(18):
            assert call(process, None, "/behaviorlib.v1.BehaviorSystem/Nothing")[:2] == \
                (grpc.StatusCode.UNIMPLEMENTED, "")
        logs[name] = [[without_time(record) for record in audit_records(file)]
                      if os.path.exists(file) else None
                      for file in (path, f"{path}.1", f"{path}.2", f"{path}.3")]
    python, cpp = logs.values()
    assert python == cpp
    assert python[3] is None and python[2]  # FILE.2 kept, nothing beyond
    assert sum(len(records) for records in python[:3]) < 18  # the oldest were removed
    assert python[0][-1] == {"identity": "anonymous",
                             "method": "/behaviorlib.v1.BehaviorSystem/Nothing",
                             "outcome": "UNIMPLEMENTED", "message": ""}


# ---- Outgoing channels: the channel broker and the simulator -------------------------------------

def test_the_simulated_clock_comes_from_a_tls_broker(stack, certs):
    broker = stack.start("channel_broker", [os.path.join(BIN, "channel_broker"), "--listen",
                                            "127.0.0.1:0", "--metrics-listen", "",
                                            *certs.flags("channel_broker")])
    process = python_system(stack, f"{SYSTEM}-sim-clock", "drone1",
                            certs.flags("drone1-python"), "--channel", broker.address,
                            "--clock", "sim")
    request = behavior_pb2.ActivateBehaviorRequest(
        behavior="WAIT", parameters=struct({"duration_s": 1})).SerializeToString()
    method = "/behaviorlib.v1.BehaviorSystem/ActivateBehavior"
    code, _, info = call(process, certs.credentials("operator"), method, request)
    assert (code, info.reason) == (grpc.StatusCode.FAILED_PRECONDITION, "CLOCK_NOT_READY")
    channel = DataChannel(broker.address, channel_credentials=certs.credentials("operator"))
    try:
        sample = types_pb2.Clock(time_scale=1000.0)
        sample.time.FromSeconds(100)
        sample.wall_time.GetCurrentTime()
        channel.publish("clock", sample)
        channel.sync()
        wait_for(lambda: call(process, certs.credentials("operator"), method, request)[0]
                 == grpc.StatusCode.OK, "the simulated clock from the TLS broker")
    finally:
        channel.close()


def test_follows_the_time_grants_of_a_tls_simulator(stack, certs):
    broker = stack.start("channel_broker-2", [os.path.join(BIN, "channel_broker"), "--listen",
                                              "127.0.0.1:0", "--metrics-listen", "",
                                              *certs.flags("channel_broker")])
    simulator = stack.start("simulator", [
        os.path.join(BIN, "simulator"), "--listen", "127.0.0.1:0", "--metrics-listen", "",
        "--channel", broker.address, "--vehicles", "drone1", "--time-scale", "max",
        "--min-followers", "1", *certs.flags("simulator")])
    process = python_system(stack, f"{SYSTEM}-following", "drone1",
                            certs.flags("drone1-python"), "--channel", broker.address,
                            "--clock", "sim", "--follow-time", simulator.address)
    wait_for(lambda: f"{SYSTEM}/drone1 follows the time grants" in simulator.log(),
             "the system following the TLS simulator's grants")
    request = behavior_pb2.ActivateBehaviorRequest(
        behavior="WAIT", parameters=struct({"duration_s": 0.5})).SerializeToString()
    code, message, _ = call(process, certs.credentials("operator"),
                            "/behaviorlib.v1.BehaviorSystem/ActivateBehavior", request)
    assert code == grpc.StatusCode.OK, message
    channel = grpc.secure_channel(process.address, certs.credentials("viewer"))
    stream = channel.unary_stream(
        "/behaviorlib.v1.BehaviorSystem/WatchEvents",
        request_serializer=behavior_pb2.WatchEventsRequest.SerializeToString,
        response_deserializer=behavior_pb2.WatchEventsResponse.FromString)(
            behavior_pb2.WatchEventsRequest(), timeout=WAIT_S)
    try:
        finished = next(message.event for message in stream
                        if message.HasField("event") and message.event.HasField("finished"))
    finally:
        stream.cancel()
        channel.close()
    assert finished.finished.cause == behavior_pb2.TERMINATION_CAUSE_GOAL_ACHIEVED


# ---- Refused command lines -----------------------------------------------------------------------

BAD_POLICIES = {
    "unknown-role.yaml": "identities:\n  - certificate: a\n    roles: [viewer, pilot]\n",
    "system-role.yaml": "identities:\n  - certificate: a\n    roles: [viewer, system]\n",
    "two-names.yaml": ("identities:\n  - certificate: a\n    token_sha256: " + "a" * 64
                       + "\n    roles: [viewer]\n"),
    "short-token.yaml": "identities:\n  - token_sha256: abc\n    roles: [viewer]\n",
    "unknown-key.yaml": "identities:\n  - certificate: a\n    roles: [viewer]\n    role: x\n",
    "not-a-list.yaml": "identities: {certificate: a}\n",
    "other-robot.yaml": ("identities:\n  - certificate: a\n    roles: [system]\n"
                         "    system: {robot: d1, name: s}\n    robot: d2\n"),
    "no-roles.yaml": "# nothing but\nidentities:\n  - certificate: a\n",
}


def bad_command_lines(certs, directory):
    """(name, flags) of command lines that both systems refuse at start."""
    not_pem = os.path.join(directory, "not.pem")
    with open(not_pem, "w") as f:
        f.write("not a certificate\n")
    too_large = os.path.join(directory, "large.pem")
    with open(too_large, "w") as f:
        f.write("-----BEGIN CERTIFICATE-----\n" + "A" * (1 << 20))
    cert, key = certs.flags("drone1-python", policy=False)[1:4:2]
    lines = [
        ("only a certificate", ["--tls-cert", cert]),
        ("no CA", ["--tls-cert", cert, "--tls-key", key]),
        ("a missing CA file", ["--tls-cert", cert, "--tls-key", key, "--tls-ca",
                               os.path.join(directory, "missing.pem")]),
        ("a key that is not PEM", ["--tls-cert", cert, "--tls-key", not_pem, "--tls-ca",
                                   certs.ca]),
        ("a directory", ["--tls-cert", directory, "--tls-key", key, "--tls-ca", certs.ca]),
        ("a file too large", ["--tls-cert", too_large, "--tls-key", key, "--tls-ca", certs.ca]),
        ("a policy without TLS", ["--access-policy", certs.policy]),
        ("a missing policy", [*certs.flags("drone1-python", policy=False), "--access-policy",
                              os.path.join(directory, "missing.yaml")]),
        ("plaintext off loopback", ["--listen", "0.0.0.0:0"]),
        ("no rotation", ["--audit-log", os.path.join(directory, "a.jsonl"),
                         "--audit-log-max-bytes", "0"]),
        ("an audit log in no directory", ["--audit-log",
                                          os.path.join(directory, "missing", "a.jsonl")]),
    ]
    for name, text in BAD_POLICIES.items():
        path = os.path.join(directory, name)
        with open(path, "w") as f:
            f.write(text)
        lines.append((name, [*certs.flags("drone1-python", policy=False), "--access-policy",
                             path]))
    return lines


def test_bad_security_flags_are_refused_with_the_cpp_messages(certs, directory):
    for name, flags in bad_command_lines(certs, directory):
        argv = ["--robot-id", "drone1", "--listen", "127.0.0.1:0", "--metrics-listen", ""]
        if "--listen" in flags:
            argv = argv[:2] + argv[4:]
        python = subprocess.run([sys.executable, os.path.abspath(__file__), *argv, *flags],
                                capture_output=True, text=True, timeout=WAIT_S)
        cpp = subprocess.run([os.path.join(BIN, CPP_SYSTEM), *argv, *flags],
                             capture_output=True, text=True, timeout=WAIT_S)
        assert python.returncode == 2, (name, python.stderr)
        assert cpp.returncode != 0, (name, cpp.stderr)
        said = python.stderr.strip().splitlines()
        assert len(said) == 1 and said[0].startswith(f"{SYSTEM}: "), (name, python.stderr)
        expected = cpp.stderr.strip().splitlines()[-1]
        assert expected.startswith(f"{CPP_SYSTEM}: "), (name, cpp.stderr)
        assert said[0][len(SYSTEM) + 2:] == expected[len(CPP_SYSTEM) + 2:], name
