"""Unit tests of the client's pure parts: behavior methods made from a
descriptor, the event stream's resume position, and errors gRPC raises
without details. No server."""

import inspect

import grpc
import pytest

import behaviorlib
from behaviorlib import _core
from behaviorlib.v1 import behavior_pb2, coordinator_pb2


def description():
    d = behavior_pb2.BehaviorDescription(name="GO_TO", description="flies to a point")
    d.parameters.add(name="point_m", type="object", proto_type="behaviorlib.v1.Point",
                     required=True, unit="m")
    speed = d.parameters.add(name="speed_m_s", type="number", proto_type="double", unit="m_s",
                             default_json="0.5")
    speed.range.min, speed.range.max = 0.1, 2.0
    d.parameters.add(name="mode", type="enum", enum_values=["FAST", "SAFE"])
    d.maximum_execution_time.seconds = 30
    return d


def test_a_method_is_made_from_the_descriptor():
    spec = _core.BehaviorSpec.from_description(description())
    assert spec.method == "go_to"
    signature = spec.signature()
    assert list(signature.parameters) == ["point_m", "speed_m_s", "mode"]
    assert all(p.kind is inspect.Parameter.KEYWORD_ONLY for p in signature.parameters.values())
    assert signature.parameters["point_m"].default is inspect.Parameter.empty
    assert signature.parameters["speed_m_s"].default == 0.5
    assert signature.parameters["mode"].default is None
    doc = spec.doc("Returns it.")
    assert "speed_m_s (number, m_s); in [0.1, 2]; default 0.5" in doc
    assert "one of FAST, SAFE" in doc
    assert "30 s of active time" in doc


def test_binding_checks_names_and_required_parameters_and_drops_unset_ones():
    spec = _core.BehaviorSpec.from_description(description())
    assert spec.bind({"point_m": {"x": 1}, "mode": None}) == {"point_m": {"x": 1}}
    with pytest.raises(TypeError, match="unexpected parameter.*speed"):
        spec.bind({"point_m": {}, "speed": 1})
    with pytest.raises(TypeError, match="missing required parameter.*point_m"):
        spec.bind({"speed_m_s": 1})


def test_method_names_are_python_identifiers():
    assert _core.method_name("TAKE_OFF") == "take_off"
    assert _core.method_name("3D_SCAN") == "b_3d_scan"
    assert _core.method_name("acme.GREET") == "acme_greet"


def fleet_event(seq, incarnation, system_incarnation, system_seq, finished=False,
                synthesized=False, activation="A-1"):
    event = coordinator_pb2.FleetEvent(seq=seq, incarnation=incarnation, synthesized=synthesized)
    behavior_event = event.behavior_event
    behavior_event.seq = system_seq
    behavior_event.incarnation = system_incarnation
    behavior_event.robot_id = "drone1"
    behavior_event.behavior = "WAIT"
    behavior_event.activation_id = activation
    if finished:
        behavior_event.finished.cause = behavior_pb2.TERMINATION_CAUSE_GOAL_ACHIEVED
    else:
        behavior_event.activated.SetInParent()
    return event


def start(incarnation, changed=False, dropped=0):
    response = coordinator_pb2.WatchFleetEventsResponse()
    response.start.incarnation = incarnation
    response.start.incarnation_changed = changed
    response.start.events_dropped = dropped > 0
    response.start.dropped_count = dropped
    return response


def batch(*events):
    response = coordinator_pb2.WatchFleetEventsResponse()
    response.events.events.extend(events)
    return response


def test_the_cursor_resumes_after_the_last_event_and_drops_replays_of_a_restarted_coordinator():
    cursor = _core.EventCursor(robot_ids=["drone1"])
    assert cursor.accept(start("c1")) == []
    first = [fleet_event(1, "c1", "s1", 7), fleet_event(2, "c1", "s1", 8, finished=True)]
    assert cursor.accept(batch(*first)) == first
    request = cursor.request()
    assert (request.since_seq, request.incarnation, list(request.robot_ids)) == (2, "c1",
                                                                                  ["drone1"])
    # The coordinator restarted: a new incarnation replays what it read
    # again from the system, then a new event and one it synthesized.
    assert cursor.accept(start("c2", changed=True)) == []
    assert cursor.restarts_seen == 1
    replay = [fleet_event(1, "c2", "s1", 7), fleet_event(2, "c2", "s1", 8, finished=True),
              fleet_event(3, "c2", "s1", 9, activation="A-2")]
    synthesized = fleet_event(4, "c2", "s1", 0, finished=True, synthesized=True,
                              activation="A-2")
    assert cursor.accept(batch(*replay)) == replay[2:]
    assert cursor.accept(batch(synthesized)) == [synthesized]
    assert cursor.accept(batch(synthesized)) == []
    assert (cursor.request().since_seq, cursor.request().incarnation) == (4, "c2")


def test_the_cursor_counts_what_the_coordinator_no_longer_had():
    cursor = _core.EventCursor(since_seq=10, incarnation="c1")
    cursor.accept(start("c1", dropped=5))
    assert cursor.dropped_count == 5
    assert cursor.restarts_seen == 0


def test_terminations_keep_the_newest_finished_activations():
    terminations = _core.Terminations(capacity=2)
    assert terminations.add(fleet_event(1, "c", "s", 1)) is None  # activated: not kept
    for i in range(3):
        terminations.add(fleet_event(2 + i, "c", "s", 2 + i, finished=True, activation=f"A-{i}"))
    assert terminations.get("A-0") is None
    termination = terminations.get("A-2")
    assert (termination.cause, termination.succeeded, termination.behavior) == (
        "GOAL_ACHIEVED", True, "WAIT")


def test_values_come_back_with_their_keys_in_order():
    struct = _core.to_struct({"b": 1, "a": {"d": [{"f": 1, "e": 2}], "c": True}})
    back = _core.from_struct(struct)
    assert back == {"a": {"c": True, "d": [{"e": 2, "f": 1}]}, "b": 1}
    assert list(back) == ["a", "b"] and list(back["a"]) == ["c", "d"]
    assert list(back["a"]["d"][0]) == ["e", "f"]


class _Refused(Exception):
    """A grpc.RpcError as gRPC raises it for the access policy's refusal:
    a code and a message, no trailing details."""

    def __init__(self, code, details):
        super().__init__(details)
        self._code, self._details = code, details

    def code(self):
        return self._code

    def details(self):
        return self._details

    def trailing_metadata(self):
        return ()


def test_the_access_policy_refusal_gets_its_reason_back():
    # gRPC's authentication layer sends no details; the client rebuilds the
    # ErrorInfo from the refusal's stable message (ROLE_REQUIRED).
    error = behaviorlib.errors.from_rpc_error(_Refused(
        grpc.StatusCode.PERMISSION_DENIED,
        "/behaviorlib.v1.Coordinator/Kill needs the role safety; "
        "'behaviorlib:operator' has viewer, operator"))
    assert isinstance(error, behaviorlib.PermissionDenied)
    assert error.reason == "ROLE_REQUIRED"
    assert error.metadata == {"role": "safety", "identity": "behaviorlib:operator"}
    unknown = behaviorlib.errors.from_rpc_error(_Refused(
        grpc.StatusCode.PERMISSION_DENIED,
        "/behaviorlib.v1.Coordinator/Kill needs the role safety; 'stranger' is not in the "
        "access policy"))
    assert unknown.metadata["identity"] == "stranger"
    # Any other refusal is left as it came.
    other = behaviorlib.errors.from_rpc_error(_Refused(grpc.StatusCode.PERMISSION_DENIED,
                                                       "no"))
    assert other.reason == "" and other.metadata == {}


def test_vehicle_sample_kinds_and_numpy_views():
    import math

    from behaviorlib import numpy_helpers as nph
    from behaviorlib.v1 import coordinator_pb2, types_pb2

    with pytest.raises(ValueError, match="ground_truth_pose"):
        _core.sample_kind("thermometer")
    request = _core.sample_request("drone1", "imu", None)
    assert (request.kind, request.max_age_s) == (coordinator_pb2.VEHICLE_SAMPLE_KIND_IMU, -1.0)
    pose = types_pb2.PoseStamped()
    pose.pose.position_m.x, pose.pose.position_m.y, pose.pose.position_m.z = 1.0, 2.0, 3.0
    # 90 degrees about z: w = cos(45), z = sin(45).
    pose.pose.orientation.w = pose.pose.orientation.z = math.sqrt(0.5)
    sample = coordinator_pb2.VehicleSample(kind=coordinator_pb2.VEHICLE_SAMPLE_KIND_POSE)
    sample.sample.Pack(pose)
    unpacked = _core.unpack_sample(sample)
    assert list(nph.position(unpacked)) == [1.0, 2.0, 3.0]
    assert nph.yaw(unpacked) == pytest.approx(math.pi / 2)
    assert nph.yaw(unpacked.pose) == pytest.approx(math.pi / 2)
    # A sample whose Any holds another type is refused, not misread.
    sample.kind = coordinator_pb2.VEHICLE_SAMPLE_KIND_BATTERY
    with pytest.raises(ValueError, match="BatteryState"):
        _core.unpack_sample(sample)
