"""The event stream across a coordinator restart, against the real stack
(conftest.py). Runs last: it SIGKILLs the coordinator, which the launcher
starts again on its port."""

import threading

import grpc

from behaviorlib import Error, EventCursor, Fleet
from behaviorlib._core import to_struct
from behaviorlib.v1 import behavior_pb2_grpc
from behaviorlib.v1.behavior_pb2 import ActivateBehaviorRequest
from conftest import wait_until

ROBOT = "drone1"
SYSTEM = f"basic_quadrotor_behaviors-{ROBOT}"


def finished_activations(events):
    return [e.behavior_event.activation_id for e in events
            if e.behavior_event.WhichOneof("kind") == "finished"]


def test_the_event_stream_resumes_after_a_coordinator_restart_without_gaps_or_duplicates(stack):
    fleet = Fleet(stack.coordinator)
    cursor = EventCursor(robot_ids=[ROBOT], behaviors=["WAIT"])
    events = []

    def read():
        for event in fleet.events(cursor=cursor):
            events.append(event)

    threading.Thread(target=read, daemon=True).start()
    drone = fleet.robot(ROBOT)
    before = drone.wait(duration_s=0.2)
    assert before.cause == "GOAL_ACHIEVED"
    wait_until(lambda: before.activation_id in finished_activations(events), 30,
               "the first WAIT's finished event")

    stack.kill("coordinator")
    # While the coordinator restarts, a WAIT activated on the behavior system
    # itself: its events reach the stream once, whether they happened before
    # or after the new coordinator read the system again.
    with grpc.insecure_channel(f"127.0.0.1:{stack.ports(SYSTEM)['grpc_port']}") as channel:
        direct = behavior_pb2_grpc.BehaviorSystemStub(channel).ActivateBehavior(
            ActivateBehaviorRequest(behavior="WAIT", parameters=to_struct({"duration_s": 0.2})), timeout=10)
    wait_until(lambda: direct.activation_id in finished_activations(events), 60,
               "the directly activated WAIT's finished event")
    # Through the new coordinator (the robot's systems registered again).
    after = wait_until(lambda: _try_wait(fleet), 60, "a WAIT through the new coordinator")
    wait_until(lambda: after.activation_id in finished_activations(events), 30,
               "the last WAIT's finished event")
    fleet.close()

    assert cursor.restarts_seen == 1
    identities = [(e.behavior_event.incarnation, e.behavior_event.seq) for e in events]
    assert len(identities) == len(set(identities)), identities
    by_activation = {}
    for event in events:
        by_activation.setdefault(event.behavior_event.activation_id, []).append(
            event.behavior_event.WhichOneof("kind"))
    for activation in (before.activation_id, direct.activation_id, after.activation_id):
        assert by_activation[activation] == ["activated", "finished"], by_activation


def _try_wait(fleet):
    try:
        termination = fleet.robot(ROBOT).wait(duration_s=0.2)
    except Error:  # the coordinator, or the robot's registration, is not back yet
        return None
    assert termination.cause == "GOAL_ACHIEVED", termination
    return termination
