"""The deterministic mode of a Python behavior system (--follow-time, time_follower.py) against
real processes on loopback: build/bin/channel_broker, build/bin/simulator --time-scale max
--min-followers 1 (as deploy/local/launch.py starts it), build/bin/coordinator, and
deterministic_wait_system.py (TEST_WAIT, which measures its ticks, their data and its wall time,
and says it in its finished message).

    BEHAVIORLIB_BUILD_DIR=build venv/bin/python -m pytest -q \
        clients/python/tests/test_system_time_follower.py

What is held: the channel's numbers that the data barrier uses; simulated time does not run
ahead of a Python behavior (every tick at its time, none missed, the clock still under a running
tick, however slow it is); the data barrier (the simulator's samples of a grant, and what the
system itself published at the previous one, are in before a tick); a system that dies or
freezes does not stall the simulator; and the follower leaves the barrier at SIGTERM, runs on in
real time when the simulator goes away and joins a restarted one, and is refused by a simulator
that grants no time. Every process a test starts is killed at the end of the test module, passed
or failed; every wait is a bounded poll, and no assertion is on wall time except as a lower
bound.
"""

import json
import os
import signal
import sys
import tempfile
import time

import grpc
import pytest
from google.protobuf import struct_pb2

from behaviorlib.system.channel import DataChannel
from behaviorlib.v1 import (behavior_pb2, behavior_pb2_grpc, coordinator_pb2,
                            coordinator_pb2_grpc, types_pb2)

from test_system_service import BIN, CALL_S, WAIT_S, Process, Stack, wait_for

SCRIPT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "deterministic_wait_system.py")
SYSTEM = "python_deterministic_waits"
BEHAVIOR = "TEST_WAIT"
QUANTUM_NS = 10_000_000  # the simulator's --quantum-ms default
TICK_NS = 10_000_000  # TEST_WAIT's 100 Hz (BehaviorOptions' default)
# The simulator's --follower-timeout-s default.
FOLLOWER_TIMEOUT_S = 5.0

Cause = behavior_pb2.TerminationCause

pytestmark = pytest.mark.skipif(
    not all(os.path.exists(os.path.join(BIN, name))
            for name in ("channel_broker", "simulator", "coordinator")),
    reason=f"needs the C++ binaries in {BIN} (build first, or set BEHAVIORLIB_BUILD_DIR)")


class Processes(Stack):
    """Starts processes (test_system_service.Process) and kills every one at the end."""

    def broker(self, name):
        return self.start(name, [os.path.join(BIN, "channel_broker"), "--listen", "127.0.0.1:0",
                                 "--metrics-listen", ""])

    def simulator(self, name, broker, *flags, listen="127.0.0.1:0"):
        """The deterministic simulator, time starting once a follower joined (unless `flags`
        say otherwise: a later --time-scale wins)."""
        return self.start(name, [os.path.join(BIN, "simulator"), "--listen", listen,
                                 "--metrics-listen", "", "--channel", broker.address,
                                 "--vehicles", "drone1", "--time-scale", "max",
                                 "--min-followers", "1", *flags])

    def system(self, robot, broker, simulator, *flags):
        """deterministic_wait_system.py following `simulator`'s time grants."""
        return self.start(f"{SYSTEM}-{robot}", [
            sys.executable, SCRIPT, "--robot-id", robot, "--listen", "127.0.0.1:0",
            "--metrics-listen", "", "--channel", broker.address, "--clock", "sim",
            "--follow-time", simulator.address, *flags])


@pytest.fixture(scope="module")
def processes():
    with tempfile.TemporaryDirectory(prefix="behaviorlib-time-follower-") as directory:
        started = Processes(directory)
        try:
            yield started
        finally:
            started.kill_all()


@pytest.fixture(scope="module")
def broker(processes):
    return processes.broker("channel_broker")


@pytest.fixture(scope="module")
def simulator(processes, broker):
    return processes.simulator("simulator", broker)


@pytest.fixture(scope="module")
def coordinator(processes):
    return processes.start("coordinator", [os.path.join(BIN, "coordinator"), "--listen",
                                           "127.0.0.1:0", "--metrics-listen", ""])


@pytest.fixture(scope="module")
def system(processes, broker, simulator, coordinator):
    """drone1's system, registered with the coordinator, the first follower: time starts."""
    process = processes.system("drone1", broker, simulator, "--coordinator", coordinator.address)
    wait_for(lambda: joined(simulator, "drone1"), "the system following the time grants")
    stub = coordinator_pb2_grpc.CoordinatorStub(grpc.insecure_channel(coordinator.address))

    def up():
        listed = stub.ListSystems(coordinator_pb2.ListSystemsRequest(robot_id="drone1"),
                                  timeout=CALL_S)
        return any(s.system == SYSTEM and s.state == coordinator_pb2.SYSTEM_STATE_UP
                   for s in listed.systems)
    wait_for(up, f"{SYSTEM} UP at the coordinator")
    return process


def participant(robot):
    return f"{SYSTEM}/{robot}"


def joined(simulator, robot, times=1):
    return simulator.log().count(f"simulator: {participant(robot)} follows the time grants") \
        >= times


def struct(values):
    out = struct_pb2.Struct()
    out.update(values)
    return out


def system_stub(process):
    return behavior_pb2_grpc.BehaviorSystemStub(grpc.insecure_channel(process.address))


def activate(process, values):
    """Activates TEST_WAIT on the system itself (through the coordinator in the first test):
    the ActivateResponse."""
    return system_stub(process).ActivateBehavior(behavior_pb2.ActivateBehaviorRequest(
        behavior=BEHAVIOR, parameters=struct(values)), timeout=CALL_S)


def finished(process, activation_id):
    """The finished event of `activation_id` (the system's WatchEvents, replayed from the start
    of its log); fails unless it arrives within the wait."""
    stream = system_stub(process).WatchEvents(behavior_pb2.WatchEventsRequest(), timeout=WAIT_S)
    try:
        for message in stream:
            event = message.event
            if event.activation_id == activation_id and event.HasField("finished"):
                return event.finished
    except grpc.RpcError as error:
        pytest.fail(f"no finished event of {activation_id} ({error.code()}):\n{process.log()}")
    finally:
        stream.cancel()
    pytest.fail("the system's event stream ended")


def nanos(duration):
    return duration.seconds * 1_000_000_000 + duration.nanos


def active_ns(process):
    return nanos(system_stub(process).CheckBehaviorActivation(
        behavior_pb2.CheckBehaviorActivationRequest(behavior=BEHAVIOR),
        timeout=CALL_S).active_duration)


def simulated_ns(broker):
    """The simulator's time, from the clock topic it publishes for those outside the barrier."""
    channel = DataChannel(broker.address)
    try:
        stamp = channel.get_latest("clock", types_pb2.Clock).time
    finally:
        channel.close()
    return stamp.seconds * 1_000_000_000 + stamp.nanos


def busy(process):
    """Activates a TEST_WAIT that does not end: the simulator waits for the system."""
    activate(process, {"duration_s": 3600})


# ---- The channel's part of the data barrier ------------------------------------------------------

def test_the_channel_tells_what_it_published_and_what_its_subscriptions_processed(broker):
    topic, other = "robots/drone9/test/barrier", "robots/drone9/test/barrier_rate"
    publisher, reader = DataChannel(broker.address), DataChannel(broker.address)
    try:
        assert publisher.sync(if_published=True) is None  # nothing published: no round trip
        for _ in range(3):
            publisher.publish(topic, types_pb2.PoseStamped())
        assert publisher.sync(if_published=True).topic_seqs[topic] == 3
        assert publisher.accepted_seqs() == {topic: 3}
        # Registered after those three: it waits for none of them.
        seen = []
        subscription = reader.subscribe(topic, types_pb2.PoseStamped, seen.append)
        reader.subscribe(other, types_pb2.PoseStamped, seen.append, max_rate_hz=1.0)
        assert subscription.wait_connected(WAIT_S)
        assert subscription.processed_seq == 3 and reader.delivered({topic: 3})
        # A rate-limited subscription promises no sample: it is not awaited.
        assert reader.awaited_topics() == [topic]
        assert reader.delivered({other: 100})
        assert not reader.wait_delivered({topic: 4}, 0.05)
        publisher.publish(topic, types_pb2.PoseStamped())
        publisher.sync()
        assert reader.wait_delivered({topic: 4}, WAIT_S) and subscription.processed_seq == 4
        assert len(seen) == 1
    finally:
        reader.close()
        publisher.close()


# ---- Time does not run ahead of a Python behavior -----------------------------------------------

def test_a_wait_ends_at_its_simulated_time_with_every_tick_and_its_data(system, coordinator):
    stub = coordinator_pb2_grpc.CoordinatorStub(grpc.insecure_channel(coordinator.address))
    activation = stub.ActivateBehavior(coordinator_pb2.ActivateFleetBehaviorRequest(
        robot_id="drone1", behavior=BEHAVIOR, parameters=struct({"duration_s": 2})),
        timeout=CALL_S).activation
    end = finished(system, activation.activation_id)
    assert end.cause == Cause.TERMINATION_CAUSE_GOAL_ACHIEVED, end
    # Two simulated seconds to the tick: the time did not move past a tick it had not run.
    assert 2_000_000_000 <= nanos(end.active_duration) < 2_000_000_000 + TICK_NS
    measured = json.loads(end.message)
    # Every tick, one quantum apart; the clock never moved under one.
    assert measured["ticks"] == 200
    assert measured["gaps_ns"] == [TICK_NS]
    assert measured["moved_during_execute"] == 0
    # The data barrier: the simulator's newest pose at each tick is of the quantum the grant
    # ended (it publishes at 100 Hz, 1 ms into each quantum), and what the system published at
    # its previous tick has come back through the broker.
    assert 0 <= measured["max_pose_lag_ns"] < QUANTUM_NS
    assert measured["max_echo_lag_ns"] == 0


def test_a_slow_behavior_slows_simulated_time_instead_of_missing_ticks(system):
    # 50 ms of wall time in each on_execute, a tick every 10 ms of simulated time.
    end = finished(system, activate(system, {"duration_s": 0.5,
                                             "execute_sleep_s": 0.05}).activation_id)
    assert end.cause == Cause.TERMINATION_CAUSE_GOAL_ACHIEVED, end
    measured = json.loads(end.message)
    assert measured["ticks"] == 50
    assert measured["gaps_ns"] == [TICK_NS]
    assert measured["moved_during_execute"] == 0
    assert 500_000_000 <= nanos(end.active_duration) < 500_000_000 + TICK_NS
    # So the simulation ran at most a fifth of real time: 0.5 s took 2.5 s of wall time or more.
    assert measured["wall_s"] >= 50 * 0.05


# ---- A follower that goes away ------------------------------------------------------------------

def test_a_killed_system_is_dropped_and_time_goes_on(processes, broker, simulator, system):
    doomed = processes.system("drone2", broker, simulator)
    wait_for(lambda: joined(simulator, "drone2"), "drone2's system following")
    busy(doomed)
    doomed.stop(signal.SIGKILL)
    # Its stream ended: the simulator forgets it at once (no follower time-out).
    wait_for(lambda: f"simulator: {participant('drone2')} stopped following the time grants"
             in simulator.log(), "the simulator dropping the killed follower")
    before = simulated_ns(broker)
    wait_for(lambda: simulated_ns(broker) > before + 1_000_000_000, "simulated time going on")
    assert f"{participant('drone4')} did not catch up" not in simulator.log()


def test_a_frozen_system_is_left_out_until_it_reports_again(processes, broker, simulator,
                                                            system):
    frozen = processes.system("drone3", broker, simulator)
    wait_for(lambda: joined(simulator, "drone3"), "drone3's system following")
    busy(frozen)
    frozen.popen.send_signal(signal.SIGSTOP)
    try:
        said = (f"simulator: {participant('drone3')} did not catch up within "
                f"{FOLLOWER_TIMEOUT_S:.1f} s of wall time; time goes on without waiting for it")
        wait_for(lambda: said in simulator.log(), "the simulator leaving the frozen follower out")
        before = simulated_ns(broker)
        wait_for(lambda: simulated_ns(broker) > before + 1_000_000_000,
                 "simulated time going on without it")
    finally:
        frozen.popen.send_signal(signal.SIGCONT)
    # Thawed, it reports again and is waited for again: a new activation ticks at every
    # quantum. (The first one may have ended already: a tick the freeze caught ran for seconds
    # of wall time, which the engine's watchdog ends with PROCESS_FAILURE.)
    try:
        system_stub(frozen).DeactivateBehavior(
            behavior_pb2.DeactivateBehaviorRequest(behavior=BEHAVIOR), timeout=CALL_S)
    except grpc.RpcError as error:
        assert error.code() == grpc.StatusCode.FAILED_PRECONDITION, error  # not active
    end = finished(frozen, activate(frozen, {"duration_s": 0.5}).activation_id)
    assert end.cause == Cause.TERMINATION_CAUSE_GOAL_ACHIEVED, end
    measured = json.loads(end.message)
    assert (measured["ticks"], measured["gaps_ns"]) == (50, [TICK_NS])
    frozen.stop(signal.SIGKILL)


def test_sigterm_leaves_the_barrier_and_ends_the_activation(processes, broker, simulator,
                                                            system):
    leaving = processes.system("drone4", broker, simulator)
    wait_for(lambda: joined(simulator, "drone4"), "drone4's system following")
    activation_id = activate(leaving, {"duration_s": 3600}).activation_id
    stream = system_stub(leaving).WatchEvents(behavior_pb2.WatchEventsRequest(), timeout=WAIT_S)
    assert next(stream).HasField("start")
    assert leaving.stop(signal.SIGTERM) == 0
    events = []
    with pytest.raises(grpc.RpcError) as ended:
        for message in stream:
            events.append(message.event)
    assert ended.value.code() == grpc.StatusCode.UNAVAILABLE  # drained, then ended
    causes = [e.finished.cause for e in events
              if e.activation_id == activation_id and e.HasField("finished")]
    assert causes == [Cause.TERMINATION_CAUSE_INTERRUPTED]
    # It left the barrier (its stream ended): the simulator did not have to time it out.
    assert f"simulator: {participant('drone4')} stopped following the time grants" \
        in simulator.log()
    assert f"{participant('drone4')} did not catch up" not in simulator.log()


# ---- The simulator goes away, comes back, or grants no time ------------------------------------

def test_time_runs_on_without_the_simulator_and_the_follower_joins_its_restart(processes):
    # A broker and a simulator of its own: this one is killed and started again on its port.
    broker = processes.broker("channel_broker-restart")
    first = processes.simulator("simulator-restart", broker)
    follower = processes.system("drone5", broker, first)
    wait_for(lambda: joined(first, "drone5"), "drone5's system following")
    busy(follower)
    first.stop(signal.SIGKILL)
    said = f"{participant('drone5')}: the time grants ended ("
    wait_for(lambda: said in follower.log(), "the follower telling that the grants ended")
    assert "time runs on in real time" in follower.log()
    # Its behavior's time goes on without grants.
    before = active_ns(follower)
    wait_for(lambda: active_ns(follower) > before + 100_000_000, "time running on")
    system_stub(follower).DeactivateBehavior(
        behavior_pb2.DeactivateBehaviorRequest(behavior=BEHAVIOR), timeout=CALL_S)

    second = processes.simulator("simulator-restart-2", broker, listen=first.address)
    wait_for(lambda: joined(second, "drone5"), "the follower joining the restarted simulator")
    end = finished(follower, activate(follower, {"duration_s": 1}).activation_id)
    assert end.cause == Cause.TERMINATION_CAUSE_GOAL_ACHIEVED, end
    assert 1_000_000_000 <= nanos(end.active_duration) < 1_000_000_000 + TICK_NS
    measured = json.loads(end.message)
    assert (measured["ticks"], measured["gaps_ns"]) == (100, [TICK_NS])


def test_a_simulator_that_grants_no_time_is_asked_again_and_told_once(processes):
    broker = processes.broker("channel_broker-free")
    free_running = processes.simulator("simulator-free", broker, "--time-scale", "1")
    follower = processes.system("drone6", broker, free_running)
    said = f"{participant('drone6')}: the simulator gives no time grants ("
    wait_for(lambda: said in follower.log(), "the follower told of the refusal")
    assert "asking again" in follower.log()
    # It asks again (0.1 s, 0.2 s, 0.4 s, ... apart) and tells it only once.
    time.sleep(1.0)
    assert follower.log().count(said) == 1
    assert follower.popen.poll() is None
