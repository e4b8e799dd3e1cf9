"""The synchronous client against the real stack (conftest.py): behavior
methods, activations, errors, beliefs, missions and safety actions."""

import inspect
import os
import threading

import pytest

import behaviorlib
from behaviorlib import Fleet
from behaviorlib.v1 import behavior_pb2

from conftest import REPO, wait_until

DEMO_MISSION = os.path.join(REPO, "deploy", "missions", "demo.yaml")
# A WAIT this long never ends by itself within a test (simulated seconds).
LONG_WAIT_S = 3600


@pytest.fixture(scope="module")
def fleet(coordinator):
    with Fleet(coordinator) as fleet:
        yield fleet


def test_a_robot_has_a_method_per_behavior_made_from_its_descriptor(fleet):
    drone = fleet.robot("drone1")
    described = {b.description.name for b in fleet.behaviors(robot_id="drone1")}
    assert set(drone.behaviors) == described
    assert {"TAKE_OFF", "LAND", "FOLLOW_PATH", "QUADROTOR_PID_MOTION_CONTROL"} <= described
    signature = inspect.signature(drone.take_off)
    assert list(signature.parameters) == ["altitude_m"]
    assert signature.parameters["altitude_m"].kind is inspect.Parameter.KEYWORD_ONLY
    assert "altitude_m (number, m); in [0.2, 30]" in drone.take_off.__doc__
    assert "follow_path" in dir(drone)
    with pytest.raises(TypeError, match="height"):
        drone.take_off(height=3)
    with pytest.raises(AttributeError, match="fly_to_the_moon"):
        drone.fly_to_the_moon  # noqa: B018


def test_an_unknown_robot_is_not_found(fleet):
    with pytest.raises(behaviorlib.NotFound):
        fleet.robot("drone9")
    assert fleet.robots() == ["drone1", "drone2"]


def test_take_off_and_land_wait_for_their_termination(fleet):
    drone = fleet.robot("drone1")
    localize = drone.self_localize_with_ground_truth.start()
    up = drone.take_off(altitude_m=1.0)
    assert (up.behavior, up.cause, up.parameters) == ("TAKE_OFF", "GOAL_ACHIEVED",
                                                      {"altitude_m": 1.0}), up
    # A behavior whose situation does not allow it: the coordinator's plan
    # refuses it, with the code.
    with pytest.raises(behaviorlib.FailedPrecondition, match="LANDED"):
        drone.take_off(altitude_m=1.0)
    down = drone.land()
    assert down.succeeded, down
    assert localize.deactivate().cause == behavior_pb2.TERMINATION_CAUSE_INTERRUPTED
    assert localize.wait(timeout_s=30).cause == "INTERRUPTED"


def test_a_parameter_out_of_range_is_invalid_argument(fleet):
    drone = fleet.robot("drone1")
    with pytest.raises(behaviorlib.InvalidArgument, match="altitude_m") as refused:
        drone.take_off(altitude_m=1000)
    assert refused.value.code.name == "INVALID_ARGUMENT"


def test_start_returns_the_activation_which_can_be_waited_for_and_deactivated(fleet):
    drone = fleet.robot("drone2")
    activation = drone.wait.start(duration_s=LONG_WAIT_S)
    assert activation.id and activation.parameters == {"duration_s": LONG_WAIT_S}
    with pytest.raises(behaviorlib.DeadlineExceeded):
        activation.wait(timeout_s=0.2)
    assert not activation.deactivate().already_finished
    termination = activation.wait(timeout_s=30)
    assert (termination.cause, termination.activation_id) == ("INTERRUPTED", activation.id)


def test_an_activation_is_paused_resumed_modified_and_checked_through_the_coordinator(fleet):
    drone = fleet.robot("drone2")
    activation = drone.wait.start(duration_s=LONG_WAIT_S)
    try:
        checked = activation.check()
        assert (checked.active, checked.state, checked.activation_id) == (
            True, behavior_pb2.BEHAVIOR_STATE_ACTIVE, activation.id)
        assert activation.pause().activation_id == activation.id
        assert activation.check().state == behavior_pb2.BEHAVIOR_STATE_PAUSED
        # Paused twice, or resumed while active: refused with the reason.
        with pytest.raises(behaviorlib.FailedPrecondition) as refused:
            activation.pause()
        assert refused.value.reason == "BEHAVIOR_ALREADY_PAUSED"
        assert refused.value.metadata["robot"] == "drone2"
        assert activation.resume().activation_id == activation.id
        assert drone.wait.check_activation().state == behavior_pb2.BEHAVIOR_STATE_ACTIVE
        modified = activation.modify(duration_s=LONG_WAIT_S + 1)
        assert modified.activation_id == activation.id
        assert behaviorlib._core.from_struct(modified.parameters) == {
            "duration_s": LONG_WAIT_S + 1}
        assert behaviorlib._core.from_struct(activation.check().parameters) == {
            "duration_s": LONG_WAIT_S + 1}
        with pytest.raises(behaviorlib.InvalidArgument) as refused:
            activation.modify(duration_s=-1)
        assert refused.value.reason == "PARAMETER_OUT_OF_RANGE"
        assert [field for field, _ in refused.value.field_violations] == ["parameters.duration_s"]
        with pytest.raises(behaviorlib.NotFound):
            drone.pause("NO_SUCH_BEHAVIOR")
    finally:
        activation.deactivate()
    assert activation.wait(timeout_s=30).cause == "INTERRUPTED"
    assert not drone.check_activation("WAIT").active


def test_beliefs_are_written_read_listed_watched_and_deleted(fleet):
    key = "pytest/sync/answer"
    first = fleet.beliefs.write(key, {"x": 1, "tags": ["a", "b"]}, writer="pytest")
    assert fleet.beliefs.value(fleet.beliefs.read(key)) == {"x": 1, "tags": ["a", "b"]}
    assert [b.key for b in fleet.beliefs.list(prefix="pytest/sync/")] == [key]
    # A watcher from the first write's version sees the next write and the
    # deletion (the store keeps each key's latest state, so the test waits
    # for the write to be seen before deleting).
    seen = []

    def watch():
        for belief in fleet.beliefs.watch(prefix="pytest/sync/", since_version=first.version):
            seen.append(belief)
            if belief.deleted:
                return

    watcher = threading.Thread(target=watch, daemon=True)
    watcher.start()
    second = fleet.beliefs.write(key, 42, writer="pytest")
    wait_until(lambda: any(b.version == second.version for b in seen), 30, "the write watched")
    fleet.beliefs.delete(key, writer="pytest")
    watcher.join(timeout=30)
    assert not watcher.is_alive(), "the deletion was not watched"
    assert fleet.beliefs.get(key, "gone") == "gone"
    assert [(fleet.beliefs.value(b), b.deleted) for b in seen] == [(42, False), (None, True)]
    assert seen[0].version < seen[1].version
    assert [b.writer for b in seen] == ["pytest", "pytest"]


def test_a_mission_file_runs_to_success(fleet):
    status = fleet.missions.run(file=DEMO_MISSION, robot_id="drone1", timeout_s=300)
    assert behaviorlib.mission_state(status) == "SUCCEEDED", status
    behaviors = [step.behavior for step in status.steps]
    assert behaviors[-1] == "LAND" and "TAKE_OFF" in behaviors, behaviors
    assert all(step.cause == behavior_pb2.TERMINATION_CAUSE_GOAL_ACHIEVED
               for step in status.steps), status
    assert status.mission_id in [m.mission_id for m in fleet.missions.list()]


def state_of(fleet, mission_id):
    return behaviorlib.mission_state(fleet.missions.get(mission_id))


def start_long_wait(fleet, robot_id):
    """Starts a mission of one long WAIT; returns its id once the WAIT is
    active."""
    text = f"{{name: waits, steps: [{{behavior: WAIT, parameters: {{duration_s: {LONG_WAIT_S}}}}}]}}"
    mission_id = fleet.missions.start(text=text, robot_id=robot_id,
                                      source_name="waits.yaml").mission_id
    for status in fleet.missions.watch(mission_id):
        if status.steps and status.steps[-1].activation_id:
            break
    return mission_id


def test_a_mission_pauses_resumes_and_aborts(fleet):
    mission_id = start_long_wait(fleet, "drone2")
    # Each request is accepted at once and carried out by the mission's
    # thread: its state follows.
    fleet.missions.pause(mission_id)
    wait_until(lambda: state_of(fleet, mission_id) == "PAUSED", 30, "the mission PAUSED")
    fleet.missions.resume(mission_id)
    wait_until(lambda: state_of(fleet, mission_id) == "RUNNING", 30, "the mission RUNNING")
    with pytest.raises(behaviorlib.DeadlineExceeded, match="did not end within 0.5 s"):
        fleet.missions.wait(mission_id, timeout_s=0.5)
    fleet.missions.abort(mission_id, reason="pytest aborts it")
    final = fleet.missions.wait(mission_id, timeout_s=60)
    assert behaviorlib.mission_state(final) == "ABORTED"
    assert "pytest aborts it" in final.message


def test_a_bad_mission_text_is_invalid_argument_naming_its_source(fleet):
    with pytest.raises(behaviorlib.InvalidArgument, match="broken.yaml"):
        fleet.missions.start(text="{name: x, steps: [{behavior: NO_SUCH_BEHAVIOR}]}",
                             robot_id="drone2", source_name="broken.yaml")


def test_a_check_lists_the_problems_of_a_mission_and_plans_a_good_one(fleet):
    text = ("name: x\nsteps:\n  - behavior: NO_SUCH_BEHAVIOR\n"
            "  - behavior: TAKE_OFF\n    parameters: {altitude_m: 500}\n")
    checked = fleet.missions.check(text=text, robot_id="drone2", source_name="broken.yaml")
    assert [(p.line, p.field) for p in checked.problems] == [
        (3, "steps[0].behavior"), (5, "steps[1].parameters.altitude_m")], checked
    assert checked.problems[0].description.startswith("broken.yaml:3: ")
    good = fleet.missions.check(file=DEMO_MISSION, robot_id="drone2")
    assert list(good.problems) == [], good
    assert [p.node for p in good.plans][:2] == ["recurrent/0", "steps/0"], good
    # A plan, or why there is none (a behavior another test left active is
    # "already active"): which, depends on the robot's state, not the file.
    for plan in good.plans:
        assert (plan.plan and plan.plan[-1].behavior == plan.behavior) or plan.no_plan, plan


def test_emergency_land_aborts_the_robots_mission_and_kill_needs_a_confirmation(fleet):
    mission_id = start_long_wait(fleet, "drone2")
    message = fleet.robot("drone2").emergency_land(reason="pytest")
    assert "EMERGENCY_LAND" in message and mission_id in message, message
    assert behaviorlib.mission_state(fleet.missions.wait(mission_id, timeout_s=60)) == "ABORTED"
    with pytest.raises(behaviorlib.FailedPrecondition, match="confirm=True"):
        fleet.robot("drone2").kill(reason="pytest")
