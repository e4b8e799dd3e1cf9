"""Machine-readable errors (errors.proto) against the real stack: every
refusal carries a google.rpc.ErrorInfo reason with metadata, and refused
parameters and mission files a BadRequest field violation, also when the
coordinator relays a behavior system's refusal."""

import pytest

import behaviorlib
from behaviorlib import Fleet
from behaviorlib.v1 import errors_pb2

# A WAIT this long never ends by itself within a test (simulated seconds).
LONG_WAIT_S = 3600


@pytest.fixture(scope="module")
def fleet(coordinator):
    with Fleet(coordinator) as fleet:
        yield fleet


def test_a_parameter_out_of_range_names_the_field_and_the_reason(fleet):
    with pytest.raises(behaviorlib.InvalidArgument) as refused:
        fleet.robot("drone1").take_off(altitude_m=1000)
    error = refused.value
    assert error.reason == "PARAMETER_OUT_OF_RANGE", error
    assert error.metadata["robot"] == "drone1", error.metadata
    assert error.metadata["behavior"] == "TAKE_OFF", error.metadata
    [(field, description)] = error.field_violations
    assert field == "parameters.altitude_m"
    assert "out of range" in description and "1000" in description


def test_a_situation_refusal_gives_the_situation_codes(fleet):
    drone = fleet.robot("drone1")
    situation = drone.land.check_situation()
    assert not situation.feasible
    # One code per text reason, in the same order.
    assert len(situation.reason_codes) == len(situation.reasons) > 0
    assert errors_pb2.SITUATION_REASON_FLIGHT_STATE in situation.reason_codes, situation
    with pytest.raises(behaviorlib.FailedPrecondition) as refused:
        drone.land()
    error = refused.value
    assert error.reason == "SITUATION_NOT_SUITABLE", error
    assert "SITUATION_REASON_FLIGHT_STATE" in error.metadata["situation_reasons"].split(",")
    assert error.metadata["behavior"] == "LAND"


def test_a_second_activation_is_behavior_already_active(fleet):
    drone = fleet.robot("drone2")
    activation = drone.wait.start(duration_s=LONG_WAIT_S)
    try:
        with pytest.raises(behaviorlib.FailedPrecondition) as refused:
            drone.wait.start(duration_s=LONG_WAIT_S)
        error = refused.value
        assert error.reason == "BEHAVIOR_ALREADY_ACTIVE", error
        assert (error.metadata["robot"], error.metadata["behavior"]) == ("drone2", "WAIT")
        assert error.field_violations == []
    finally:
        activation.deactivate()


def test_a_bad_mission_names_the_field_with_file_and_line(fleet):
    text = ("name: broken\n"
            "steps:\n"
            "  - behavior: WAIT\n"
            "    parameters: {duration_s: 1}\n"
            "    on: {TIMEOUT: abort}\n")
    with pytest.raises(behaviorlib.InvalidArgument) as refused:
        fleet.missions.start(text=text, robot_id="drone2", source_name="broken.yaml")
    error = refused.value
    assert error.reason == "MISSION_INVALID", error
    [(field, description)] = error.field_violations
    assert field == "steps[0].on.TIMEOUT"
    assert description.startswith("broken.yaml:5: "), description

    # Checked against the registered behaviors: the parameter's path.
    text = ("steps:\n"
            "  - behavior: WAIT\n"
            "    parameters: {duration_s: 1, durationn_s: 2}\n")
    with pytest.raises(behaviorlib.InvalidArgument) as refused:
        fleet.missions.start(text=text, robot_id="drone2", source_name="typo.yaml")
    assert refused.value.reason == "MISSION_INVALID"
    [(field, description)] = refused.value.field_violations
    assert field == "steps[0].parameters.durationn_s"
    assert description.startswith("typo.yaml:3: "), description


def test_an_unreasoned_error_still_carries_an_error_info(fleet):
    # A mission that does not exist: every error has an ErrorInfo, with a
    # reason from errors.proto.
    with pytest.raises(behaviorlib.NotFound) as refused:
        fleet.missions.get("no-such-mission")
    reasons = set(errors_pb2.ErrorReason.keys())
    assert refused.value.reason in reasons, refused.value
    assert refused.value.reason == "MISSION_NOT_FOUND", refused.value

