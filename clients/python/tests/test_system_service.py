"""A Python behavior system as a process (behaviorlib.system.run_system), against real
processes: the coordinator (build/bin/coordinator) and, for comparison, the C++ system that
hosts WAIT (build/bin/basic_quadrotor_behaviors), all on loopback with ports picked by the
kernel and read from their port files.

    BEHAVIORLIB_BUILD_DIR=build venv/bin/python -m pytest -q \
        clients/python/tests/test_system_service.py

The system under test is this file run as a program: it hosts WAIT, written in Python with the
C++ WAIT's parameters (WaitParameters) and options, so that everything it serves can be held to
what the C++ system serves: ListBehaviors' description, the errors' codes, messages and details,
the /metrics names. Every process a test starts is killed when the test module ends, passed or
failed; every wait is a bounded poll, never a timing assertion.
"""

import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import urllib.request

import grpc
import pytest
from google.protobuf import descriptor_pb2, struct_pb2
from google.rpc import error_details_pb2, status_pb2

from behaviorlib.system import run_system
from behaviorlib.system import health, reflection, typed
from behaviorlib.system._protocol import add_file, message_class
from behaviorlib.system.main import MAX_STREAMS
from behaviorlib.system.channel import DataChannel
from behaviorlib.v1 import (behavior_pb2, behavior_pb2_grpc, coordinator_pb2,
                            coordinator_pb2_grpc, types_pb2)
from behaviorlib.v1.behaviors import basic_quadrotor_behaviors_pb2
from behaviorlib.v1.behaviors.basic_quadrotor_behaviors_pb2 import WaitParameters

from python_wait import Wait  # this directory, as the program runs

SYSTEM = "python_test_behaviors"


if __name__ == "__main__":
    sys.exit(run_system([Wait()], system=SYSTEM))


REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", "..", ".."))
BUILD_DIR = os.path.abspath(os.environ.get("BEHAVIORLIB_BUILD_DIR", os.path.join(REPO, "build")))
BIN = os.path.join(BUILD_DIR, "bin")
GRPCURL = os.path.join(REPO, "tests", "e2e", "readme_grpcurl_test.py")
# The grpcurl runner needs only Debian's python3-grpcio and python3-protobuf.
DEBIAN_PYTHON = "/usr/bin/python3" if os.path.exists("/usr/bin/python3") else sys.executable
GRPC_PROTO_DIR = "/usr/share/grpc-proto"
PROTOC = shutil.which("protoc") or "/usr/bin/protoc"
WAIT_S = 60.0  # bound of every wait for another process
CALL_S = 30.0  # deadline of every call

# The launcher's reflection client (python3-grpcio and python3-protobuf only).
sys.path.insert(0, os.path.join(REPO, "deploy", "local"))
import reflection_client  # noqa: E402

Cause = behavior_pb2.TerminationCause

pytestmark = pytest.mark.skipif(
    not all(os.path.exists(os.path.join(BIN, name))
            for name in ("coordinator", "basic_quadrotor_behaviors")),
    reason=f"needs the C++ binaries in {BIN} (build first, or set BEHAVIORLIB_BUILD_DIR)")


def wait_for(predicate, what, timeout=WAIT_S):
    """Polls `predicate` until it returns something true; fails naming `what` after
    `timeout` seconds."""
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout:.0f} s waiting for {what}")
        time.sleep(0.05)


class Process:
    """A server process started with --port-file; its output goes to a log file."""

    def __init__(self, name, argv, directory):
        self.name = name
        self.port_file = os.path.join(directory, f"{name}.ports")
        self.log_path = os.path.join(directory, f"{name}.log")
        self.argv = list(argv) + ["--port-file", self.port_file]
        with open(self.log_path, "wb") as log:
            self.popen = subprocess.Popen(self.argv, stdin=subprocess.DEVNULL, stdout=log,
                                          stderr=subprocess.STDOUT)
        self.ports = wait_for(self._read_ports, f"{name}'s port file")

    def _read_ports(self):
        if self.popen.poll() is not None:
            pytest.fail(f"{self.name} exited with {self.popen.returncode}:\n{self.log()}")
        if not os.path.exists(self.port_file):
            return None
        with open(self.port_file) as f:
            return {key: int(value) for key, _, value in
                    (line.strip().partition("=") for line in f) if value}

    @property
    def address(self):
        return f"127.0.0.1:{self.ports['grpc_port']}"

    def log(self):
        with open(self.log_path, errors="replace") as f:
            return f.read()

    def stop(self, sig=signal.SIGKILL, timeout=WAIT_S):
        """Sends `sig` (unless it has exited) and waits for the exit; returns the exit code."""
        if self.popen.poll() is None:
            self.popen.send_signal(sig)
        try:
            return self.popen.wait(timeout)
        except subprocess.TimeoutExpired:
            self.popen.kill()
            self.popen.wait()
            pytest.fail(f"{self.name} did not exit within {timeout:.0f} s of signal {sig}")


class Stack:
    """Starts processes and kills every one at the end."""

    def __init__(self, directory):
        self.directory = directory
        self.processes = []

    def start(self, name, argv):
        process = Process(name, argv, self.directory)
        self.processes.append(process)
        return process

    def coordinator(self, name="coordinator", listen="127.0.0.1:0"):
        return self.start(name, [os.path.join(BIN, "coordinator"), "--listen", listen,
                                 "--metrics-listen", ""])

    def python_system(self, robot, coordinator, *flags, name=None):
        return self.start(name or f"{SYSTEM}-{robot}",
                          [sys.executable, os.path.abspath(__file__), "--robot-id", robot,
                           "--listen", "127.0.0.1:0", "--metrics-listen", "127.0.0.1:0",
                           *(["--coordinator", coordinator.address] if coordinator else []),
                           *flags])

    def kill_all(self):
        for process in self.processes:
            if process.popen.poll() is None:
                process.popen.send_signal(signal.SIGCONT)  # a frozen one too
                process.popen.kill()
                process.popen.wait()


@pytest.fixture(scope="module")
def stack():
    with tempfile.TemporaryDirectory(prefix="behaviorlib-python-system-") as directory:
        processes = Stack(directory)
        try:
            yield processes
        finally:
            processes.kill_all()


def coordinator_stub(process):
    return coordinator_pb2_grpc.CoordinatorStub(grpc.insecure_channel(process.address))


def system_stub(process):
    return behavior_pb2_grpc.BehaviorSystemStub(grpc.insecure_channel(process.address))


def system_state(coordinator, robot, system):
    """The coordinator's state of `system` of `robot` (SYSTEM_STATE_UNSPECIFIED: unknown)."""
    listed = coordinator_stub(coordinator).ListSystems(
        coordinator_pb2.ListSystemsRequest(robot_id=robot), timeout=CALL_S)
    return next((s.state for s in listed.systems if s.system == system),
                coordinator_pb2.SYSTEM_STATE_UNSPECIFIED)


def wait_up(coordinator, robot, system):
    wait_for(lambda: system_state(coordinator, robot, system) == coordinator_pb2.SYSTEM_STATE_UP,
             f"{system} of {robot} UP at the coordinator")


@pytest.fixture(scope="module")
def coordinator(stack):
    return stack.coordinator()


@pytest.fixture(scope="module")
def python_system(stack, coordinator):
    process = stack.python_system("drone1", coordinator)
    wait_up(coordinator, "drone1", SYSTEM)
    return process


@pytest.fixture(scope="module")
def cpp_system(stack, coordinator):
    """The C++ system hosting WAIT, for robot drone2 (a robot's systems host distinct
    behaviors)."""
    process = stack.start("basic_quadrotor_behaviors", [
        os.path.join(BIN, "basic_quadrotor_behaviors"), "--robot-id", "drone2",
        "--listen", "127.0.0.1:0", "--metrics-listen", "127.0.0.1:0",
        "--coordinator", coordinator.address])
    wait_up(coordinator, "drone2", "basic_quadrotor_behaviors")
    return process


def struct(values):
    out = struct_pb2.Struct()
    out.update(values)
    return out


def details(error):
    """(code, message, ErrorInfo, BadRequest or None) of a failed call."""
    info, bad = None, None
    for key, value in error.trailing_metadata() or ():
        if key == "grpc-status-details-bin":
            for detail in status_pb2.Status.FromString(value).details:
                if detail.Is(error_details_pb2.ErrorInfo.DESCRIPTOR):
                    info = error_details_pb2.ErrorInfo()
                    detail.Unpack(info)
                elif detail.Is(error_details_pb2.BadRequest.DESCRIPTOR):
                    bad = error_details_pb2.BadRequest()
                    detail.Unpack(bad)
    assert info is not None, f"no ErrorInfo in {error}"
    return error.code(), error.details(), info, bad


def refusal(call):
    with pytest.raises(grpc.RpcError) as raised:
        call()
    return details(raised.value)


def typed_stub(process, method, request_class, response_class):
    channel = grpc.insecure_channel(process.address)
    return channel.unary_unary(f"/behaviorlib.v1.Wait/{method}",
                               request_serializer=request_class.SerializeToString,
                               response_deserializer=response_class.FromString)


def typed_request(method):
    """The typed service's request class of `method` (the Python system's runtime-built
    WaitActivateRequest and WaitModifyRequest, the same messages as the C++ build's)."""
    file, _ = typed.add_services_file(basic_quadrotor_behaviors_pb2.DESCRIPTOR)
    return message_class(file.message_types_by_name[f"Wait{method}Request"])


def fleet_events(coordinator, robot, activation_id, until_cause):
    """The coordinator's FleetEvents of `activation_id`, replayed from the start of its log, up
    to its finished event; fails unless that event arrives within the wait."""
    stream = coordinator_stub(coordinator).WatchEvents(
        coordinator_pb2.WatchFleetEventsRequest(robot_ids=[robot]), timeout=WAIT_S)
    events = []
    try:
        for message in stream:
            for fleet_event in ([message.event] if message.HasField("event")
                                else list(message.events.events)):
                event = fleet_event.behavior_event
                if fleet_event.HasField("behavior_event") and event.activation_id == activation_id:
                    events.append(fleet_event)
                    if event.HasField("finished"):
                        assert event.finished.cause == until_cause, event
                        return events
    except grpc.RpcError as error:
        pytest.fail(f"no finished event of {activation_id} at the coordinator ({error.code()}); "
                    f"got {kinds(events)}")
    finally:
        stream.cancel()
    pytest.fail("the coordinator's stream ended")


def kinds(events):
    """What each FleetEvent of a behavior reports ("activated", "finished", ...)."""
    return [e.behavior_event.WhichOneof("kind") for e in events]


def activate_through_coordinator(coordinator, robot, values):
    return coordinator_stub(coordinator).ActivateBehavior(
        coordinator_pb2.ActivateFleetBehaviorRequest(robot_id=robot, behavior="WAIT",
                                                     parameters=struct(values)),
        timeout=CALL_S).activation.activation_id


# ---- What is served ------------------------------------------------------------------------------

def test_registers_and_the_coordinator_lists_its_behavior(coordinator, python_system, cpp_system):
    listed = coordinator_stub(coordinator).ListBehaviors(
        coordinator_pb2.ListFleetBehaviorsRequest(robot_id="drone1"), timeout=CALL_S)
    assert [(b.system, b.description.name, b.description.service) for b in listed.behaviors] == \
        [(SYSTEM, "WAIT", "behaviorlib.v1.Wait")]
    assert listed.behaviors[0].address == python_system.address
    # The Python system describes WAIT exactly as the C++ one does.
    ours = system_stub(python_system).ListBehaviors(behavior_pb2.ListBehaviorsRequest(),
                                                    timeout=CALL_S)
    theirs = system_stub(cpp_system).ListBehaviors(behavior_pb2.ListBehaviorsRequest(),
                                                   timeout=CALL_S)
    assert (ours.robot_id, ours.system) == ("drone1", SYSTEM)
    assert len(ours.behaviors) == 1
    assert ours.behaviors[0] == next(b for b in theirs.behaviors if b.name == "WAIT")
    assert ours.behaviors[0].description.startswith("WAIT: stays active for a given time")


def test_list_behaviors_pages_as_the_cpp_system(python_system, cpp_system):
    for process in (python_system, cpp_system):
        stub = system_stub(process)
        first = stub.ListBehaviors(behavior_pb2.ListBehaviorsRequest(page_size=1),
                                   timeout=CALL_S)
        assert len(first.behaviors) == 1
        if first.next_page_token:
            second = stub.ListBehaviors(behavior_pb2.ListBehaviorsRequest(
                page_size=1, page_token=first.next_page_token), timeout=CALL_S)
            assert second.behaviors[0].name > first.behaviors[0].name
    for request in (behavior_pb2.ListBehaviorsRequest(page_size=-1),
                    behavior_pb2.ListBehaviorsRequest(page_token="nonsense")):
        ours = refusal(lambda: system_stub(python_system).ListBehaviors(request, timeout=CALL_S))
        theirs = refusal(lambda: system_stub(cpp_system).ListBehaviors(request, timeout=CALL_S))
        assert ours == theirs


def test_activation_through_the_coordinator_finishes_goal_achieved(coordinator, python_system):
    activation_id = activate_through_coordinator(coordinator, "drone1", {"duration_s": 0.2})
    events = fleet_events(coordinator, "drone1", activation_id,
                          Cause.TERMINATION_CAUSE_GOAL_ACHIEVED)
    assert kinds(events) == ["activated", "finished"]
    assert events[-1].behavior_event.finished.message == "waited"
    assert events[-1].behavior_event.system == SYSTEM
    assert not events[-1].synthesized


def test_bad_parameters_are_refused_as_by_the_cpp_system(coordinator, python_system, cpp_system):
    activate_request = typed_request("Activate")
    for parameters in (WaitParameters(duration_s=-1), WaitParameters()):
        request = activate_request(parameters=parameters)
        ours = refusal(lambda: typed_stub(python_system, "Activate", activate_request,
                                          behavior_pb2.ActivateResponse)(request, timeout=CALL_S))
        theirs = refusal(lambda: typed_stub(cpp_system, "Activate", activate_request,
                                            behavior_pb2.ActivateResponse)(request,
                                                                           timeout=CALL_S))
        assert ours == theirs
        assert ours[0] == grpc.StatusCode.INVALID_ARGUMENT
        assert [v.field for v in ours[3].field_violations] == ["parameters.duration_s"]
    assert ours[1].startswith("parameter 'duration_s' is required: How long to wait")

    for values in ({"duration_s": "five"}, {"duration_s": 1e6}, {"durations": 1}):
        request = behavior_pb2.ActivateBehaviorRequest(behavior="WAIT", parameters=struct(values))
        direct = refusal(lambda: system_stub(python_system).ActivateBehavior(request,
                                                                             timeout=CALL_S))
        theirs = refusal(lambda: system_stub(cpp_system).ActivateBehavior(request,
                                                                          timeout=CALL_S))
        assert direct == theirs

        # Through the coordinator: the same reason and field violation; the coordinator names
        # the robot and the system in the message and the metadata.
        ours = refusal(lambda: activate_through_coordinator(coordinator, "drone1", values))
        theirs = refusal(lambda: activate_through_coordinator(coordinator, "drone2", values))
        assert ours[0] == theirs[0] == grpc.StatusCode.INVALID_ARGUMENT
        assert ours[2].reason == theirs[2].reason == direct[2].reason
        assert ours[3] == theirs[3]
        assert ours[1].endswith(f"system {SYSTEM} at {python_system.address}: {direct[1]}")
        assert theirs[1].endswith(f": {direct[1]}")
        assert (ours[2].metadata["robot"], ours[2].metadata["system"]) == ("drone1", SYSTEM)

    request = behavior_pb2.CheckBehaviorActivationRequest(behavior="LAND")
    code, message, info, _ = refusal(
        lambda: system_stub(python_system).CheckBehaviorActivation(request, timeout=CALL_S))
    assert (code, info.reason) == (grpc.StatusCode.NOT_FOUND, "UNKNOWN_BEHAVIOR")
    assert message == f"unknown behavior 'LAND'; {SYSTEM} hosts: WAIT"
    assert dict(info.metadata) == {"robot": "drone1", "system": SYSTEM, "behavior": "LAND"}


def test_pause_resume_and_modify_through_the_typed_service(coordinator, python_system):
    activate_request = typed_request("Activate")
    modify_request = typed_request("Modify")

    def call(method, request_class, response_class, request):
        return typed_stub(python_system, method, request_class, response_class)(
            request, timeout=CALL_S)

    activation = call("Activate", activate_request, behavior_pb2.ActivateResponse,
                      activate_request(parameters=WaitParameters(duration_s=600),
                                       request_id="pause-resume-modify"))
    activation_id = activation.activation_id
    again = call("Activate", activate_request, behavior_pb2.ActivateResponse,
                 activate_request(parameters=WaitParameters(duration_s=600),
                                  request_id="pause-resume-modify"))
    assert (again.activation_id, again.replayed) == (activation_id, True)
    call("Pause", behavior_pb2.PauseRequest, behavior_pb2.PauseResponse,
         behavior_pb2.PauseRequest(activation_id=activation_id))
    state = call("CheckActivation", behavior_pb2.CheckActivationRequest,
                 behavior_pb2.CheckActivationResponse, behavior_pb2.CheckActivationRequest())
    assert (state.state, state.activation_id) == (behavior_pb2.BEHAVIOR_STATE_PAUSED,
                                                  activation_id)
    code, _, info, _ = refusal(lambda: call("Pause", behavior_pb2.PauseRequest,
                                            behavior_pb2.PauseResponse,
                                            behavior_pb2.PauseRequest()))
    assert (code, info.reason) == (grpc.StatusCode.FAILED_PRECONDITION,
                                   "BEHAVIOR_ALREADY_PAUSED")
    call("Resume", behavior_pb2.ResumeRequest, behavior_pb2.ResumeResponse,
         behavior_pb2.ResumeRequest(activation_id=activation_id))
    code, _, info, bad = refusal(lambda: call(
        "Modify", modify_request, behavior_pb2.ModifyResponse,
        modify_request(parameters=WaitParameters(duration_s=-2))))
    assert (code, info.reason) == (grpc.StatusCode.INVALID_ARGUMENT, "PARAMETER_OUT_OF_RANGE")
    assert [v.field for v in bad.field_violations] == ["parameters.duration_s"]
    modified = call("Modify", modify_request, behavior_pb2.ModifyResponse,
                    modify_request(activation_id=activation_id,
                                   parameters=WaitParameters(duration_s=0.05)))
    assert modified.parameters["duration_s"] == 0.05

    events = fleet_events(coordinator, "drone1", activation_id,
                          Cause.TERMINATION_CAUSE_GOAL_ACHIEVED)
    assert kinds(events) == ["activated", "paused", "resumed", "modified", "finished"]

    # The system's own resumable stream: the same events, in batches, and a resume after the
    # second one replays only what followed.
    stub = system_stub(python_system)
    watched = []
    stream = stub.WatchEvents(behavior_pb2.WatchEventsRequest(max_events_per_message=64),
                              timeout=WAIT_S)
    start = next(stream).start
    for message in stream:
        watched += [e for e in message.events.events if e.activation_id == activation_id]
        if watched and watched[-1].HasField("finished"):
            break
    stream.cancel()
    assert [e.seq for e in watched] == [e.behavior_event.seq for e in events]
    resumed = stub.WatchEvents(behavior_pb2.WatchEventsRequest(
        since_seq=watched[1].seq, incarnation=start.incarnation), timeout=WAIT_S)
    assert not next(resumed).start.incarnation_changed
    assert next(resumed).event.seq == watched[2].seq
    resumed.cancel()
    other = stub.WatchEvents(behavior_pb2.WatchEventsRequest(since_seq=3, incarnation="other"),
                             timeout=WAIT_S)
    assert next(other).start.incarnation_changed
    other.cancel()


def health_messages():
    """The request and response classes of grpc.health.v1 (health.py's description)."""
    file = add_file(health.file_descriptor_proto())
    return (message_class(file.message_types_by_name["HealthCheckRequest"]),
            message_class(file.message_types_by_name["HealthCheckResponse"]))


def health_check(process, service):
    """The status grpc.health.v1.Health/Check answers for `service`."""
    request_class, response_class = health_messages()
    check = grpc.insecure_channel(process.address).unary_unary(
        "/grpc.health.v1.Health/Check", request_serializer=request_class.SerializeToString,
        response_deserializer=response_class.FromString)
    return check(request_class(service=service), timeout=CALL_S).status


def test_health_check_serving(python_system):
    for service in ("", "behaviorlib.v1.BehaviorSystem", "behaviorlib.v1.Wait",
                    "grpc.health.v1.Health"):
        assert health_check(python_system, service) == health.SERVING
    with pytest.raises(grpc.RpcError) as unknown:
        health_check(python_system, "behaviorlib.v1.Land")
    assert (unknown.value.code(), unknown.value.details()) == \
        (grpc.StatusCode.NOT_FOUND, "service name unknown")  # the C++ servers' words
    request_class, response_class = health_messages()
    channel = grpc.insecure_channel(python_system.address)
    watch = channel.unary_stream("/grpc.health.v1.Health/Watch",
                                 request_serializer=request_class.SerializeToString,
                                 response_deserializer=response_class.FromString)
    stream = watch(request_class(service=""), timeout=CALL_S)
    assert next(stream).status == health.SERVING
    stream.cancel()


def test_streams_are_bounded_and_unary_calls_still_answered(python_system):
    """A stream holds a thread of the server's pool: past the bound, a stream is refused, and
    health checks and other calls are still answered."""
    stub = system_stub(python_system)
    streams = []
    try:
        # The coordinator's event stream holds one slot.
        for _ in range(MAX_STREAMS):
            stream = stub.WatchEvents(behavior_pb2.WatchEventsRequest(), timeout=WAIT_S)
            streams.append(stream)
            try:
                assert next(stream).HasField("start")
            except grpc.RpcError as error:
                code, _, info, _ = details(error)
                break
        else:
            pytest.fail(f"{MAX_STREAMS} streams open beside the coordinator's")
        assert (code, info.reason) == (grpc.StatusCode.RESOURCE_EXHAUSTED, "LIMIT_EXCEEDED")
        assert stub.ListBehaviors(behavior_pb2.ListBehaviorsRequest(), timeout=CALL_S).behaviors
        assert health_check(python_system, "") == health.SERVING
    finally:
        for stream in streams:
            stream.cancel()

    def accepted():
        stream = stub.WatchEvents(behavior_pb2.WatchEventsRequest(), timeout=CALL_S)
        try:
            return next(stream).HasField("start")
        except grpc.RpcError as error:
            assert error.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
            return False
        finally:
            stream.cancel()

    wait_for(accepted, "the streams' slots given back")


def grpcurl(*args):
    """Runs the repository's grpcurl-compatible runner: (exit code, stdout, stderr)."""
    done = subprocess.run([DEBIAN_PYTHON, GRPCURL, "--grpcurl", "-plaintext", *args],
                          capture_output=True, text=True, timeout=WAIT_S)
    return done.returncode, done.stdout, done.stderr


def test_the_typed_method_through_reflection_with_the_grpcurl_runner(coordinator, python_system):
    code, out, err = grpcurl(python_system.address, "list")
    assert code == 0, err
    assert out.split() == ["behaviorlib.v1.BehaviorSystem", "behaviorlib.v1.Wait",
                           "grpc.health.v1.Health", "grpc.reflection.v1.ServerReflection",
                           "grpc.reflection.v1alpha.ServerReflection"]
    code, out, err = grpcurl(python_system.address, "describe", "behaviorlib.v1.Wait")
    assert code == 0, err
    assert "// WAIT: stays active for a given time" in out
    assert "rpc Activate ( .behaviorlib.v1.WaitActivateRequest )" in out

    code, out, err = grpcurl("-d", '{"parameters": {"durationS": 0.05}}', python_system.address,
                             "behaviorlib.v1.Wait/Activate")
    assert code == 0, err
    activation_id = json.loads(out)["activationId"]
    fleet_events(coordinator, "drone1", activation_id, Cause.TERMINATION_CAUSE_GOAL_ACHIEVED)

    code, out, err = grpcurl("-d", '{"parameters": {"durationS": -1}}', python_system.address,
                             "behaviorlib.v1.Wait/Activate")
    assert code == 64 + grpc.StatusCode.INVALID_ARGUMENT.value[0]
    assert "Message: parameter 'duration_s' = -1 is out of range [0, 86400]" in err


def test_reflection_v1alpha_and_every_request(python_system):
    """What the grpcurl runner does not ask (it speaks v1): v1alpha, the symbols of every kind,
    the extensions, and the errors."""
    address = python_system.address
    assert reflection_client.list_services(address, version="v1alpha") == \
        reflection_client.list_services(address, version="v1")
    for symbol in ("behaviorlib.v1.Wait.Modify", "behaviorlib.v1.WaitModifyRequest.parameters",
                   "behaviorlib.v1.WaitParameters.duration_s", "grpc.health.v1.Health",
                   "behaviorlib.v1.TERMINATION_CAUSE_GOAL_ACHIEVED"):
        files = reflection_client.file_containing_symbol(address, symbol, version="v1alpha")
        pool = reflection_client.pool_from_files(files)  # every dependency was sent
        assert pool.FindFileByName(files[0].name)
    files = reflection_client.file_by_filename(
        address, typed.services_file_name(basic_quadrotor_behaviors_pb2.DESCRIPTOR.name))
    assert [s.name for s in files[0].service] == ["Wait", "TakeOff", "Land",
                                                  "HoverWithFlightActionControl",
                                                  "SelfLocalizeWithGroundTruth",
                                                  "EstimatePositionWithSensor",
                                                  "EstimatePositionWithLinearSpeed"]
    assert 51235 in reflection_client.all_extension_numbers_of_type(
        address, "google.protobuf.ServiceOptions")
    files = reflection_client.file_containing_extension(address, "google.protobuf.ServiceOptions",
                                                        51235)
    assert files[0].name == "behaviorlib/v1/options.proto"
    with pytest.raises(reflection_client.ReflectionError) as unknown:
        reflection_client.file_containing_symbol(address, "behaviorlib.v1.Nothing")
    assert unknown.value.code == grpc.StatusCode.NOT_FOUND


def metric_names(process):
    """The names of the series on a process's /metrics."""
    url = f"http://127.0.0.1:{process.ports['metrics_port']}/metrics"
    with urllib.request.urlopen(url, timeout=CALL_S) as response:
        text = response.read().decode()
    return {line.split("{")[0].split(" ")[0] for line in text.splitlines()
            if line and not line.startswith("#")}


def test_metrics_have_the_cpp_systems_names(python_system, cpp_system):
    # After calls and an activation (the tests above), every series has samples.
    ours = metric_names(python_system)
    theirs = metric_names(cpp_system)
    # The C++ HTTP server's own series aside, every C++ series is served (the audit counter
    # too: test_system_security.py counts audited calls at both).
    theirs = {name for name in theirs if not name.startswith("exposer_")}
    assert theirs - ours == set()
    assert {"behaviorlib_activations_total", "behaviorlib_terminations_total",
            "behaviorlib_monitoring_seconds_bucket", "grpc_server_handled_total"} <= ours


# ---- The process's life --------------------------------------------------------------------------

def test_kill_9_is_detected_by_the_coordinator_as_process_failure(stack, coordinator):
    process = stack.python_system("drone3", coordinator)
    wait_up(coordinator, "drone3", SYSTEM)
    activation_id = activate_through_coordinator(coordinator, "drone3", {"duration_s": 3600})
    process.stop(signal.SIGKILL)
    events = fleet_events(coordinator, "drone3", activation_id,
                          Cause.TERMINATION_CAUSE_PROCESS_FAILURE)
    assert kinds(events) == ["activated", "finished"]
    assert events[-1].synthesized  # the coordinator's, the system being dead


def test_sigterm_interrupts_unregisters_and_ends_the_streams(stack, coordinator):
    process = stack.python_system("drone4", coordinator)
    wait_up(coordinator, "drone4", SYSTEM)
    activation_id = activate_through_coordinator(coordinator, "drone4", {"duration_s": 3600})
    stream = system_stub(process).WatchEvents(behavior_pb2.WatchEventsRequest(), timeout=WAIT_S)
    assert next(stream).HasField("start")
    assert process.stop(signal.SIGTERM) == 0
    with pytest.raises(grpc.RpcError) as ended:
        for _ in stream:
            pass
    code, message, info, _ = details(ended.value)
    assert (code, info.reason) == (grpc.StatusCode.UNAVAILABLE, "SHUTTING_DOWN")
    assert "resume with since_seq=" in message
    # The system's own event, read by the coordinator before the system left.
    events = fleet_events(coordinator, "drone4", activation_id,
                          Cause.TERMINATION_CAUSE_INTERRUPTED)
    assert events[-1].behavior_event.finished.message == "process shutting down"
    assert not events[-1].synthesized
    # A registered system that unregistered is removed.
    wait_for(lambda: system_state(coordinator, "drone4", SYSTEM)
             == coordinator_pb2.SYSTEM_STATE_UNSPECIFIED, "the system removed")
    assert "unregistered from the coordinator" in process.log()


def test_registers_again_after_a_coordinator_restart(stack):
    first = stack.coordinator("restarted-coordinator")
    process = stack.python_system("drone5", first)
    wait_up(first, "drone5", SYSTEM)
    first.stop(signal.SIGKILL)
    second = stack.coordinator("restarted-coordinator-2", listen=first.address)
    wait_up(second, "drone5", SYSTEM)
    assert "registering again" in process.log()


def test_simulated_clock_from_the_channel(stack):
    broker = stack.start("channel_broker", [os.path.join(BIN, "channel_broker"),
                                            "--listen", "127.0.0.1:0", "--metrics-listen", ""])
    process = stack.python_system("drone6", None, "--channel", broker.address, "--clock", "sim")
    request = behavior_pb2.ActivateBehaviorRequest(behavior="WAIT",
                                                   parameters=struct({"duration_s": 1}))
    code, _, info, _ = refusal(lambda: system_stub(process).ActivateBehavior(request,
                                                                             timeout=CALL_S))
    assert (code, info.reason) == (grpc.StatusCode.FAILED_PRECONDITION, "CLOCK_NOT_READY")

    # Simulated time at 1000 times the wall time: WAIT's second passes in a millisecond.
    channel = DataChannel(broker.address)
    try:
        sample = types_pb2.Clock(time_scale=1000.0)
        sample.time.FromSeconds(100)
        sample.wall_time.GetCurrentTime()
        channel.publish("clock", sample)
        channel.sync()
        activation = wait_for(lambda: _activated(process, request), "the simulated clock")
    finally:
        channel.close()
    stream = system_stub(process).WatchEvents(behavior_pb2.WatchEventsRequest(), timeout=WAIT_S)
    for message in stream:
        event = message.event
        if event.activation_id == activation.activation_id and event.HasField("finished"):
            break
    stream.cancel()
    assert event.finished.cause == Cause.TERMINATION_CAUSE_GOAL_ACHIEVED
    assert activation.activation_time.seconds >= 100  # simulated time, not the host's


def _activated(process, request):
    try:
        return system_stub(process).ActivateBehavior(request, timeout=CALL_S)
    except grpc.RpcError as error:
        if details(error)[2].reason != "CLOCK_NOT_READY":
            raise
        return None


@pytest.mark.parametrize("flags, said", [
    (["--follow-time", "127.0.0.1:1"], "--follow-time needs --clock sim"),
    (["--config", "x.yaml"], "--config (the system's YAML configuration) is not supported"),
    (["--clock", "sim"], "--clock sim needs --channel"),
    (["--listen", "0.0.0.0:0"], "or --insecure to accept that risk"),
    (["--tls-cert", "/nonexistent.pem"], "--tls-cert /nonexistent.pem: /nonexistent.pem: "
                                         "cannot open"),
    (["--access-policy", "x.yaml"], "--access-policy needs TLS"),
    (["--descriptor-set", "/nonexistent.binpb"], "--descriptor-set /nonexistent.binpb: "),
])
def test_flags_not_served_are_refused(flags, said):
    done = subprocess.run([sys.executable, os.path.abspath(__file__), "--metrics-listen", "",
                           "--listen", "127.0.0.1:0", *flags], capture_output=True, text=True,
                          timeout=WAIT_S)
    assert done.returncode == 2, done.stderr
    assert said in done.stderr


# ---- The protocols' descriptions -----------------------------------------------------------------

def compiled(root, name):
    """protoc's FileDescriptorProto of `name` under `root` (with source info)."""
    with tempfile.TemporaryDirectory() as directory:
        out = os.path.join(directory, "set.binpb")
        subprocess.run([PROTOC, f"--proto_path={root}", f"--proto_path={REPO}/proto",
                        "--include_source_info", f"--descriptor_set_out={out}", name],
                       check=True)
        with open(out, "rb") as f:
            return descriptor_pb2.FileDescriptorSet.FromString(f.read()).file[0]


def without_options_and_comments(file):
    out = descriptor_pb2.FileDescriptorProto()
    out.CopyFrom(file)
    out.ClearField("options")
    out.ClearField("source_code_info")
    return out


@pytest.mark.skipif(not os.path.isdir(GRPC_PROTO_DIR), reason="needs Debian's grpc-proto")
@pytest.mark.parametrize("name, built", [
    ("grpc/health/v1/health.proto", health.file_descriptor_proto()),
    ("grpc/reflection/v1/reflection.proto", reflection.file_descriptor_proto("v1")),
    ("grpc/reflection/v1alpha/reflection.proto", reflection.file_descriptor_proto("v1alpha")),
])
def test_protocol_descriptions_match_the_packaged_protos(name, built):
    assert without_options_and_comments(built) == \
        without_options_and_comments(compiled(GRPC_PROTO_DIR, name))


def test_typed_services_file_matches_the_cpp_builds():
    """The runtime-built services file is the one protoc-gen-behaviorlib generated for the C++
    build: messages, service, option, methods, and the comments and their places."""
    generated = os.path.join(BUILD_DIR, "proto", "gen")
    name = "behaviorlib/v1/behaviors/basic_quadrotor_behaviors_services.proto"
    if not os.path.exists(os.path.join(generated, name)):
        pytest.skip(f"no generated {name} in {generated}")
    theirs = compiled(generated, name)
    documented = compiled(os.path.join(REPO, "proto"),
                          basic_quadrotor_behaviors_pb2.DESCRIPTOR.name)
    ours = typed.services_file(basic_quadrotor_behaviors_pb2.DESCRIPTOR, documented)
    assert without_options_and_comments(ours) == without_options_and_comments(theirs)
    assert ours.options == theirs.options
    locations = {tuple(location.path): location for location in theirs.source_code_info.location}
    for location in ours.source_code_info.location:
        compiled_location = locations[tuple(location.path)]
        assert location.leading_comments == compiled_location.leading_comments
        assert location.span == compiled_location.span
