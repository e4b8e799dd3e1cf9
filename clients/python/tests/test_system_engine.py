"""Unit tests of behaviorlib.system, the Python port of the behavior engine's contract: the
monitoring order, every termination cause, the time-out on active time, pause, resume and
modify, the refusals with their reasons, exceptions and the watchdog, the resumable event log,
the deterministic mode's catch-up report, and parameter validation held to the C++ unit tests'
messages. No server: time is a FakeClock, and a test waits for the engine to have run what is
due (ExecutionManager.caught_up) instead of sleeping.

    venv/bin/python -m pytest -q -p no:cacheprovider clients/python/tests/test_system_engine.py

The C++ tests' own parameter messages (tests/unit/behaviorlib/test_parameters.proto) are
compiled here with protoc, with a descriptor set that carries the .proto comments.
"""

import concurrent.futures
import importlib
import json
import math
import os
import shutil
import subprocess
import sys
import threading
import time

import grpc
import pytest
from google.protobuf import json_format, struct_pb2, text_format
from google.rpc import error_details_pb2

from behaviorlib.system import (Behavior, BehaviorContext, BehaviorObserver, BehaviorOptions,
                                Delivery, EventLog, ExecutionManager, FakeClock, Situation,
                                SteadyClock, StatusError, Verdict, apply_defaults_and_validate,
                                cause_name, declared_behavior_name, describe, from_struct,
                                load_descriptor_set, merge_update, number_text, seconds,
                                to_struct, unit_of_field_name)
from behaviorlib.v1 import behavior_pb2, errors_pb2
from behaviorlib.v1.behaviors.basic_quadrotor_behaviors_pb2 import WaitParameters

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", "..", ".."))
CPP_TESTS = os.path.join(REPO, "tests", "unit", "behaviorlib")

Cause = behavior_pb2.TerminationCause
PERIOD = seconds(0.01)  # 100 Hz, the default frequency
WAIT_S = 10.0  # wall-time bound of every wait for the engine's threads


def eventually(predicate, timeout=WAIT_S):
    """Polls `predicate` until it holds or `timeout` seconds of wall time pass."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.001)
    return predicate()


def wait_params(duration_s):
    return WaitParameters(duration_s=duration_s)


# ---- A scriptable behavior (tests/unit/behaviorlib/test_behaviors.h) -----------------------------

class Scripted(Behavior):
    """A behavior whose every function is scriptable, recording its calls and their threads."""

    Parameters = WaitParameters

    def __init__(self, options=None, name="SCRIPTED"):
        super().__init__(name, options)
        self._lock = threading.Lock()
        self._calls = []
        self.situation = Situation.ok
        self.goal = Verdict.keep_going
        self.progress = Verdict.keep_going
        self.processes = Verdict.keep_going
        self.activate_hook = lambda: None
        self.execute_hook = lambda: None
        self.pause_hook = lambda: None
        self.modify_hook = lambda parameters: None
        self.last_active_time = 0
        self.last_duration = 0.0

    def record(self, call):
        with self._lock:
            self._calls.append((call, threading.current_thread()))

    def calls(self):
        with self._lock:
            return [call for call, _ in self._calls]

    def threads(self):
        with self._lock:
            return [thread for _, thread in self._calls]

    def count(self, call):
        return self.calls().count(call)

    def on_activate(self):
        self.record("on_activate")
        self.activate_hook()

    def on_execute(self):
        self.record("on_execute")
        self.last_active_time = self.active_time()
        self.last_duration = self.parameters.duration_s
        self.execute_hook()

    def on_deactivate(self):
        self.record("on_deactivate")

    def on_pause(self):
        self.record("on_pause")
        self.pause_hook()

    def on_resume(self):
        self.record("on_resume")

    def on_modify(self, new_parameters):
        self.record("on_modify")
        self.modify_hook(new_parameters)

    def check_situation(self):
        self.record("check_situation")
        return self.situation()

    def check_goal(self):
        self.record("check_goal")
        return self.goal()

    def check_progress(self):
        self.record("check_progress")
        return self.progress()

    def check_processes(self):
        self.record("check_processes")
        return self.processes()


class Harness:
    """A started engine on a FakeClock with every event collected."""

    def __init__(self, options=None, behavior=None, clock=None, observer=None,
                 before_command=None):
        self.clock = clock or FakeClock()
        self.events = EventLog(robot_id="drone1", system="test")
        self.behavior = behavior or Scripted(options)
        self.engine = ExecutionManager(self.behavior)
        self._subscription = self.events.subscribe()
        self._seen = []
        self.engine.start(BehaviorContext(clock=self.clock, events=self.events,
                                          robot_id="drone1", observer=observer,
                                          before_command=before_command))

    def collected(self):
        self._seen.extend(self._subscription.pop_up_to(1000))
        return list(self._seen)

    def count_kind(self, kind):
        return sum(1 for e in self.collected() if e.WhichOneof("kind") == kind)

    def finished(self, skip=0):
        """The finished event after `skip` earlier ones (waits for it)."""
        found = []

        def seen():
            done = [e for e in self.collected() if e.HasField("finished")]
            found[:] = done[skip:skip + 1]
            return bool(found)

        assert eventually(seen), f"no finished event; events: {self.collected()}"
        return found[0]

    def settle(self):
        """Waits until the engine ran everything due at the clock's time."""
        assert eventually(lambda: self.engine.caught_up(self.clock.now()))

    def tick(self, delta=PERIOD):
        before = self.behavior.count("check_processes")
        self.clock.advance(delta)
        self.settle()
        return self.behavior.count("check_processes") - before

    def activate(self, duration_s=1.0, request_id=""):
        response = self.engine.activate_and_wait(wait_params(duration_s), request_id)
        self.settle()
        return response

    def stop(self):
        self.engine.stop()


@pytest.fixture
def harness():
    made = []

    def make(**kwargs):
        made.append(Harness(**kwargs))
        return made[-1]

    yield make
    for h in made:
        h.stop()


def expect_refusal(call, code, reason, contains=""):
    with pytest.raises(StatusError) as caught:
        call()
    error = caught.value
    assert error.code == code, error
    assert error.reason == reason, error
    assert contains in error.message
    return error


# ---- The tick and the monitoring order -----------------------------------------------------------

def test_the_first_tick_runs_at_activation_in_the_monitoring_order(harness):
    h = harness()
    h.activate()
    assert h.behavior.calls() == ["check_situation", "on_activate", "check_processes",
                                  "check_situation", "check_goal", "check_progress",
                                  "on_execute"]
    time.sleep(0.03)
    assert h.behavior.count("on_execute") == 1, "no further tick until the clock advances"
    assert h.tick() == 1
    assert h.behavior.count("on_execute") == 2
    # Every user function ran on the worker, none on the caller's thread.
    assert threading.current_thread() not in h.behavior.threads()
    assert len(set(h.behavior.threads())) == 1


def test_an_inactive_behavior_does_not_tick(harness):
    h = harness()
    h.clock.advance(seconds(1))
    time.sleep(0.02)
    assert h.behavior.count("check_processes") == 0


def test_ticks_follow_the_frequency_on_the_clock(harness):
    h = harness(options=BehaviorOptions(frequency_hz=10.0))
    h.activate()
    assert h.tick(seconds(0.05)) == 0, "half a period: no tick"
    assert h.tick(seconds(0.05)) == 1
    # A late clock does not burst: one tick, and the schedule moves.
    assert h.tick(seconds(1)) == 1
    assert h.tick(seconds(0.099)) == 0
    assert h.tick(seconds(0.001)) == 1
    # A tick a little late keeps the schedule: the next one is due a period after the last due.
    assert h.tick(seconds(0.15)) == 1
    assert h.tick(seconds(0.05)) == 1


def finish_from_second_tick(h, check, verdict):
    """From the second tick on, `check` reports `verdict`."""
    def script():
        return verdict() if h.behavior.count("on_execute") >= 1 else Verdict.keep_going()
    setattr(h.behavior, check, script)


def infeasible_from_second_tick(h, reason):
    def script():
        if h.behavior.count("on_execute") >= 1:
            return Situation.infeasible(errors_pb2.SITUATION_REASON_UNSPECIFIED, reason)
        return Situation.ok()
    h.behavior.situation = script


@pytest.mark.parametrize("reporting, cause, message", [
    (("processes", "situation", "goal", "progress", "time_out"), Cause.Value(
        "TERMINATION_CAUSE_PROCESS_FAILURE"), "planner died"),
    (("situation", "goal", "progress", "time_out"),
     Cause.Value("TERMINATION_CAUSE_SITUATION_CHANGE"), "too dark"),
    (("goal", "progress", "time_out"), Cause.Value("TERMINATION_CAUSE_GOAL_ACHIEVED"),
     "reached"),
    (("progress", "time_out"), Cause.Value("TERMINATION_CAUSE_WRONG_PROGRESS"), "moving away"),
    (("time_out",), Cause.Value("TERMINATION_CAUSE_TIME_OUT"), "maximum_execution_time"),
])
def test_the_first_check_that_reports_ends_the_activation(harness, reporting, cause, message):
    h = harness(options=BehaviorOptions(maximum_execution_time=seconds(1)))
    if "processes" in reporting:
        finish_from_second_tick(h, "processes", lambda: Verdict.finish("planner died"))
    if "situation" in reporting:
        infeasible_from_second_tick(h, "too dark")
    if "goal" in reporting:
        finish_from_second_tick(h, "goal", lambda: Verdict.finish("reached"))
    if "progress" in reporting:
        finish_from_second_tick(h, "progress", lambda: Verdict.finish("moving away"))
    h.activate()
    mark = len(h.behavior.calls())
    h.tick(seconds(1.5) if "time_out" in reporting else PERIOD)
    finished = h.finished()
    assert finished.finished.cause == cause
    assert message in finished.finished.message
    # The checks after the one that reported did not run, nor did on_execute.
    order = ["check_processes", "check_situation", "check_goal", "check_progress"]
    calls = h.behavior.calls()[mark:]
    assert calls == order[:len(calls) - 1] + ["on_deactivate"]
    assert len(calls) - 1 == (1 + order.index(f"check_{reporting[0]}")
                              if reporting[0] != "time_out" else 4)


TIME_OUT_S = 1.0


@pytest.mark.parametrize("name, cause, script, message", [
    ("goal", "GOAL_ACHIEVED",
     lambda h: finish_from_second_tick(h, "goal", lambda: Verdict.finish("reached")), "reached"),
    ("time_out", "TIME_OUT", lambda h: None, "not finished within maximum_execution_time 1 s "
                                              "of active time"),
    ("progress", "WRONG_PROGRESS",
     lambda h: finish_from_second_tick(h, "progress", lambda: Verdict.finish("moving away")),
     "moving away"),
    ("situation", "SITUATION_CHANGE", lambda h: infeasible_from_second_tick(h, "too dark"),
     "too dark"),
    ("processes", "PROCESS_FAILURE",
     lambda h: finish_from_second_tick(h, "processes", lambda: Verdict.finish("planner died")),
     "planner died"),
    ("exception", "PROCESS_FAILURE",
     lambda h: setattr(h.behavior, "execute_hook", lambda: 1 / 0 if h.behavior.count(
         "on_execute") >= 2 else None),
     "on_execute threw: ZeroDivisionError: division by zero"),
    ("interrupted", "INTERRUPTED", lambda h: None, "deactivation requested"),
])
def test_every_termination_cause_deactivates_then_emits_the_event(harness, name, cause, script,
                                                                   message):
    h = harness(options=BehaviorOptions(maximum_execution_time=seconds(TIME_OUT_S)))
    script(h)
    activation = h.activate()
    if name == "interrupted":
        response = h.engine.deactivate_and_wait(activation.activation_id)
        assert response.cause == Cause.Value("TERMINATION_CAUSE_INTERRUPTED")
        assert not response.already_finished
    elif name == "time_out":
        h.tick(seconds(1.5))
    else:
        h.tick()
    finished = h.finished()
    assert cause_name(finished.finished.cause) == cause
    assert message in finished.finished.message
    assert finished.activation_id == activation.activation_id
    assert finished.behavior == "SCRIPTED"
    assert finished.finished.parameters.fields["duration_s"].number_value == 1.0
    assert h.behavior.count("on_deactivate") == 1
    assert h.behavior.calls()[-1] == "on_deactivate", "on_deactivate runs before the event"
    assert h.engine.state() == behavior_pb2.BEHAVIOR_STATE_INACTIVE
    assert not h.engine.check_activation().active


def test_an_exception_in_a_check_names_the_function_and_the_exception(harness):
    h = harness()

    def bad_index():
        raise IndexError("bad index")

    h.behavior.goal = bad_index
    h.activate()
    finished = h.finished()
    assert finished.finished.cause == Cause.Value("TERMINATION_CAUSE_PROCESS_FAILURE")
    assert finished.finished.message == "check_goal threw: IndexError: bad index"


def test_a_failing_on_deactivate_keeps_the_cause_and_adds_its_failure(harness):
    class FailsToLand(Scripted):
        def on_deactivate(self):
            super().on_deactivate()
            raise RuntimeError("motors did not stop")

    h = harness(behavior=FailsToLand())
    finish_from_second_tick(h, "goal", lambda: Verdict.finish("reached"))
    h.activate()
    h.tick()
    finished = h.finished()
    assert finished.finished.cause == Cause.Value("TERMINATION_CAUSE_GOAL_ACHIEVED")
    assert finished.finished.message == ("reached; on_deactivate threw: RuntimeError: motors did "
                                         "not stop")
    assert h.engine.state() == behavior_pb2.BEHAVIOR_STATE_INACTIVE


def test_a_check_that_returns_no_verdict_is_a_process_failure(harness):
    h = harness()
    h.behavior.progress = lambda: None
    h.activate()
    assert (h.finished().finished.message ==
            "check_progress threw: TypeError: check_progress returned NoneType, not a Verdict")


# ---- Time-out on active time, pause, resume, modify ----------------------------------------------

def test_pause_stops_monitoring_and_the_time_out_counts_active_time_only(harness):
    h = harness(options=BehaviorOptions(maximum_execution_time=seconds(2)))
    activation = h.activate()
    h.tick(seconds(1.5))
    assert h.behavior.last_active_time == seconds(1.5)
    h.engine.pause_and_wait(activation.activation_id)
    assert h.engine.state() == behavior_pb2.BEHAVIOR_STATE_PAUSED
    expect_refusal(h.engine.pause_and_wait, grpc.StatusCode.FAILED_PRECONDITION,
                   "BEHAVIOR_ALREADY_PAUSED", "SCRIPTED is already paused")
    checks = h.behavior.count("check_processes")
    assert h.tick(seconds(10)) == 0, "no monitoring while paused"
    time.sleep(0.03)
    assert h.behavior.count("check_processes") == checks
    assert h.engine.state() == behavior_pb2.BEHAVIOR_STATE_PAUSED, "paused time never times out"
    paused = h.engine.check_activation()
    assert paused.active
    assert paused.active_duration.ToNanoseconds() == seconds(1.5)

    h.engine.resume_and_wait(activation.activation_id)
    h.settle()
    assert h.behavior.count("check_processes") == checks + 1, "resume ticks at once"
    h.tick(seconds(0.4))
    assert h.engine.state() == behavior_pb2.BEHAVIOR_STATE_ACTIVE
    h.tick(seconds(0.2))
    finished = h.finished()
    assert finished.finished.cause == Cause.Value("TERMINATION_CAUSE_TIME_OUT")
    assert finished.finished.active_duration.ToNanoseconds() == seconds(2.1)
    assert h.behavior.count("on_pause") == 1
    assert h.behavior.count("on_resume") == 1
    assert h.count_kind("paused") == 1
    assert h.count_kind("resumed") == 1


def test_a_behavior_ending_through_the_time_out_gives_its_reason(harness):
    class GivesUp(Scripted):
        def check_progress(self):
            if self.give_up:
                self.set_maximum_execution_time(max(self.active_time(), 1),
                                                "planning timed out 3 times")
            return super().check_progress()

    behavior = GivesUp(BehaviorOptions(maximum_execution_time=seconds(1)))
    behavior.give_up = True
    h = harness(behavior=behavior)
    h.activate()
    h.tick()
    first = h.finished()
    assert first.finished.cause == Cause.Value("TERMINATION_CAUSE_TIME_OUT")
    assert first.finished.message == "planning timed out 3 times"
    # The next activation times out on its own limit, with the library's message.
    behavior.give_up = False
    second = h.activate()
    h.tick(seconds(1.1))
    finished = h.finished(skip=1)
    assert finished.activation_id == second.activation_id
    assert finished.finished.message == ("not finished within maximum_execution_time 1 s of "
                                         "active time")


def test_modify_merges_validates_and_notifies(harness):
    h = harness()
    seen = []
    h.behavior.modify_hook = lambda p: seen.append((p.duration_s,
                                                    h.behavior.parameters.duration_s))
    activation = h.activate(5.0)
    modified = h.engine.modify_and_wait(wait_params(7.0), activation.activation_id)
    assert seen == [(7.0, 5.0)], "on_modify sees the new parameters before they take effect"
    assert modified.parameters.fields["duration_s"].number_value == 7.0
    h.tick()
    assert h.behavior.last_duration == 7.0
    assert h.engine.check_activation().parameters.fields["duration_s"].number_value == 7.0

    bad = expect_refusal(lambda: h.engine.modify_and_wait(wait_params(-3.0)),
                         grpc.StatusCode.INVALID_ARGUMENT, "PARAMETER_OUT_OF_RANGE",
                         "parameter 'duration_s' = -3 is out of range [0, 86400]")
    assert bad.field_violations[0][0] == "parameters.duration_s"
    # An empty update keeps everything.
    h.engine.modify_and_wait(WaitParameters())
    assert h.engine.check_activation().parameters.fields["duration_s"].number_value == 7.0

    def refuse(_):
        raise StatusError(grpc.StatusCode.FAILED_PRECONDITION, "cannot shorten now",
                          reason=errors_pb2.BEHAVIOR_FAILED)

    h.behavior.modify_hook = refuse
    refused = expect_refusal(lambda: h.engine.modify_and_wait(wait_params(1.0)),
                             grpc.StatusCode.FAILED_PRECONDITION, "BEHAVIOR_FAILED")
    assert refused.message == "SCRIPTED refused the new parameters: cannot shorten now"
    assert h.engine.check_activation().parameters.fields["duration_s"].number_value == 7.0
    assert h.engine.state() == behavior_pb2.BEHAVIOR_STATE_ACTIVE
    assert h.count_kind("modified") == 2


def test_a_hook_that_raises_while_pausing_ends_the_activation(harness):
    h = harness()

    def brake_stuck():
        raise RuntimeError("brake stuck")

    h.behavior.pause_hook = brake_stuck
    activation = h.activate()
    expect_refusal(lambda: h.engine.pause_and_wait(activation.activation_id),
                   grpc.StatusCode.ABORTED, "",
                   "SCRIPTED: on_pause threw: RuntimeError: brake stuck; the activation ended "
                   "with PROCESS_FAILURE")
    assert h.finished().finished.cause == Cause.Value("TERMINATION_CAUSE_PROCESS_FAILURE")
    assert h.engine.state() == behavior_pb2.BEHAVIOR_STATE_INACTIVE
    assert h.count_kind("paused") == 0


def test_a_performance_change_emits_situation_changed(harness):
    h = harness()
    performance = [1.0]
    h.behavior.situation = lambda: Situation.ok(performance[0])
    h.activate()
    h.tick()
    performance[0] = 0.95  # below the 0.1 threshold
    h.tick()
    assert h.count_kind("situation_changed") == 0
    performance[0] = 0.5
    h.tick()
    changed = [e for e in h.collected() if e.HasField("situation_changed")]
    assert len(changed) == 1
    assert changed[0].situation_changed.performance_ratio == 0.5
    assert changed[0].situation_changed.feasible


# ---- Refusals ------------------------------------------------------------------------------------

def test_invalid_parameters_are_refused_naming_the_field(harness):
    h = harness()
    missing = expect_refusal(lambda: h.engine.activate_and_wait(WaitParameters()),
                             grpc.StatusCode.INVALID_ARGUMENT, "PARAMETER_INVALID", "duration_s")
    assert missing.field_violations[0][0] == "parameters.duration_s"
    negative = expect_refusal(lambda: h.engine.activate_and_wait(wait_params(-1)),
                              grpc.StatusCode.INVALID_ARGUMENT, "PARAMETER_OUT_OF_RANGE")
    assert negative.message == "parameter 'duration_s' = -1 is out of range [0, 86400]"
    assert negative.metadata == {"behavior": "SCRIPTED"}
    assert negative.field_violations == [("parameters.duration_s", negative.message)]
    expect_refusal(lambda: h.engine.activate_and_wait(behavior_pb2.PauseResponse()),
                   grpc.StatusCode.INVALID_ARGUMENT, "INVALID_REQUEST",
                   "SCRIPTED takes parameters of type behaviorlib.v1.WaitParameters")
    assert h.behavior.count("on_activate") == 0


def test_a_second_activation_while_active_is_refused(harness):
    h = harness()
    activation = h.activate()
    error = expect_refusal(lambda: h.engine.activate_and_wait(wait_params(2)),
                           grpc.StatusCode.FAILED_PRECONDITION, "BEHAVIOR_ALREADY_ACTIVE",
                           f"SCRIPTED is already active (activation {activation.activation_id});"
                           " deactivate it first, or use Modify to change its parameters")
    assert error.metadata["current_activation_id"] == activation.activation_id
    assert activation.activation_id == f"SCRIPTED-{h.events.incarnation[:8]}-1"


def test_an_infeasible_situation_refuses_activation_with_its_reasons(harness):
    h = harness()

    def not_flying():
        situation = Situation.infeasible(errors_pb2.SITUATION_REASON_FLIGHT_STATE,
                                         "the robot is not flying")
        situation.add(errors_pb2.SITUATION_REASON_BATTERY_LOW, "battery at 0.10")
        return situation

    h.behavior.situation = not_flying
    error = expect_refusal(lambda: h.engine.activate_and_wait(wait_params(1)),
                           grpc.StatusCode.FAILED_PRECONDITION, "SITUATION_NOT_SUITABLE")
    assert error.message == ("SCRIPTED cannot be activated in the current situation: the robot "
                             "is not flying; battery at 0.10")
    assert (error.metadata["situation_reasons"] ==
            "SITUATION_REASON_FLIGHT_STATE,SITUATION_REASON_BATTERY_LOW")
    situation = h.engine.check_situation_and_wait()
    assert not situation.feasible
    assert list(situation.reasons) == ["the robot is not flying", "battery at 0.10"]
    assert list(situation.reason_codes) == [errors_pb2.SITUATION_REASON_FLIGHT_STATE,
                                            errors_pb2.SITUATION_REASON_BATTERY_LOW]


def test_on_activate_refuses_with_its_code_or_internal_on_an_exception(harness):
    h = harness()

    def no_map():
        raise StatusError(grpc.StatusCode.FAILED_PRECONDITION, "no map loaded")

    h.behavior.activate_hook = no_map
    expect_refusal(lambda: h.engine.activate_and_wait(wait_params(1)),
                   grpc.StatusCode.FAILED_PRECONDITION, "",
                   "SCRIPTED refused activation: no map loaded")

    def crash():
        raise KeyError("map")

    h.behavior.activate_hook = crash
    expect_refusal(lambda: h.engine.activate_and_wait(wait_params(1)), grpc.StatusCode.INTERNAL,
                   "", "SCRIPTED refused activation: on_activate threw: KeyError: 'map'")
    assert h.engine.state() == behavior_pb2.BEHAVIOR_STATE_INACTIVE
    assert h.count_kind("activated") == 0
    assert h.behavior.count("on_execute") == 0


def test_calls_on_an_inactive_behavior_are_refused_not_active(harness):
    h = harness()
    for call, verb in [(h.engine.deactivate_and_wait, "deactivate"),
                       (h.engine.pause_and_wait, "pause"), (h.engine.resume_and_wait, "resume"),
                       (lambda: h.engine.modify_and_wait(wait_params(2)), "modify")]:
        error = expect_refusal(call, grpc.StatusCode.FAILED_PRECONDITION, "BEHAVIOR_NOT_ACTIVE",
                               f"cannot {verb} SCRIPTED: it is not active")
        assert error.metadata == {"behavior": "SCRIPTED"}


def test_resume_when_not_paused_is_refused(harness):
    h = harness()
    h.activate()
    expect_refusal(h.engine.resume_and_wait, grpc.StatusCode.FAILED_PRECONDITION,
                   "BEHAVIOR_NOT_PAUSED", "SCRIPTED is not paused")


def test_a_stale_activation_id_never_acts_on_a_newer_activation(harness):
    h = harness()
    old = h.activate()
    h.engine.deactivate_and_wait(old.activation_id)
    retry = h.engine.deactivate_and_wait(old.activation_id)
    assert retry.already_finished
    assert retry.cause == Cause.Value("TERMINATION_CAUSE_INTERRUPTED")

    current = h.activate()
    assert current.activation_id != old.activation_id
    for call, verb in [(h.engine.deactivate_and_wait, "deactivate"),
                       (h.engine.pause_and_wait, "pause"), (h.engine.resume_and_wait, "resume"),
                       (lambda i: h.engine.modify_and_wait(wait_params(3), i), "modify")]:
        error = expect_refusal(lambda: call(old.activation_id), grpc.StatusCode.ABORTED,
                               "ACTIVATION_MISMATCH")
        assert error.message == (f"cannot {verb} activation {old.activation_id} of SCRIPTED: it "
                                 f"is not the current activation (current: "
                                 f"{current.activation_id})")
        assert error.metadata == {"behavior": "SCRIPTED", "activation_id": old.activation_id,
                                  "current_activation_id": current.activation_id}
    assert h.engine.check_activation().activation_id == current.activation_id
    assert h.engine.check_activation().active


def test_the_same_request_id_replays_the_same_activation(harness):
    h = harness()
    first = h.activate(1.0, "req-1")
    retry = h.engine.activate_and_wait(wait_params(1.0), "req-1")
    assert retry.activation_id == first.activation_id
    assert retry.replayed and not first.replayed
    assert h.behavior.count("on_activate") == 1
    assert h.count_kind("activated") == 1
    expect_refusal(lambda: h.engine.activate_and_wait(wait_params(1.0), "req-2"),
                   grpc.StatusCode.FAILED_PRECONDITION, "BEHAVIOR_ALREADY_ACTIVE")
    h.engine.deactivate_and_wait()
    late = h.engine.activate_and_wait(wait_params(1.0), "req-1")
    assert late.activation_id == first.activation_id
    assert h.engine.state() == behavior_pb2.BEHAVIOR_STATE_INACTIVE


def test_a_clock_without_time_refuses_activation(harness):
    class NoTimeYet(FakeClock):
        def valid(self):
            return False

    h = harness(clock=NoTimeYet())
    expect_refusal(lambda: h.engine.activate_and_wait(wait_params(1)),
                   grpc.StatusCode.FAILED_PRECONDITION, "CLOCK_NOT_READY",
                   "the behavior clock has no time yet")


def test_stop_interrupts_the_activation_and_later_calls_are_shutting_down(harness):
    h = harness()
    activation = h.activate()
    h.engine.stop()
    finished = h.finished()
    assert finished.finished.cause == Cause.Value("TERMINATION_CAUSE_INTERRUPTED")
    assert finished.finished.message == "process shutting down"
    assert finished.activation_id == activation.activation_id
    assert h.behavior.count("on_deactivate") == 1
    expect_refusal(lambda: h.engine.activate_and_wait(wait_params(1)),
                   grpc.StatusCode.UNAVAILABLE, "SHUTTING_DOWN", "SCRIPTED is shutting down")


def test_a_behavior_is_named_by_its_parameters_declaration():
    class Wait(Behavior):
        Parameters = WaitParameters

    class Undeclared(Behavior):
        Parameters = struct_pb2.Struct

    assert Wait().name == "WAIT"
    assert declared_behavior_name(WaitParameters) == "WAIT"
    assert declared_behavior_name(struct_pb2.Struct) == ""
    with pytest.raises(ValueError, match="google.protobuf.Struct declares no behavior"):
        Undeclared()
    wait = Wait()
    with pytest.raises(RuntimeError, match="no engine holds it yet"):
        wait.active_time()
    engine = ExecutionManager(wait)
    assert engine.behavior is wait and engine.name == "WAIT"
    with pytest.raises(ValueError, match="already held by an engine"):
        ExecutionManager(wait)


def test_start_refuses_bad_options_and_a_failing_on_configure():
    clock, events = FakeClock(), EventLog()
    with pytest.raises(StatusError, match="frequency_hz must be in"):
        ExecutionManager(Scripted(BehaviorOptions(frequency_hz=-1))).start(
            BehaviorContext(clock=clock, events=events))

    class Refuses(Scripted):
        def on_configure(self, config):
            raise StatusError(grpc.StatusCode.INVALID_ARGUMENT, "refused by the behavior")

    engine = ExecutionManager(Refuses())
    with pytest.raises(StatusError, match="refused by the behavior"):
        engine.start(BehaviorContext(clock=clock, events=events))
    expect_refusal(lambda: engine.activate_and_wait(wait_params(1)), grpc.StatusCode.UNAVAILABLE,
                   "SHUTTING_DOWN")


# ---- The watchdog --------------------------------------------------------------------------------

class Blocks:
    """What a stuck function waits for; set at the end of the test."""

    def __init__(self):
        self.release = threading.Event()
        self.entered = threading.Event()

    def __call__(self):
        self.entered.set()
        self.release.wait()


class Observer(BehaviorObserver):
    def __init__(self):
        self.blocked = []
        self.finished = []

    def on_blocked(self, blocked):
        self.blocked.append(blocked)

    def on_finished(self, cause):
        self.finished.append(cause)


def test_the_watchdog_ends_the_activation_and_blocks_until_the_stuck_function_returns(harness):
    observer = Observer()
    h = harness(options=BehaviorOptions(watchdog_timeout=seconds(0.2)), observer=observer)
    stuck = Blocks()
    h.behavior.execute_hook = stuck
    try:
        first = h.activate()
        finished = h.finished()
        assert finished.activation_id == first.activation_id
        assert finished.finished.cause == Cause.Value("TERMINATION_CAUSE_PROCESS_FAILURE")
        assert finished.finished.message == (
            "on_execute did not return within 0.2 s (watchdog); SCRIPTED accepts activations "
            "again once it returns")
        assert observer.blocked == [True]
        old_worker = h.behavior.threads()[0]
        assert old_worker.is_alive(), "the stuck function still runs"

        # BLOCKED, as in C++: every call that would run the behavior's code is refused.
        assert h.engine.state() == behavior_pb2.BEHAVIOR_STATE_BLOCKED
        check = h.engine.check_activation()
        assert not check.active and check.state == behavior_pb2.BEHAVIOR_STATE_BLOCKED
        blocked = "is blocked: user code of its previous activation has not returned yet"
        for call in (lambda: h.engine.activate_and_wait(wait_params(1)),
                     lambda: h.engine.pause_and_wait(first.activation_id),
                     lambda: h.engine.resume_and_wait(first.activation_id),
                     lambda: h.engine.check_situation_and_wait(),
                     lambda: h.engine.deactivate_and_wait()):
            expect_refusal(call, grpc.StatusCode.FAILED_PRECONDITION, "BEHAVIOR_BLOCKED", blocked)
        # The finished activation, named, is said finished.
        gone = h.engine.deactivate_and_wait(first.activation_id)
        assert gone.already_finished
        assert gone.cause == Cause.Value("TERMINATION_CAUSE_PROCESS_FAILURE")
        assert h.behavior.count("on_deactivate") == 0, "nothing runs beside the stuck function"
    finally:
        stuck.release.set()
    # Once it returns, its own thread runs on_deactivate and ends; activations are accepted.
    old_worker.join(WAIT_S)
    assert not old_worker.is_alive()
    assert h.behavior.count("on_deactivate") == 1
    assert h.behavior.threads()[-1] is old_worker, "on_deactivate ran on the stuck worker"
    assert h.engine.state() == behavior_pb2.BEHAVIOR_STATE_INACTIVE
    assert eventually(lambda: observer.blocked == [True, False])
    h.behavior.execute_hook = lambda: None
    second = h.activate()
    assert h.engine.state() == behavior_pb2.BEHAVIOR_STATE_ACTIVE
    assert h.tick() == 1
    assert h.behavior.threads()[-1] is not old_worker, "a new worker serves"
    h.engine.deactivate_and_wait(second.activation_id)
    assert h.count_kind("finished") == 2


def test_the_watchdog_answers_the_call_waiting_on_a_stuck_hook(harness):
    h = harness(options=BehaviorOptions(watchdog_timeout=seconds(0.2)))
    stuck = Blocks()
    h.behavior.pause_hook = stuck
    try:
        activation = h.activate()
        future = h.engine.pause(activation.activation_id)
        with pytest.raises(StatusError) as caught:
            future.result(WAIT_S)
        assert caught.value.code == grpc.StatusCode.ABORTED
        assert caught.value.message == ("SCRIPTED: stopped by the watchdog; the activation "
                                        "ended with PROCESS_FAILURE")
        finished = h.finished()
        assert finished.finished.cause == Cause.Value("TERMINATION_CAUSE_PROCESS_FAILURE")
        assert finished.finished.message.startswith("on_pause did not return within 0.2 s")
        assert h.count_kind("paused") == 0
    finally:
        stuck.release.set()
    assert eventually(lambda: h.engine.state() == behavior_pb2.BEHAVIOR_STATE_INACTIVE)
    h.activate()
    assert h.engine.state() == behavior_pb2.BEHAVIOR_STATE_ACTIVE


def test_a_stuck_on_deactivate_ends_the_activation_once(harness):
    stuck = Blocks()

    class StuckLanding(Scripted):
        block = True

        def on_deactivate(self):
            super().on_deactivate()
            if self.block:
                stuck()

    h = harness(behavior=StuckLanding(BehaviorOptions(watchdog_timeout=seconds(0.2))))
    try:
        activation = h.activate()
        # As in C++, the caller is told the deactivation it asked for.
        response = h.engine.deactivate_and_wait(activation.activation_id, timeout=WAIT_S)
        assert response.cause == Cause.Value("TERMINATION_CAUSE_INTERRUPTED")
        finished = h.finished()
        assert finished.finished.cause == Cause.Value("TERMINATION_CAUSE_PROCESS_FAILURE")
        assert finished.finished.message.startswith("on_deactivate did not return within 0.2 s")
        assert h.engine.state() == behavior_pb2.BEHAVIOR_STATE_BLOCKED
        h.behavior.block = False
    finally:
        stuck.release.set()
    assert eventually(lambda: h.engine.state() == behavior_pb2.BEHAVIOR_STATE_INACTIVE)
    assert h.behavior.count("on_deactivate") == 1, "not run again once it returned"
    h.activate()
    assert h.engine.state() == behavior_pb2.BEHAVIOR_STATE_ACTIVE


def test_a_stuck_check_situation_while_active_answers_infeasible(harness):
    h = harness(options=BehaviorOptions(watchdog_timeout=seconds(0.2)))
    stuck = Blocks()
    try:
        h.activate()
        # Nothing ticks without the clock: the call below is the only one that runs it.
        h.behavior.situation = lambda: (stuck(), Situation.ok())[1]
        answer = h.engine.check_situation_and_wait(timeout=WAIT_S)
        assert not answer.feasible
        assert list(answer.reasons) == ["stopped by the watchdog"]
        assert h.finished().finished.cause == Cause.Value("TERMINATION_CAUSE_PROCESS_FAILURE")
    finally:
        stuck.release.set()


def test_stop_abandons_a_worker_stuck_in_user_code(harness):
    stuck = Blocks()

    class StuckLanding(Scripted):
        def on_deactivate(self):
            super().on_deactivate()
            stuck()

    h = harness(behavior=StuckLanding())  # watchdog 1 s: longer than stop's wait below
    try:
        h.activate()
        started = time.monotonic()
        h.engine.stop(timeout=0.2)
        assert time.monotonic() - started < WAIT_S
        expect_refusal(lambda: h.engine.activate_and_wait(wait_params(1)),
                       grpc.StatusCode.UNAVAILABLE, "SHUTTING_DOWN")
    finally:
        stuck.release.set()


def test_a_caller_of_a_stuck_unwatched_function_gets_unresponsive(harness):
    # on_activate runs before the activation exists: the watchdog does not watch it (C++ too).
    h = harness(options=BehaviorOptions(watchdog_timeout=seconds(0.05)))
    stuck = Blocks()
    h.behavior.activate_hook = stuck
    try:
        expect_refusal(lambda: h.engine.activate_and_wait(wait_params(1), timeout=0.3),
                       grpc.StatusCode.DEADLINE_EXCEEDED, "BEHAVIOR_UNRESPONSIVE",
                       "the behavior did not answer in time")
    finally:
        stuck.release.set()
    h.settle()
    assert h.engine.state() == behavior_pb2.BEHAVIOR_STATE_ACTIVE, "the late activation ran"


# ---- Data onto the worker ------------------------------------------------------------------------

def test_samples_reach_the_handler_on_the_worker_and_die_with_their_activation(harness):
    h = harness()
    received = []
    feeds = []

    def activate_hook():
        feeds.append(h.behavior.on_worker(
            lambda sample: received.append((sample, threading.current_thread()))))

    h.behavior.activate_hook = activate_hook
    h.activate()
    worker = h.behavior.threads()[0]
    feeds[0]("a")
    feeds[0]("b")
    assert eventually(lambda: len(received) == 2)
    assert [s for s, _ in received] == ["a", "b"]
    assert all(thread is worker for _, thread in received)
    h.engine.deactivate_and_wait()
    feeds[0]("late")
    h.engine.check_situation_and_wait()  # the worker has looked at its inbox since
    assert [s for s, _ in received] == ["a", "b"], "a sample of an ended activation is dropped"


def test_a_failing_sample_handler_ends_the_activation(harness):
    h = harness()
    feeds = []
    h.behavior.activate_hook = lambda: feeds.append(h.behavior.on_worker(
        lambda sample: int(sample), Delivery.LATEST))
    h.activate()
    feeds[0]("not a number")
    finished = h.finished()
    assert finished.finished.cause == Cause.Value("TERMINATION_CAUSE_PROCESS_FAILURE")
    assert finished.finished.message.startswith(
        "a sample handler (on_worker) threw: ValueError: invalid literal")


# ---- The deterministic mode's hook ---------------------------------------------------------------

def test_caught_up_reports_ticks_due_up_to_a_time(harness):
    h = harness()
    assert h.engine.caught_up(h.clock.now()) and h.engine.idle()
    h.activate()
    assert h.engine.caught_up(h.clock.now())
    assert not h.engine.idle(), "active"
    assert not h.engine.caught_up(h.clock.now() + PERIOD), "the next tick is due then"
    h.clock.advance(PERIOD)
    h.settle()
    assert h.behavior.count("on_execute") == 2


def test_a_command_held_at_the_time_gate_is_caught_up_but_not_idle(harness):
    gate_open = threading.Event()
    gate_open.set()
    waiting = threading.Event()

    def before_command():
        if not gate_open.is_set():
            waiting.set()
        gate_open.wait()

    h = harness(before_command=before_command)
    activated_at = []
    h.behavior.activate_hook = lambda: activated_at.append(h.clock.now())
    gate_open.clear()
    future = h.engine.activate(wait_params(10.0))
    assert waiting.wait(WAIT_S)
    t0 = h.clock.now()
    assert h.engine.caught_up(t0 + seconds(1))
    assert not h.engine.idle()
    assert h.behavior.count("on_activate") == 0
    # The grant moves the clock, then the gate opens: the activation starts at the new time.
    h.clock.advance(seconds(0.7))
    gate_open.set()
    future.result(WAIT_S)
    assert activated_at == [t0 + seconds(0.7)]
    h.settle()
    assert not h.engine.idle()


# ---- Events --------------------------------------------------------------------------------------

def test_events_carry_identity_and_consecutive_seqs(harness):
    h = harness()
    activation = h.activate()
    h.engine.deactivate_and_wait()
    events = h.collected()
    assert [e.WhichOneof("kind") for e in events] == ["activated", "finished"]
    assert events[1].seq == events[0].seq + 1
    for e in events:
        assert (e.robot_id, e.system, e.behavior) == ("drone1", "test", "SCRIPTED")
        assert e.incarnation == h.events.incarnation
        assert e.activation_id == activation.activation_id
        assert e.time.seconds == 3600  # the fake clock's start
        assert e.wall_time.seconds > 0
    assert events[0].activated.parameters.fields["duration_s"].number_value == 1.0


def test_a_watcher_resumes_from_since_seq(harness):
    h = harness()
    for _ in range(3):
        h.activate()
        h.engine.deactivate_and_wait()
    assert h.events.latest_seq() == 6
    resumed = h.events.subscribe(since_seq=4, incarnation=h.events.incarnation)
    assert resumed.start.latest_seq == 6 and not resumed.start.events_dropped
    assert [e.seq for e in resumed.pop_up_to(100)] == [5, 6]
    assert resumed.last_popped_seq() == 6
    h.activate()
    assert [e.seq for e in resumed.pop_up_to(100)] == [7]
    restarted = h.events.subscribe(since_seq=4, incarnation="another-run")
    assert restarted.start.incarnation_changed
    assert [e.seq for e in restarted.pop_up_to(100)] == [1, 2, 3, 4, 5, 6, 7]
    only = h.events.subscribe(behaviors=["OTHER"])
    assert only.pop() is None


def test_the_log_is_bounded_and_reports_what_a_watcher_lost():
    log = EventLog(capacity=5, incarnation="run-b")
    for i in range(8):
        log.append(behavior_pb2.BehaviorEvent(behavior="WAIT", activation_id=str(i),
                                              activated=behavior_pb2.ActivatedEvent()))
    assert log.retained_count() == 5
    lost = log.subscribe(since_seq=1)
    assert lost.start.events_dropped and lost.start.dropped_count == 2
    assert lost.start.oldest_retained_seq == 4
    assert [e.seq for e in lost.pop_up_to(100)] == [4, 5, 6, 7, 8]
    assert not log.subscribe(since_seq=3).start.events_dropped


def test_a_slow_watcher_overflows_while_others_keep_receiving():
    log = EventLog(subscriber_queue_limit=2)
    wakes = []
    slow = log.subscribe(wake=lambda: wakes.append("slow"))
    fast = log.subscribe()
    for i in range(4):
        log.append(behavior_pb2.BehaviorEvent(behavior="WAIT",
                                              modified=behavior_pb2.ModifiedEvent()))
        assert fast.pop().seq == i + 1
    assert slow.overflowed()
    assert [e.seq for e in slow.pop_up_to(10)] == [1, 2]
    assert wakes == ["slow", "slow"], "woken when it became non-empty, and at the overflow"


def test_finished_activations_expire_after_the_retention():
    now = [0]
    log = EventLog(retention=seconds(10), wall_now=lambda: now[0])
    log.append(behavior_pb2.BehaviorEvent(behavior="WAIT", activation_id="a",
                                          activated=behavior_pb2.ActivatedEvent()))
    now[0] += seconds(60)
    assert log.retained_count() == 1, "kept while its activation runs"
    log.append(behavior_pb2.BehaviorEvent(behavior="WAIT", activation_id="a",
                                          finished=behavior_pb2.FinishedEvent()))
    now[0] += seconds(9)
    assert log.retained_count() == 2
    now[0] += seconds(1)
    assert log.retained_count() == 0


def test_a_cancelled_subscription_is_not_woken():
    log = EventLog()
    wakes = []
    subscription = log.subscribe(wake=lambda: wakes.append(1))
    subscription.cancel()
    log.append(behavior_pb2.BehaviorEvent(behavior="WAIT"))
    assert wakes == [] and subscription.pop() is None


# ---- Clocks --------------------------------------------------------------------------------------

def test_the_steady_clock_reads_as_unix_time_and_never_goes_back():
    clock = SteadyClock()
    first = clock.now()
    assert abs(first - time.time_ns()) < seconds(1)
    assert clock.now() >= first
    assert clock.wall_wait_for(seconds(0.5)) == 0.5


def test_the_fake_clock_never_goes_back_and_tells_its_listeners():
    clock = FakeClock()
    assert clock.now() == seconds(3600)
    advanced = []

    class Listener:
        def on_clock_advanced(self):
            advanced.append(clock.now())

        def caught_up(self, t):
            return t <= seconds(3601)

    listener = Listener()
    clock.add_listener(listener)
    clock.advance(seconds(1))
    clock.set(seconds(10))  # backwards: ignored
    assert advanced == [seconds(3601), seconds(3601)]
    assert clock.listeners_caught_up(seconds(3601))
    assert not clock.listeners_caught_up(seconds(3602))
    clock.remove_listener(listener)
    clock.advance(1)
    assert len(advanced) == 2


# ---- Parameters ----------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def test_protos(tmp_path_factory):
    """tests/unit/behaviorlib/test_parameters.proto compiled with protoc, and the comments of
    it and of proto/behaviorlib loaded (what the C++ embeds)."""
    protoc = os.environ.get("PROTOC") or shutil.which("protoc")
    assert protoc, "protoc is needed (Debian's protobuf-compiler), as for installing the package"
    out = tmp_path_factory.mktemp("test_protos")
    roots = [f"--proto_path={CPP_TESTS}", f"--proto_path={os.path.join(REPO, 'proto')}"]
    subprocess.run([protoc, *roots, f"--python_out={out}", "test_parameters.proto"], check=True)
    descriptor_set = out / "descriptors.binpb"
    subprocess.run([protoc, *roots, "--include_imports", "--include_source_info",
                    f"--descriptor_set_out={descriptor_set}", "test_parameters.proto",
                    "behaviorlib/v1/behaviors/basic_quadrotor_behaviors.proto"], check=True)
    load_descriptor_set(descriptor_set.read_bytes())
    sys.path.insert(0, str(out))
    try:
        return importlib.import_module("test_parameters_pb2")
    finally:
        sys.path.remove(str(out))


def struct_of(text):
    """A Struct from JSON text, as the C++ tests build their inputs."""
    return json_format.Parse(text, struct_pb2.Struct())


def message_class(test_protos, name):
    return WaitParameters if name == "Wait" else getattr(test_protos, name)


INVALID = "PARAMETER_INVALID"
OUT_OF_RANGE = "PARAMETER_OUT_OF_RANGE"

# (message, JSON input, the C++ test's expected text, reason, violated field). The expected
# texts are copied from tests/unit/behaviorlib/parameters_test.cc (FromStructTest), which holds
# the C++ implementation to them as substrings; the reasons and fields are what
# parameters.cc attaches to each.
FROM_STRUCT_CASES = [
    ("Wait", '{"duration_s": "five"}',
     """parameter 'duration_s': expected a number, got a string ("five")""", INVALID,
     "duration_s"),
    ("AllKinds", '{"count": "5"}', """parameter 'count': expected an integer, got a string ("5")""",
     INVALID, "count"),
    ("AllKinds", '{"enabled": 1}', "parameter 'enabled': expected a boolean, got a number (1)",
     INVALID, "enabled"),
    ("AllKinds", '{"name": false}', "parameter 'name': expected a string, got a boolean (false)",
     INVALID, "name"),
    ("AllKinds", '{"blob": 3}', "parameter 'blob': expected a base64 string, got a number (3)",
     INVALID, "blob"),
    ("AllKinds", '{"target": 5}', "parameter 'target': expected an object, got a number (5)",
     INVALID, "target"),
    ("AllKinds", '{"target": [1]}', "parameter 'target': expected an object, got a list", INVALID,
     "target"),
    ("AllKinds", '{"ids": 3}', "parameter 'ids': expected a list, got a number (3)", INVALID,
     "ids"),
    ("AllKinds", '{"count": {}}', "parameter 'count': expected an integer, got an object",
     INVALID, "count"),
    ("AllKinds", '{"limits": [1]}', "parameter 'limits': expected an object, got a list",
     INVALID, "limits"),
    ("Wait", '{"durration_s": 5}',
     "unknown parameter 'durration_s' for behaviorlib.v1.WaitParameters; known parameters: "
     "duration_s", INVALID, "durration_s"),
    ("AllKinds", '{"target": {"z_m": 1}}',
     "unknown parameter 'target.z_m' for behaviorlib.test.Waypoint; known parameters: x_m, y_m, "
     "speed_m_s", INVALID, "target.z_m"),
    ("Wait", '{"duration_s": null}', "parameter 'duration_s': null is not accepted", INVALID,
     "duration_s"),
    ("AllKinds", '{"ids": [1, null]}', "parameter 'ids[1]': expected an integer, got null",
     INVALID, "ids[1]"),
    ("AllKinds", '{"target": null}', "parameter 'target': null is not accepted", INVALID,
     "target"),
    ("AllKinds", '{"count": 2.5}', "parameter 'count': 2.5 is not an integer", INVALID, "count"),
    ("AllKinds", '{"ids": [1, 2.5]}', "parameter 'ids[1]': 2.5 is not an integer", INVALID,
     "ids[1]"),
    ("AllKinds", '{"small_u": -1}',
     "parameter 'small_u': -1 is negative, but the parameter is uint32 (unsigned)", INVALID,
     "small_u"),
    ("AllKinds", '{"big_u": -2}', "parameter 'big_u': -2 is negative", INVALID, "big_u"),
    ("AllKinds", '{"count": 3000000000}',
     "parameter 'count': 3000000000 is out of range for int32 [-2147483648, 2147483647]",
     OUT_OF_RANGE, "count"),
    ("AllKinds", '{"count": -2147483649}', "out of range for int32", OUT_OF_RANGE, "count"),
    ("AllKinds", '{"small_u": 4294967296}', "out of range for uint32 [0, 4294967295]",
     OUT_OF_RANGE, "small_u"),
    ("AllKinds", '{"big": 1e19}', "out of range for int64", OUT_OF_RANGE, "big"),
    ("AllKinds", '{"big_u": 2e19}', "out of range for uint64", OUT_OF_RANGE, "big_u"),
    ("AllKinds", '{"ratio": 1e40}', "parameter 'ratio': 1e+40 is out of range for float",
     INVALID, "ratio"),
    ("AllKinds", '{"blob": "%%%"}', """parameter 'blob': "%%%" is not valid base64""", INVALID,
     "blob"),
    ("AllKinds", '{"mode": "FAST"}',
     """parameter 'mode': unknown value "FAST"; accepted: SLOW, MEDIUM""", INVALID, "mode"),
    ("AllKinds", '{"mode": "medium"}', """unknown value "medium\"""", INVALID, "mode"),
    ("AllKinds", '{"modes": ["SLOW", 7]}',
     "parameter 'modes[1]': unknown value 7; accepted: SLOW (0), MEDIUM (1)", INVALID,
     "modes[1]"),
    ("AllKinds", '{"mode": 0.5}', "parameter 'mode': 0.5 is not an integer", INVALID, "mode"),
    ("AllKinds", '{"mode": true}',
     "parameter 'mode': expected one of SLOW, MEDIUM, got a boolean (true)", INVALID, "mode"),
    ("AllKinds", '{"path": {"waypoints": [{"x_m": 1}, {"x_m": "far"}]}}',
     """parameter 'path.waypoints[1].x_m': expected a number, got a string ("far")""", INVALID,
     "path.waypoints[1].x_m"),
    ("Path", '{"waypoints": [{"x_m": 1}, {"x_m": true}]}',
     "parameter 'waypoints[1].x_m': expected a number", INVALID, "waypoints[1].x_m"),
    ("Path", '{"waypoints": [{"x_m": 1}, 2]}',
     "parameter 'waypoints[1]': expected an object, got a number (2)", INVALID, "waypoints[1]"),
    ("Path", '{"waypoints": [{"xm": 1}]}',
     "unknown parameter 'waypoints[0].xm' for behaviorlib.test.Waypoint", INVALID,
     "waypoints[0].xm"),
    ("AllKinds", '{"stops": {"x": {}}}', """parameter 'stops': key "x" is not a valid int32""",
     INVALID, "stops"),
    ("AllKinds", '{"limits": {"a": "high"}}', """parameter 'limits["a"]': expected a number""",
     INVALID, 'limits["a"]'),
    ("AllKinds", '{"stops": {"2": {"x_m": "far"}}}',
     "parameter 'stops[2].x_m': expected a number", INVALID, "stops[2].x_m"),
    ("AllKinds", '{"goal_name": "home", "goal_yaw_rad": 1}',
     "parameters 'goal_name' and 'goal_yaw_rad' are alternatives (oneof goal); set only one",
     INVALID, "goal_yaw_rad"),
    ("AllKinds", '{"camel_case_name": "a", "camelCaseName": "b"}',
     "parameter 'camel_case_name' is given twice, as 'camelCaseName' and as 'camel_case_name'",
     INVALID, "camel_case_name"),
]

# (message, text-format input, the C++ test's expected text, reason, violated field), copied
# from parameters_test.cc's ValidateTest.
VALIDATE_CASES = [
    ("Wait", "",
     "parameter 'duration_s' is required: How long to wait, in seconds of the behavior's clock.",
     INVALID, "duration_s"),
    ("Wait", "duration_s: -1", "parameter 'duration_s' = -1 is out of range [0, 86400]",
     OUT_OF_RANGE, "duration_s"),
    ("Wait", "duration_s: 86400.5",
     "parameter 'duration_s' = 86400.5 is out of range [0, 86400]", OUT_OF_RANGE, "duration_s"),
    ("AllKinds", "", "parameter 'duration_s' is required: How long.", INVALID, "duration_s"),
    ("AllKinds", "duration_s: 1 count: 11", "parameter 'count' = 11 is out of range [0, 10]",
     OUT_OF_RANGE, "count"),
    ("AllKinds", "duration_s: -1", "parameter 'duration_s' = -1 is out of range [0, +inf)",
     OUT_OF_RANGE, "duration_s"),
    ("AllKinds", "duration_s: 1 ids: [ 5, 0 ]", "parameter 'ids[1]' = 0 is out of range [1, 99]",
     OUT_OF_RANGE, "ids[1]"),
    ("AllKinds", "duration_s: 1 gains: [ 11 ]",
     "parameter 'gains[0]' = 11 is out of range (-inf, 10]", OUT_OF_RANGE, "gains[0]"),
    ("AllKinds", "duration_s: 1 ratio: 1.5", "parameter 'ratio' = 1.5 is out of range [0, 1]",
     OUT_OF_RANGE, "ratio"),
    ("AllKinds", "duration_s: 1 altitude_m: 121",
     "parameter 'altitude_m' = 121 is out of range [0, 120]", OUT_OF_RANGE, "altitude_m"),
    ("AllKinds", "duration_s: 1 path { waypoints { x_m: 1 } waypoints { x_m: 200 } }",
     "parameter 'path.waypoints[1].x_m' = 200 is out of range [-100, 100]", OUT_OF_RANGE,
     "path.waypoints[1].x_m"),
    ("Path", "waypoints { } waypoints { speed_m_s: 21 }",
     "parameter 'waypoints[1].speed_m_s' = 21 is out of range [0, 20]", OUT_OF_RANGE,
     "waypoints[1].speed_m_s"),
    ("AllKinds", 'duration_s: 1 limits { key: "a" value: -1 }',
     """parameter 'limits["a"]' = -1 is out of range [0, +inf)""", OUT_OF_RANGE, 'limits["a"]'),
    ("AllKinds", "duration_s: 1 stops { key: 3 value { x_m: -101 } }",
     "parameter 'stops[3].x_m' = -101 is out of range [-100, 100]", OUT_OF_RANGE, "stops[3].x_m"),
    ("Strict", "", "parameter 'level' = 0 is out of range [1, 5]", OUT_OF_RANGE, "level"),
    ("AllKinds", "duration_s: 0", "parameter 'duration_s' is required", INVALID, "duration_s"),
    ("AllKinds", "duration_s: 1 gains: [ 1, nan ]",
     "parameter 'gains[1]' = NaN is not a finite", INVALID, "gains[1]"),
    ("AllKinds", "duration_s: 1 ratio: inf", "parameter 'ratio' = Infinity is not a finite",
     INVALID, "ratio"),
    ("AllKinds", "duration_s: 1 target { y_m: nan }", "parameter 'target.y_m' = NaN", INVALID,
     "target.y_m"),
    ("Wait", "duration_s: -inf", "= -Infinity is not a finite number", INVALID, "duration_s"),
]


def expect_parameter_error(error, expected, reason, field):
    assert error.code == grpc.StatusCode.INVALID_ARGUMENT, error
    assert expected in error.message
    assert error.reason == reason
    assert error.field_violations == [(field, error.message)]
    info = error.to_rpc_status()
    assert info.code == grpc.StatusCode.INVALID_ARGUMENT.value[0]


@pytest.mark.parametrize("name, text, expected, reason, field", FROM_STRUCT_CASES)
def test_from_struct_refusals_match_the_cpp_tests(test_protos, name, text, expected, reason,
                                                  field):
    with pytest.raises(StatusError) as caught:
        from_struct(struct_of(text), message_class(test_protos, name))
    expect_parameter_error(caught.value, expected, reason, field)


@pytest.mark.parametrize("name, text, expected, reason, field", VALIDATE_CASES)
def test_validation_refusals_match_the_cpp_tests(test_protos, name, text, expected, reason,
                                                 field):
    message = text_format.Parse(text, message_class(test_protos, name)())
    with pytest.raises(StatusError) as caught:
        apply_defaults_and_validate(message)
    expect_parameter_error(caught.value, expected, reason, field)


@pytest.mark.parametrize("text, expected", [
    ('{"goal_yaw_rad": 1, "goal_name": "home"}',
     "parameters 'goal_name' and 'goal_yaw_rad' are alternatives (oneof goal); set only one"),
    ('{"camelCaseName": "b", "camel_case_name": "a"}',
     "parameter 'camel_case_name' is given twice, as 'camelCaseName' and as 'camel_case_name'"),
    ('{"zz": 1, "count": "x", "aa": 1}', "unknown parameter 'aa'"),
])
def test_the_error_reported_does_not_depend_on_the_key_order(test_protos, text, expected):
    # parameters.cc reads a Struct's keys sorted, as these inputs' reversed orders show.
    with pytest.raises(StatusError) as caught:
        from_struct(struct_of(text), test_protos.AllKinds)
    assert caught.value.message.startswith(expected)


def test_defaults_are_applied_and_set_values_kept(test_protos):
    wait = from_struct({"durationS": 2.5}, WaitParameters)  # JSON names are accepted
    apply_defaults_and_validate(wait)
    assert wait.duration_s == 2.5
    kinds = text_format.Parse("duration_s: 1 path { waypoints { x_m: 1 } waypoints "
                              "{ speed_m_s: 0 } }", test_protos.AllKinds())
    apply_defaults_and_validate(kinds)
    assert (kinds.count, kinds.enabled, kinds.mode) == (3, True, test_protos.MEDIUM)
    assert kinds.HasField("altitude_m") and kinds.altitude_m == 1.5
    assert not kinds.HasField("retries"), "no default: stays unset"
    assert kinds.path.frame == "map"
    assert [w.speed_m_s for w in kinds.path.waypoints] == [2.5, 0]
    assert not kinds.HasField("target"), "unset nested messages are not created"
    kept = text_format.Parse("duration_s: 1 count: 9 altitude_m: 0", test_protos.AllKinds())
    apply_defaults_and_validate(kept)
    assert (kept.count, kept.altitude_m) == (9, 0)
    choice = test_protos.Choice(b="x")
    apply_defaults_and_validate(choice)
    assert choice.WhichOneof("pick") == "b", "a default does not displace the caller's choice"


def test_a_default_that_does_not_fit_is_a_schema_error(test_protos):
    with pytest.raises(StatusError) as caught:
        apply_defaults_and_validate(test_protos.BadDefault())
    assert caught.value.code == grpc.StatusCode.INTERNAL
    assert "schema error in behaviorlib.test.BadDefault.n" in caught.value.message
    assert "expected an integer" in caught.value.message


def test_from_struct_reads_every_kind(test_protos):
    kinds = from_struct(struct_of(
        '{"count": 7, "big": -4611686018427387904, "small_u": 4294967295, "big_u": 1e19, '
        '"s32": -3, "f64": 12, "ratio": 0.1, "name": "h\u00e9llo", "blob": "aGVsbG8=", '
        '"chunks": ["AAE=", "_-8"], "mode": 1, "modes": ["SLOW", 1], "limits": {"a": 1.5}, '
        '"stops": {"3": {"x_m": 4}}, "goal_name": "home", "target": {}}'), test_protos.AllKinds)
    assert (kinds.count, kinds.big, kinds.small_u) == (7, -4611686018427387904, 4294967295)
    assert (kinds.big_u, kinds.s32, kinds.f64) == (10000000000000000000, -3, 12)
    assert kinds.name == "h\u00e9llo" and kinds.blob == b"hello"
    assert list(kinds.chunks) == [b"\x00\x01", b"\xff\xef"]
    assert kinds.mode == test_protos.MEDIUM
    assert list(kinds.modes) == [test_protos.SLOW, test_protos.MEDIUM]
    assert dict(kinds.limits) == {"a": 1.5} and kinds.stops[3].x_m == 4
    assert kinds.goal_name == "home" and kinds.HasField("target")
    long = StatusError  # the long string case of FromStructTest.LongStringsAreCutInMessages
    with pytest.raises(long) as caught:
        from_struct({"duration_s": "x" * 500}, WaitParameters)
    assert len(caught.value.message) < 200 and '"...' in caught.value.message


def test_non_finite_numbers_are_refused_from_a_struct():
    for value, text in [(math.nan, "NaN"), (math.inf, "Infinity")]:
        values = struct_pb2.Struct()
        values.fields["duration_s"].number_value = value
        with pytest.raises(StatusError, match=f"parameter 'duration_s': {text} is not a finite"):
            from_struct(values, WaitParameters)


def test_to_struct_round_trips(test_protos):
    original = text_format.Parse("""
        count: 4 big: -12345678901 small_u: 7 big_u: 123456789012 s32: -5 f64: 99 ratio: 0.25
        duration_s: 12.5 enabled: true name: "n" blob: "\\x00\\xff" mode: MEDIUM
        target { x_m: 1 y_m: 2 speed_m_s: 0 } path { waypoints { x_m: 1 } frame: "map" }
        ids: [3, 4] gains: [0.5, -1] tags: ["a", ""] modes: [MEDIUM, SLOW] flags: [false, true]
        chunks: ["x", ""] altitude_m: 0 retries: 2 tree { label: "root" children { label: "l" } }
        goal_yaw_rad: 0.5 limits { key: "a" value: 1 } stops { key: 3 value { x_m: 5 } }
        camel_case_name: "c" """, test_protos.AllKinds())
    values = to_struct(original)
    assert values.fields["ratio"].number_value == 0.25
    assert values.fields["blob"].string_value == "AP8="
    assert values.fields["mode"].string_value == "MEDIUM"
    assert values.fields["retries"].number_value == 2
    assert "speed_m_s" in values.fields["target"].struct_value.fields, "explicit zero is set"
    assert from_struct(values, test_protos.AllKinds) == original
    float_tenth = test_protos.AllKinds(ratio=0.1)
    assert to_struct(float_tenth).fields["ratio"].number_value == 0.1, "not 0.10000000149011612"


def test_merge_update_replaces_set_fields_and_keeps_others(test_protos):
    current = text_format.Parse("""
        count: 5 name: "x" ids: [1, 2] altitude_m: 3 goal_yaw_rad: 1 target { x_m: 1 y_m: 2 }
        path { waypoints { x_m: 1 } frame: "map" } limits { key: "a" value: 1 }
        limits { key: "b" value: 2 } modes: [SLOW] chunks: ["c"]""", test_protos.AllKinds())
    update = text_format.Parse("""
        ids: [9] altitude_m: 0 goal_name: "home" target { y_m: 7 } path { frame: "odom" }
        limits { key: "c" value: 3 } mode: MEDIUM""", test_protos.AllKinds())
    merge_update(update, current)
    expected = text_format.Parse("""
        count: 5 name: "x" ids: [9] altitude_m: 0 goal_name: "home" target { x_m: 1 y_m: 7 }
        path { waypoints { x_m: 1 } frame: "odom" } limits { key: "c" value: 3 } modes: [SLOW]
        chunks: ["c"] mode: MEDIUM""", test_protos.AllKinds())
    assert current == expected


def test_describe_gives_the_schema_of_a_parameter_message(test_protos):
    out = behavior_pb2.BehaviorDescription().parameters
    describe(WaitParameters.DESCRIPTOR, out)
    [duration] = out
    assert (duration.name, duration.type, duration.proto_type, duration.unit) == (
        "duration_s", "number", "double", "s")
    assert duration.value_type == behavior_pb2.PARAMETER_TYPE_NUMBER
    assert (duration.range.min, duration.range.max, duration.required) == (0, 86400, True)
    assert duration.description == "How long to wait, in seconds of the behavior's clock."
    kinds = behavior_pb2.BehaviorDescription().parameters
    describe(test_protos.AllKinds.DESCRIPTOR, kinds)
    by_name = {s.name: s for s in kinds}
    assert by_name["stops"].proto_type == "map<int32, behaviorlib.test.Waypoint>"
    assert list(by_name["modes"].enum_values) == ["SLOW", "MEDIUM"]
    assert by_name["target"].fields[2].unit == "m/s"
    assert [f.name for f in by_name["tree"].fields] == ["label", "children"]
    assert not by_name["tree"].fields[1].fields, "a recursive type is described once"
    chain = behavior_pb2.BehaviorDescription().parameters
    describe(test_protos.L1.DESCRIPTOR, chain)
    depth = 0
    while chain:
        depth += 1
        chain = chain[0].fields
    assert depth == 8


@pytest.mark.parametrize("name, unit", [
    ("duration_s", "s"), ("timeout_ms", "ms"), ("speed_m_s", "m/s"), ("accel_m_s2", "m/s^2"),
    ("yaw_rate_rad_s", "rad/s"), ("rate_hz", "Hz"), ("battery_percent", "%"),
    ("quadratic_drag_n_s2_m2", "N s^2/m^2"), ("items", ""), ("_s", ""), ("", "")])
def test_units_come_from_the_field_name(name, unit):
    assert unit_of_field_name(name) == unit


@pytest.mark.parametrize("value, text", [
    (0.2, "0.2"), (30.0, "30"), (1e-06, "1e-06"), (3e9, "3000000000"), (1e40, "1e+40"),
    (0.0001, "1e-04"), (0.001, "0.001"), (-2.5, "-2.5"), (math.nan, "NaN"),
    (-math.inf, "-Infinity")])
def test_numbers_print_as_cpp_to_chars_prints_them(value, text):
    assert number_text(value) == text


def test_a_refusal_carries_its_details_as_a_server_sends_them():
    error = (StatusError(grpc.StatusCode.INVALID_ARGUMENT, "parameter 'x': bad",
                         reason=errors_pb2.PARAMETER_INVALID, field_violations=[("x", "bad")])
             .prefix_field_violations("parameters.").with_reason("PARAMETER_OUT_OF_RANGE",
                                                                  {"behavior": "WAIT"}))
    status = error.to_rpc_status()
    assert (status.code, status.message) == (3, "parameter 'x': bad")
    info = error_details_pb2.ErrorInfo()
    assert status.details[0].Unpack(info)
    assert (info.reason, info.domain, dict(info.metadata)) == (
        "PARAMETER_OUT_OF_RANGE", "behaviorlib.v1", {"behavior": "WAIT"})
    bad = error_details_pb2.BadRequest()
    assert status.details[1].Unpack(bad)
    assert [(v.field, v.description) for v in bad.field_violations] == [("parameters.x", "bad")]
    [(key, value)] = error.trailing_metadata()
    assert key == "grpc-status-details-bin" and value == status.SerializeToString()
    plain = StatusError(grpc.StatusCode.INVALID_ARGUMENT, "no details")
    assert plain.error_info().reason == "INVALID_REQUEST", "the C++ default for the code"
    assert StatusError(grpc.StatusCode.ABORTED, "x").error_info().reason == (
        "ERROR_REASON_UNSPECIFIED")
    assert plain.bad_request() is None


def test_a_future_answers_a_lifecycle_call(harness):
    h = harness()
    future = h.engine.activate(wait_params(1))
    assert isinstance(future, concurrent.futures.Future)
    assert future.result(WAIT_S).activation_id
    assert json.loads(json_format.MessageToJson(h.engine.check_activation()))["active"]
