"""The engine of a Python behavior: a port of
services/behaviorlib/core/behavior_execution_manager.{h,cc} (the contract of decision 1), with
the resumable event log of event_log.{h,cc} and resumable_log.{h,cc}.

A behavior's author derives from Behavior, names its parameter message, and overrides the
paper's functions:

    class Wait(Behavior):
        Parameters = basic_quadrotor_behaviors_pb2.WaitParameters   # declares "WAIT"

        def check_goal(self):
            if self.active_time() >= seconds(self.parameters.duration_s):
                return Verdict.finish("waited")
            return Verdict.keep_going()

A host wraps each behavior in an ExecutionManager, which runs it:

    events = EventLog(robot_id="drone1", system="python_behaviors")
    engine = ExecutionManager(Wait())
    engine.start(BehaviorContext(clock=SteadyClock(), events=events, robot_id="drone1"))
    engine.activate_and_wait(WaitParameters(duration_s=3))
    engine.stop()

Threading. Every user function of one behavior runs on that behavior's worker thread, one at a
time, so user code needs no lock for its own state. Lifecycle calls (activate, deactivate,
pause, resume, modify, check_situation) may come from any thread: they are queued to the worker
and return a concurrent.futures.Future (the *_and_wait forms wait for it). Data from other
threads reaches the behavior through on_worker(): its handler runs on the worker, between ticks.

The tick, while active, at the behavior's frequency on the injected clock, runs in this order:
  1. check_processes()  -> PROCESS_FAILURE
  2. check_situation()  -> SITUATION_CHANGE
  3. check_goal()       -> GOAL_ACHIEVED
  4. check_progress()   -> WRONG_PROGRESS
  5. maximum_execution_time (active time only; paused time does not count) -> TIME_OUT
  6. on_execute()
The first check that reports ends the activation with its cause: on_deactivate() runs, then the
finished event is emitted. An exception from any user function of an activation ends it with
PROCESS_FAILURE, the message naming the function and the exception. Activation wakes the
worker at once: the first tick follows on_activate immediately, without waiting for the clock.

The watchdog. A user function of a running activation that does not return within the
behavior's watchdog_timeout (wall time) ends the activation with PROCESS_FAILURE, and the
behavior is BLOCKED until the stuck call returns, as in C++: activation, deactivation, pause,
resume, modify and check_situation are refused with BEHAVIOR_BLOCKED (a deactivation naming the
finished activation is answered already_finished). A Python thread cannot be stopped, so the
stuck worker is abandoned: a new worker thread takes over at once and answers the call that was
waiting on the stuck function, but runs no user code of the behavior while it is BLOCKED. When
the stuck function returns, its own thread runs on_deactivate() (unless that was the stuck
function), the behavior is INACTIVE again, and that thread ends. Calls are thus never answered
with the behavior's code running twice at once. A thread stuck forever costs its stack until the
process ends (the threads are daemon threads). As in C++, functions that run while no
activation does (on_configure, the check_situation and on_activate of an activation that is
being decided) are not watched: a caller waiting on one gets BEHAVIOR_UNRESPONSIVE from the
*_and_wait forms.

Refusals raise (or set on the Future) parameters.StatusError with the C++ codes, messages and
ErrorInfo reasons: BEHAVIOR_ALREADY_ACTIVE, SITUATION_NOT_SUITABLE, BEHAVIOR_NOT_ACTIVE,
ACTIVATION_MISMATCH, BEHAVIOR_ALREADY_PAUSED, BEHAVIOR_NOT_PAUSED, BEHAVIOR_FAILED,
CLOCK_NOT_READY, SHUTTING_DOWN, BEHAVIOR_UNRESPONSIVE, BEHAVIOR_BLOCKED, PARAMETER_INVALID,
PARAMETER_OUT_OF_RANGE and INVALID_REQUEST.

Function names in messages are the Python ones ("on_execute threw: ZeroDivisionError: division
by zero", "check_goal did not return within 0.2 s (watchdog); ..."), where C++ writes
"onExecute threw: ...".
"""

import collections
import concurrent.futures
import dataclasses
import enum
import math
import secrets
import threading
import time

import grpc
from google.protobuf import duration_pb2, empty_pb2, timestamp_pb2

from behaviorlib.v1 import behavior_pb2, errors_pb2, options_pb2

from .clock import ClockListener, to_seconds
from .parameters import StatusError, apply_defaults_and_validate, merge_update, to_struct

_INACTIVE = behavior_pb2.BEHAVIOR_STATE_INACTIVE
_ACTIVE = behavior_pb2.BEHAVIOR_STATE_ACTIVE
_PAUSED = behavior_pb2.BEHAVIOR_STATE_PAUSED
_BLOCKED = behavior_pb2.BEHAVIOR_STATE_BLOCKED

_UNSPECIFIED = behavior_pb2.TERMINATION_CAUSE_UNSPECIFIED
_GOAL_ACHIEVED = behavior_pb2.TERMINATION_CAUSE_GOAL_ACHIEVED
_TIME_OUT = behavior_pb2.TERMINATION_CAUSE_TIME_OUT
_WRONG_PROGRESS = behavior_pb2.TERMINATION_CAUSE_WRONG_PROGRESS
_SITUATION_CHANGE = behavior_pb2.TERMINATION_CAUSE_SITUATION_CHANGE
_PROCESS_FAILURE = behavior_pb2.TERMINATION_CAUSE_PROCESS_FAILURE
_INTERRUPTED = behavior_pb2.TERMINATION_CAUSE_INTERRUPTED

_NANOS = 1_000_000_000


# ---- What the paper's functions return --------------------------------------------------------

class Situation:
    """check_situation()'s answer: do the behavior's assumptions hold, and how well would it
    perform. `reasons` say why in words (mostly why it is not feasible); `codes` are the same
    reasons as errors_pb2.SituationReason values, in the same order (a reason without a code
    reads as SITUATION_REASON_UNSPECIFIED)."""

    __slots__ = ("feasible", "performance_ratio", "reasons", "codes")

    def __init__(self, feasible=True, performance_ratio=1.0, reasons=None, codes=None):
        self.feasible = feasible
        self.performance_ratio = performance_ratio
        self.reasons = list(reasons or [])
        self.codes = list(codes or [])

    @staticmethod
    def ok(performance_ratio=1.0):
        return Situation(True, performance_ratio)

    @staticmethod
    def infeasible(code, reason):
        return Situation(False, 0.0, [reason], [code])

    def add(self, code, reason):
        """Adds a reason with its code (feasibility and ratio are left alone)."""
        self.codes.extend([errors_pb2.SITUATION_REASON_UNSPECIFIED] *
                          (len(self.reasons) - len(self.codes)))
        self.reasons.append(reason)
        self.codes.append(code)

    def code(self, i):
        """The code of reasons[i]."""
        return self.codes[i] if i < len(self.codes) else errors_pb2.SITUATION_REASON_UNSPECIFIED


class Verdict:
    """The answer of check_goal(), check_progress() and check_processes(): keep going, or
    finish the activation with that function's termination cause and say why."""

    __slots__ = ("finishes", "message")

    def __init__(self, finishes, message):
        self.finishes = finishes
        self.message = message

    @staticmethod
    def keep_going():
        return _KEEP_GOING

    @staticmethod
    def finish(message):
        return Verdict(True, message)


_KEEP_GOING = Verdict(False, "")


@dataclasses.dataclass
class BehaviorOptions:
    """Execution settings. Times are int nanoseconds (clock.seconds() makes them)."""
    # Ticks per second of the behavior's clock while active; in (0, 10000].
    frequency_hz: float = 100.0
    # Maximum active time before TIME_OUT; 0 means none.
    maximum_execution_time: int = 0
    # Wall time a user function of an activation may run before it ends with PROCESS_FAILURE.
    watchdog_timeout: int = _NANOS
    # A change of the performance ratio at least this large, while active, emits a
    # situation-changed event.
    situation_report_threshold: float = 0.1


class BehaviorObserver:
    """Receives the measurements the engine makes (Prometheus in servers). Called on the
    behavior's worker (on_blocked also on the watchdog's thread); must be cheap and must not
    block. Durations are int nanoseconds of wall (or thread CPU) time."""

    def on_activated(self, activate_call):
        """An activation succeeded, `activate_call` after the request arrived."""

    def on_first_execute(self, activation_latency):
        """The first on_execute ran, `activation_latency` after the request arrived (t3)."""

    def on_finished(self, cause):
        """An activation finished with `cause`."""

    def on_monitoring(self, wall, cpu):
        """One tick's four monitoring functions took `wall` time and `cpu` thread time (t1)."""

    def on_situation(self, performance_ratio):
        """A situation-changed event was emitted."""

    def on_blocked(self, blocked):
        """The watchdog abandoned a stuck function (True); an abandoned function returned
        (False)."""


class Delivery(enum.Enum):
    """How samples handed to a behavior's worker wait (Behavior.on_worker())."""
    # Only the newest undelivered sample waits (a pose, an image): a busy worker skips stale ones.
    LATEST = 1
    # Every sample, in order (an IMU stream, messages), up to a capacity; beyond it the oldest
    # waiting sample is dropped and counted.
    EVERY = 2


@dataclasses.dataclass
class BehaviorContext:
    """What the hosting system gives a behavior when it starts."""
    clock: object = None
    events: object = None  # an EventLog
    observer: BehaviorObserver = None
    robot_id: str = ""
    # The behavior's configuration, a message of its Configuration type (the system decodes its
    # section of the --config file into it); None gives the type's defaults.
    configuration: object = None
    # Called on the worker with True/False when the behavior becomes active or inactive.
    on_active_changed: object = None
    # Called on the worker before each command runs; may block until the command may run at the
    # current time (the deterministic mode's time gate). While a command waits there the
    # behavior counts as caught up but not idle.
    before_command: object = None


# ---- Helpers ------------------------------------------------------------------------------------

def cause_name(cause):
    """A TerminationCause's short name ("GOAL_ACHIEVED")."""
    name = behavior_pb2.TerminationCause.Name(cause)
    prefix = "TERMINATION_CAUSE_"
    return name[len(prefix):] if name.startswith(prefix) else name


def declared_behavior_name(message_class):
    """The name of the behavior that `message_class` declares with the (behaviorlib.v1.declare)
    option, or "" when it declares none."""
    message_options = message_class.DESCRIPTOR.GetOptions()
    if not message_options.HasExtension(options_pb2.declare):
        return ""
    return message_options.Extensions[options_pb2.declare].name


def parameter_error(error, behavior):
    """A parameter refusal of validation as the engine reports it: field violations under
    "parameters.", reason PARAMETER_INVALID unless a finer one is set, and the behavior."""
    return error.prefix_field_violations("parameters.").with_default_reason(
        errors_pb2.PARAMETER_INVALID, {"behavior": behavior})


def _seconds_text(ns):
    """A duration as C++ writes a double of seconds to a stream: "0.2 s", "1 s", "1e+06 s"."""
    return f"{to_seconds(ns):g} s"


def _timestamp(ns):
    stamp = timestamp_pb2.Timestamp()
    stamp.FromNanoseconds(ns)
    return stamp


def _duration(ns):
    duration = duration_pb2.Duration()
    duration.FromNanoseconds(ns)
    return duration


def _join_reasons(reasons):
    return "; ".join(reasons) if reasons else "no reason given"


def _code_names(situation):
    """The situation's codes, comma-separated (ErrorInfo metadata)."""
    return ",".join(errors_pb2.SituationReason.Name(situation.code(i))
                    for i in range(len(situation.reasons)))


def _add_reasons(situation, out):
    for i, reason in enumerate(situation.reasons):
        out.reasons.append(reason)
        out.reason_codes.append(situation.code(i))


def _exception_text(error):
    text = str(error)
    return f"{type(error).__name__}: {text}" if text else type(error).__name__


def _verdict(value, function):
    if not isinstance(value, Verdict):
        raise TypeError(f"{function} returned {type(value).__name__}, not a Verdict")
    return value


def _situation(value, function="check_situation"):
    if not isinstance(value, Situation):
        raise TypeError(f"{function} returned {type(value).__name__}, not a Situation")
    return value


def _error(code, message, reason, metadata):
    return StatusError(code, message, reason=reason, metadata=metadata)


# ---- The event log (event_log.h, resumable_log.h) ------------------------------------------------

def new_incarnation_id():
    """A fresh random 128-bit id as 32 lowercase hex digits."""
    return secrets.token_hex(16)


_KEEP_FOREVER = math.inf


class _WakeSlot:
    """The wake callback of one subscription. Its lock is held while the callback runs and by
    cancel(), so that no wake runs once cancel() has returned; being reentrant, it lets a
    callback cancel its own subscription or append again on its own thread."""

    def __init__(self, wake):
        self._lock = threading.RLock()
        self._wake = wake
        self._cancelled = False

    def fire(self):
        with self._lock:
            if not self._cancelled and self._wake is not None:
                self._wake()

    def cancel(self):
        with self._lock:
            self._cancelled = True


class Subscription:
    """One subscriber's view of an EventLog: `start` (the WatchEventsStart that says what the
    replay covers), then a queue of events. Thread-safe. The events are the log's own messages:
    read them, do not change them."""

    def __init__(self, log, start, behaviors, limit, wake):
        self.start = start
        self._behaviors = frozenset(behaviors)
        self._limit = limit
        self._wake = _WakeSlot(wake)
        self._lock = threading.Lock()
        self._queue = collections.deque()
        self._replay_left = 0
        self._overflowed = False
        self._cancelled = False
        self._last_popped_seq = 0
        self._log = log

    def _matches(self, event):
        return not self._behaviors or event.behavior in self._behaviors

    def pop(self):
        """The next queued event, or None."""
        events = self.pop_up_to(1)
        return events[0] if events else None

    def pop_up_to(self, max_events):
        """Up to `max_events` queued events, oldest first."""
        with self._lock:
            out = []
            while len(out) < max_events and self._queue:
                out.append(self._queue.popleft())
            self._replay_left -= min(self._replay_left, len(out))
            if out:
                self._last_popped_seq = out[-1].seq
            return out

    def overflowed(self):
        """True once the queue overflowed; nothing more is delivered (resume with since_seq)."""
        with self._lock:
            return self._overflowed

    def last_popped_seq(self):
        """Seq of the last event handed out, or the since_seq the subscription started from: a
        valid resume point."""
        with self._lock:
            return self._last_popped_seq

    def cancel(self):
        """Stops delivery; the wake callback is not called after this returns (it waits for a
        wake running on another thread). May be called from inside the wake."""
        with self._lock:
            self._cancelled = True
            log, self._log = self._log, None
        if log is not None:
            log._unsubscribe(self)
        self._wake.cancel()

    def _deliver(self, event):
        """Under the log's lock: queues `event`; returns whether to wake the subscriber."""
        if not self._matches(event):
            return False
        with self._lock:
            if self._cancelled or self._overflowed:
                return False
            if len(self._queue) - self._replay_left >= self._limit:
                # Keep what is queued so that the reader drains it and resumes after the last
                # event it got; wake it once so that it notices even when idle.
                self._overflowed = True
                return True
            was_empty = not self._queue
            self._queue.append(event)
            return was_empty


class EventLog:
    """The per-process log of behavior lifecycle events with resumable subscriptions
    (BehaviorSystem.WatchEvents). Events are numbered 1, 2, 3... per log; each log has a new
    random incarnation, so a subscriber resuming with a seq of another run is told and replayed
    from the start. At most `capacity` events are kept (oldest evicted first), and an event only
    until `retention` nanoseconds (on `wall_now`, monotonic by default) after its activation
    finished (an event of no activation: after it was appended). A subscriber whose undelivered
    live events exceed `subscriber_queue_limit` is marked overflowed and gets nothing more, so
    appending never waits for a subscriber."""

    def __init__(self, robot_id="", system="", *, capacity=2048, retention=600 * _NANOS,
                 subscriber_queue_limit=4096, incarnation="", wall_now=time.monotonic_ns):
        self.robot_id = robot_id
        self.system = system
        self.incarnation = incarnation or new_incarnation_id()
        self._capacity = capacity
        self._retention = retention
        self._queue_limit = max(1, subscriber_queue_limit)
        self._wall_now = wall_now
        self._lock = threading.Lock()
        self._next_seq = 1
        self._retained = collections.deque()  # [event, expires_at], seqs consecutive
        self._subscribers = []

    def _expiry(self, now):
        return now + self._retention

    def append(self, event):
        """Appends `event` (the log takes it): fills seq, incarnation, robot_id, system and
        wall_time, retains it and queues it for every matching subscriber, whose wake runs after
        the log's lock is released. A finished event starts the retention countdown of its
        activation's events. Returns the stored event."""
        to_wake = []
        with self._lock:
            now = self._wall_now()
            event.robot_id = self.robot_id
            event.system = self.system
            event.incarnation = self.incarnation
            event.wall_time.FromNanoseconds(time.time_ns())
            event.seq = self._next_seq
            self._next_seq += 1
            if not event.activation_id:
                expires_at = self._expiry(now)  # no finished event would release it
            elif not event.HasField("finished"):
                expires_at = _KEEP_FOREVER
            else:
                expires_at = self._expiry(now)
                for entry in self._retained:
                    # Events already counting down keep their expiry: a duplicate finished
                    # event cannot extend it.
                    older = entry[0]
                    if (entry[1] == _KEEP_FOREVER and older.activation_id == event.activation_id
                            and older.behavior == event.behavior):
                        entry[1] = expires_at
            self._retained.append([event, expires_at])
            self._evict_locked(now)
            for subscription in self._subscribers:
                if subscription._deliver(event):
                    to_wake.append(subscription._wake)
        for slot in to_wake:
            slot.fire()
        return event

    def _evict_locked(self, now):
        # From the front only, so that retained seqs stay consecutive.
        while self._retained and (len(self._retained) > self._capacity
                                  or self._retained[0][1] <= now):
            self._retained.popleft()

    def subscribe(self, since_seq=0, incarnation="", behaviors=(), wake=None):
        """A Subscription whose queue holds the retained events after `since_seq` (all retained
        ones if `incarnation` names another run), of `behaviors` (all when empty), then each new
        one. `wake` is called, never under a lock of the log, when the queue becomes non-empty
        or overflows; the replay is queued without a wake, so drain once after subscribing.
        A behavior's engine appends under its own lock, so `wake` must not block nor call into
        an ExecutionManager: it should only signal the thread that drains the queue."""
        start = behavior_pb2.WatchEventsStart(incarnation=self.incarnation)
        changed = bool(incarnation) and incarnation != self.incarnation
        start.incarnation_changed = changed
        # A since_seq of another run says nothing about this one.
        since = 0 if changed else since_seq
        with self._lock:
            subscription = Subscription(self, start, behaviors, self._queue_limit, wake)
            self._evict_locked(self._wall_now())
            latest = self._next_seq - 1
            oldest = self._retained[0][0].seq if self._retained else 0
            start.oldest_retained_seq = oldest
            start.latest_seq = latest
            # Retained seqs are consecutive, so the gap before the oldest is exactly the loss.
            dropped = 0
            if self._retained:
                if since + 1 < oldest:
                    dropped = oldest - since - 1
            elif latest > since:
                dropped = latest - since
            start.events_dropped = dropped > 0
            start.dropped_count = dropped
            first = max(0, since + 1 - oldest) if self._retained else 0
            for index in range(first, len(self._retained)):
                event = self._retained[index][0]
                if subscription._matches(event):
                    subscription._queue.append(event)
            subscription._replay_left = len(subscription._queue)
            subscription._last_popped_seq = min(since, latest)
            self._subscribers.append(subscription)
        return subscription

    def _unsubscribe(self, subscription):
        with self._lock:
            self._subscribers = [s for s in self._subscribers if s is not subscription]

    def latest_seq(self):
        """Seq of the newest event (0 if none)."""
        with self._lock:
            return self._next_seq - 1

    def retained_count(self):
        """Number of retained events, as a subscriber would see them now."""
        with self._lock:
            now = self._wall_now()
            expired = 0
            while expired < len(self._retained) and self._retained[expired][1] <= now:
                expired += 1
            return len(self._retained) - expired


# ---- The behavior ------------------------------------------------------------------------------

class Behavior:
    """What a behavior's author derives from. Set `Parameters` to the parameter message class
    (its (behaviorlib.v1.declare) option names the behavior) and, for settings of its own,
    `Configuration` to a configuration message class; override the paper's functions. The
    helpers (parameters, active_time(), clock, ...) are for those functions, on the worker."""

    Parameters = None
    Configuration = empty_pb2.Empty

    def __init__(self, name=None, options=None):
        """`name` defaults to the name Parameters declares; a behavior named here (a test
        borrowing WAIT's parameters) is served only through the generic BehaviorSystem service.
        `options` are the execution settings (BehaviorOptions)."""
        if self.Parameters is None:
            raise TypeError(f"{type(self).__name__} sets no Parameters message class")
        if name is None:
            name = declared_behavior_name(self.Parameters)
            if not name:
                raise ValueError(f"{self.Parameters.DESCRIPTOR.full_name} declares no behavior: "
                                 "give it option (behaviorlib.v1.declare), or name the behavior "
                                 "in its constructor")
        self._name = name
        self._initial_options = dataclasses.replace(options or BehaviorOptions())
        self._engine = None

    @property
    def name(self):
        return self._name

    # ---- Activation management (the paper's table) ----

    def on_configure(self, config):
        """Reads the behavior's configuration (a Configuration message, defaults applied and
        checked) once, on the worker, before any activation. Raise StatusError (or anything) to
        stop the system at start."""

    def on_activate(self):
        """Prepares an activation; `parameters` are set. Raise StatusError to refuse it with
        its code; any other exception refuses it with INTERNAL."""

    def on_execute(self):
        """One step of the behavior's control."""

    def on_deactivate(self):
        """Leaves a safe, stable state; releases what on_activate acquired."""

    # ---- Execution monitoring (the paper's table) ----

    def check_situation(self):
        """Do the behavior's assumptions hold now (a Situation)?"""
        return Situation.ok()

    def check_goal(self):
        """A Verdict: finishing ends the activation with GOAL_ACHIEVED."""
        return _KEEP_GOING

    def check_progress(self):
        """A Verdict: finishing ends the activation with WRONG_PROGRESS."""
        return _KEEP_GOING

    def check_processes(self):
        """A Verdict: finishing ends the activation with PROCESS_FAILURE."""
        return _KEEP_GOING

    # ---- Beyond the paper ----

    def on_pause(self):
        """Paused: a motion behavior should hold position here."""

    def on_resume(self):
        """Resumed: ticks follow at once."""

    def on_modify(self, new_parameters):
        """`new_parameters` (the current ones with the update's set fields, defaults applied,
        validated) are about to take effect. Raise StatusError to refuse them (the current ones
        stay); any other exception ends the activation with PROCESS_FAILURE."""

    # ---- Helpers (worker thread) ----

    def _held(self):
        if self._engine is None:
            raise RuntimeError(f"behavior {self._name}: no engine holds it yet (a helper was "
                               "called from its constructor; use on_configure)")
        return self._engine

    @property
    def clock(self):
        return self._held()._context.clock

    def now(self):
        """The behavior clock's time, int nanoseconds."""
        return self._held()._context.clock.now()

    def active_time(self):
        """Active (not paused) time of the current activation, int nanoseconds."""
        return self._held()._active_time()

    @property
    def parameters(self):
        """The current activation's parameters (defaults applied, validated). Read-only."""
        return self._held()._parameters

    @property
    def activation_id(self):
        return self._held()._activation_id

    @property
    def robot_id(self):
        return self._held()._context.robot_id

    @property
    def options(self):
        """The execution options in effect."""
        return self._held()._options

    def set_maximum_execution_time(self, duration, reason=""):
        """Overrides maximum_execution_time (int nanoseconds; 0: none) for the current
        activation, e.g. from its parameters in on_activate. `reason`, when not empty, is the
        TIME_OUT's message instead of the library's."""
        engine = self._held()
        engine._maximum_execution_time = duration
        engine._time_out_reason = reason

    def on_worker(self, handler, delivery=Delivery.EVERY, capacity=1024):
        """A callable that any thread may call with a sample (a channel reader, a helper
        thread, a future's done callback): `handler(sample)` then runs on this behavior's
        worker, between ticks, like every other user function, so behavior state needs no lock.
        The sample is handed over, not copied: the caller must not change it afterwards. Made
        during an activation, its samples still waiting when the activation ends are dropped;
        made outside one (on_configure), it delivers whenever. An exception from `handler` ends
        an activation with PROCESS_FAILURE. `capacity` bounds the waiting samples of
        Delivery.EVERY."""
        engine = self._held()
        inbox = _Inbox(engine, handler, delivery, max(1, capacity), engine._inbox_generation())
        return inbox.push


class _Inbox:
    """Samples waiting for one on_worker() handler: any thread pushes, the worker drains."""

    def __init__(self, engine, handler, delivery, capacity, generation):
        self._engine = engine
        self._handler = handler
        self._delivery = delivery
        self._capacity = capacity
        self.generation = generation
        self._lock = threading.Lock()
        self._waiting = collections.deque()
        self._scheduled = False
        self.dropped = 0

    def push(self, sample):
        with self._lock:
            if self._delivery is Delivery.LATEST:
                self._waiting.clear()
            elif len(self._waiting) >= self._capacity:
                self._waiting.popleft()
                self.dropped += 1
            self._waiting.append(sample)
            schedule = not self._scheduled
            self._scheduled = True
        if schedule:
            self._engine._schedule(self)

    def _take(self):
        with self._lock:
            self._scheduled = False
            samples = list(self._waiting)
            self._waiting.clear()
            return samples

    def drain(self):
        for sample in self._take():
            self._handler(sample)

    def discard(self):
        self._take()


# ---- The engine ----------------------------------------------------------------------------------

class _Abandoned(BaseException):
    """Raised on an abandoned worker when its stuck user function returns: unwinds the worker,
    which then ends without touching the engine."""


class _Worker:
    """One worker thread and what caught_up()/idle() read of it."""
    __slots__ = ("thread", "retired", "ticking", "commanding", "gated")

    def __init__(self):
        self.thread = None
        self.retired = False
        self.ticking = False
        self.commanding = False
        self.gated = False


class _Call:
    """A user function running on a worker, for the watchdog. `abandoned` answers the caller
    waiting on it when the watchdog abandons it."""
    __slots__ = ("function", "started", "fired", "abandoned")

    def __init__(self, function, abandoned):
        self.function = function
        self.started = time.monotonic()
        self.fired = False
        self.abandoned = abandoned


class _Command:
    __slots__ = ("run", "cancel")

    def __init__(self, run, cancel):
        self.run = run
        self.cancel = cancel


class _WakeOnClock(ClockListener):
    """Wakes the worker when simulated or fake time moves (towards the next tick)."""

    def __init__(self, engine):
        self._engine = engine

    def on_clock_advanced(self):
        engine = self._engine
        if not engine._wants_ticks:
            return
        with engine._lock:
            engine._wakes += 1
            engine._wake.notify_all()


class ExecutionManager:
    """The engine of one behavior: it holds the behavior, runs its functions on the behavior's
    worker thread and serves the uniform lifecycle interface to the host. The lifecycle calls
    are thread-safe; those that run user code return a concurrent.futures.Future whose result is
    the response message, or whose exception is a StatusError. Callbacks added to the Future run
    on the worker: they must not wait for this behavior."""

    # How long request_ids are remembered for idempotent activation (seconds of wall time).
    REQUEST_ID_WINDOW_S = 600.0
    # How many finished activation ids are remembered (for Deactivate replies).
    FINISHED_REMEMBERED = 64

    def __init__(self, behavior):
        if not isinstance(behavior, Behavior):
            raise TypeError("an ExecutionManager needs a Behavior")
        if behavior._engine is not None:
            raise ValueError(f"behavior {behavior.name} is already held by an engine")
        behavior._engine = self
        self._behavior = behavior
        self._options = dataclasses.replace(behavior._initial_options)
        self._context = None
        self._configuration = None
        self._lock = threading.Lock()
        self._wake = threading.Condition(self._lock)  # the worker (and stop()) wait here
        self._watchdog_wake = threading.Condition(self._lock)
        self._commands = collections.deque()
        self._ready = collections.deque()  # inboxes with samples
        self._generation = 1
        self._stopping = False
        self._exited = False
        self._wakes = 0
        self._worker = None
        self._watchdog = None
        self._watchdog_stop = False
        self._clock_listener = None
        self._call = None  # the current worker's running user function
        # Activation state: written on the worker under the lock; read by the worker without.
        self._state = _INACTIVE
        self._activation_id = ""
        self._parameters = None
        self._activation_time = 0
        self._active_since = 0
        self._active_accumulated = 0
        self._maximum_execution_time = 0
        self._time_out_reason = ""
        self._next_tick = 0
        self._period = 0
        self._wants_ticks = False
        self._first_execute_pending = False
        self._activate_received = 0
        self._reported_performance = 1.0
        self._reported_reasons = []
        self._reported_codes = []
        self._activation_counter = 0
        self._request_ids = {}
        self._request_id_order = collections.deque()
        self._finished = collections.deque(maxlen=self.FINISHED_REMEMBERED)

    # ---- Identity ----

    @property
    def behavior(self):
        return self._behavior

    @property
    def name(self):
        return self._behavior.name

    @property
    def parameters_type(self):
        """The behavior's parameter message class."""
        return self._behavior.Parameters

    @property
    def configuration_type(self):
        return self._behavior.Configuration

    @property
    def options(self):
        """Options in effect (BehaviorOptions)."""
        return self._options

    # ---- Host interface ----

    def start(self, context, timeout=60.0):
        """Starts the worker and the watchdog and runs on_configure() on the worker. Raises
        StatusError when the context, the options or the configuration are refused, or when
        on_configure fails; the behavior then stays stopped."""
        if context.clock is None or context.events is None:
            raise StatusError(grpc.StatusCode.INVALID_ARGUMENT,
                              f"behavior {self.name} needs a clock and an event log")
        if not 0.0 < self._options.frequency_hz <= 10000.0:
            raise StatusError(grpc.StatusCode.INVALID_ARGUMENT,
                              f"configuration of {self.name}: frequency_hz must be in (0, 10000]")
        if self._options.watchdog_timeout <= 0:
            raise StatusError(grpc.StatusCode.INVALID_ARGUMENT,
                              f"configuration of {self.name}: watchdog_timeout_s must be positive")
        configuration = context.configuration
        if configuration is None:
            configuration = self._behavior.Configuration()
        elif configuration.DESCRIPTOR is not self._behavior.Configuration.DESCRIPTOR:
            raise StatusError(grpc.StatusCode.INVALID_ARGUMENT,
                              f"{self.name} takes a configuration of type "
                              f"{self._behavior.Configuration.DESCRIPTOR.full_name}")
        apply_defaults_and_validate(configuration)
        self._context = context
        self._configuration = configuration
        self._period = round(_NANOS / self._options.frequency_hz)
        self._clock_listener = _WakeOnClock(self)
        context.clock.add_listener(self._clock_listener)
        with self._lock:
            worker = self._new_worker_locked()
        worker.thread.start()
        self._watchdog = threading.Thread(target=self._watchdog_loop, daemon=True,
                                          name=f"behavior-{self.name}-watchdog")
        self._watchdog.start()

        future = concurrent.futures.Future()

        def configure():
            refusal = None

            def call(_):
                nonlocal refusal
                try:
                    self._behavior.on_configure(self._configuration)
                except StatusError as error:
                    refusal = error

            failure = self._guarded("on_configure", call)
            if failure is not None:
                future.set_exception(StatusError(grpc.StatusCode.INTERNAL, failure))
            elif refusal is not None:
                future.set_exception(refusal)
            else:
                future.set_result(None)

        self._post(configure, self._cancel_with(future))
        try:
            _wait(future, timeout)
        except StatusError:
            self.stop()
            raise

    def stop(self, timeout=3.0):
        """Ends a running activation with INTERRUPTED ("process shutting down"), emits its
        event and ends the worker; waits at most `timeout` seconds for a worker stuck in user
        code, then abandons it. Later calls are answered UNAVAILABLE (SHUTTING_DOWN)."""
        if self._worker is None:
            return

        def shut_down():
            if self._running():
                self._finish(_INTERRUPTED, "process shutting down", self._set_stopping)
            self._set_stopping()

        self._post(shut_down, None)
        left = []
        with self._lock:
            if not self._wake.wait_for(lambda: self._exited, timeout):
                # Stuck in user code: the process is going away; do not hang it.
                self._worker.retired = True
                if self._call is not None:
                    self._call.fired = True
                self._stopping = True
                self._exited = True
                left = list(self._commands)
                self._commands.clear()
            worker = self._worker
            self._watchdog_stop = True
            self._watchdog_wake.notify_all()
        for command in left:
            if command.cancel is not None:
                command.cancel()
        if not worker.retired:
            worker.thread.join()
        self._watchdog.join()
        self._context.clock.remove_listener(self._clock_listener)

    def watchdog_check(self, now=None):
        """Abandons the running user function of an activation if it has run longer than the
        watchdog timeout at `now` (time.monotonic() seconds; default: now). The engine's own
        watchdog thread calls it; tests may too."""
        now = time.monotonic() if now is None else now
        with self._lock:
            call = self._call
            limit = self._options.watchdog_timeout / _NANOS
            if (call is None or call.fired or now - call.started < limit or not self._running()
                    or self._exited):
                return
            call.fired = True
            self._call = None
            self._record_finished_locked(
                _PROCESS_FAILURE,
                f"{call.function} did not return within "
                f"{_seconds_text(self._options.watchdog_timeout)} (watchdog); {self.name} "
                "accepts activations again once it returns")
            self._state = _BLOCKED
            self._worker.retired = True
            worker = self._new_worker_locked()
            self._commands.appendleft(_Command(lambda: self._recover(call), None))
        if self._context.observer is not None:
            self._context.observer.on_blocked(True)
        worker.thread.start()

    # ---- Uniform interface ----

    def activate(self, parameters, request_id="", received=None):
        """Validates `parameters` (a Parameters message: defaults applied, ranges checked;
        INVALID_ARGUMENT naming the field under "parameters."), then on the worker: replays a
        known `request_id`; refuses when already active or the situation is infeasible; runs
        on_activate(); emits the activated event; answers an ActivateResponse; and runs the
        first tick at once. `received` (time.monotonic_ns()) is when the request arrived."""
        future = concurrent.futures.Future()
        if getattr(parameters, "DESCRIPTOR", None) is not self.parameters_type.DESCRIPTOR:
            future.set_exception(self._wrong_type())
            return future
        owned = self.parameters_type()
        owned.CopyFrom(parameters)
        try:
            apply_defaults_and_validate(owned)
        except StatusError as error:
            future.set_exception(parameter_error(error, self.name))
            return future
        received = time.monotonic_ns() if received is None else received
        if self._refused_while_blocked(future):
            return future
        self._post(lambda: self._do_activate(owned, request_id, received, future),
                   self._cancel_with(future))
        return future

    def deactivate(self, activation_id=""):
        """Ends the activation with INTERRUPTED. ABORTED when `activation_id` is set but is not
        the current activation, except a finished one while nothing else runs: success with
        already_finished and its cause."""
        future = concurrent.futures.Future()
        with self._lock:
            if self._state == _BLOCKED:
                known = [cause for finished_id, cause in self._finished
                         if activation_id and finished_id == activation_id]
                if known:
                    future.set_result(behavior_pb2.DeactivateResponse(
                        activation_id=activation_id, cause=known[-1], already_finished=True))
                else:
                    future.set_exception(self._blocked_error_locked())
                return future

        def run():
            response = error = None
            with self._lock:
                if not self._running() and activation_id:
                    for finished_id, cause in self._finished:
                        if finished_id == activation_id:
                            response = behavior_pb2.DeactivateResponse(
                                activation_id=activation_id, cause=cause, already_finished=True)
                if response is None:
                    error = self._check_activation_id_locked(activation_id, "deactivate")
                current = self._activation_id
            if response is not None or error is not None:
                _answer(future, response, error)
                return
            interrupted = behavior_pb2.DeactivateResponse(activation_id=current,
                                                          cause=_INTERRUPTED)
            self._finish(_INTERRUPTED, "deactivation requested",
                         lambda: future.set_result(interrupted))
            future.set_result(interrupted)

        self._post(run, self._cancel_with(future))
        return future

    def pause(self, activation_id=""):
        """Pauses the activation: no ticks, the active time stops; on_pause() runs."""
        future = concurrent.futures.Future()
        if self._refused_while_blocked(future):
            return future

        def run():
            with self._lock:
                error = self._check_activation_id_locked(activation_id, "pause")
                if error is None and self._state == _PAUSED:
                    error = _error(grpc.StatusCode.FAILED_PRECONDITION,
                                   f"{self.name} is already paused",
                                   errors_pb2.BEHAVIOR_ALREADY_PAUSED, {"behavior": self.name})
                if error is None:
                    self._active_accumulated += self._context.clock.now() - self._active_since
                    self._state = _PAUSED
                    self._wants_ticks = False
                current = self._activation_id
            if error is not None:
                future.set_exception(error)
                return
            if not self._hook_or_abort("on_pause", self._behavior.on_pause, future):
                return
            with self._lock:
                event = self._new_event_locked()
                event.paused.SetInParent()
                self._context.events.append(event)
            future.set_result(behavior_pb2.PauseResponse(activation_id=current))

        self._post(run, self._cancel_with(future))
        return future

    def resume(self, activation_id=""):
        """Resumes a paused activation: on_resume() runs, then a tick at once."""
        future = concurrent.futures.Future()
        if self._refused_while_blocked(future):
            return future

        def run():
            with self._lock:
                error = self._check_activation_id_locked(activation_id, "resume")
                if error is None and self._state != _PAUSED:
                    error = _error(grpc.StatusCode.FAILED_PRECONDITION,
                                   f"{self.name} is not paused", errors_pb2.BEHAVIOR_NOT_PAUSED,
                                   {"behavior": self.name})
                current = self._activation_id
            if error is not None:
                future.set_exception(error)
                return
            if not self._hook_or_abort("on_resume", self._behavior.on_resume, future):
                return
            with self._lock:
                now = self._context.clock.now()
                self._state = _ACTIVE
                self._active_since = now
                self._next_tick = now
                event = self._new_event_locked()
                event.resumed.SetInParent()
                self._context.events.append(event)
                self._wants_ticks = True
            future.set_result(behavior_pb2.ResumeResponse(activation_id=current))

        self._post(run, self._cancel_with(future))
        return future

    def modify(self, update, activation_id=""):
        """Applies the set fields of `update` (a Parameters message) over the current
        parameters (merge_update), validates the result, and calls on_modify() with it before it
        takes effect."""
        future = concurrent.futures.Future()
        if getattr(update, "DESCRIPTOR", None) is not self.parameters_type.DESCRIPTOR:
            future.set_exception(self._wrong_type())
            return future
        owned = self.parameters_type()
        owned.CopyFrom(update)
        if self._refused_while_blocked(future):
            return future

        def run():
            with self._lock:
                error = self._check_activation_id_locked(activation_id, "modify")
                if error is None:
                    merged = self.parameters_type()
                    merged.CopyFrom(self._parameters)
                current = self._activation_id
            if error is not None:
                future.set_exception(error)
                return
            merge_update(owned, merged)
            try:
                apply_defaults_and_validate(merged)
            except StatusError as invalid:
                future.set_exception(parameter_error(invalid, self.name))
                return
            refusal = None

            def hook():
                nonlocal refusal
                try:
                    self._behavior.on_modify(merged)
                except StatusError as refused:
                    refusal = refused

            if not self._hook_or_abort("on_modify", hook, future):
                return
            if refusal is not None:
                future.set_exception(refusal.rewrap(
                    f"{self.name} refused the new parameters: {refusal.message}"))
                return
            with self._lock:
                self._parameters = merged
                response = behavior_pb2.ModifyResponse(activation_id=current,
                                                       parameters=to_struct(merged))
                event = self._new_event_locked()
                event.modified.parameters.CopyFrom(response.parameters)
                self._context.events.append(event)
            future.set_result(response)

        self._post(run, self._cancel_with(future))
        return future

    def check_situation(self):
        """Runs check_situation() on the worker: a CheckSituationResponse."""
        future = concurrent.futures.Future()
        if self._refused_while_blocked(future):
            return future

        def run():
            result = None

            def call(_):
                nonlocal result
                result = _situation(self._behavior.check_situation())

            failure = self._guarded(
                "check_situation", call, lambda: future.set_result(
                    behavior_pb2.CheckSituationResponse(feasible=False,
                                                        reasons=["stopped by the watchdog"])))
            if failure is not None:
                future.set_result(behavior_pb2.CheckSituationResponse(feasible=False,
                                                                      reasons=[failure]))
                return
            response = behavior_pb2.CheckSituationResponse(
                feasible=result.feasible, performance_ratio=result.performance_ratio)
            _add_reasons(result, response)
            future.set_result(response)

        self._post(run, self._cancel_with(future))
        return future

    def check_activation(self):
        """The current activation state, at once (no user code): a CheckActivationResponse."""
        with self._lock:
            running = self._running()
            response = behavior_pb2.CheckActivationResponse(active=running, state=self._state)
            if running:
                response.activation_id = self._activation_id
                response.parameters.CopyFrom(to_struct(self._parameters))
                response.activation_time.CopyFrom(_timestamp(self._activation_time))
                response.active_duration.CopyFrom(
                    _duration(self._active_time_locked(self._context.clock.now())))
            return response

    def state(self):
        """The lifecycle state, a behavior_pb2.BehaviorState value."""
        with self._lock:
            return self._state

    def caught_up(self, t):
        """Whether everything due up to time point `t` on the behavior's clock has run: no
        command waits or runs, and an active behavior is not ticking and has its next tick
        after `t` (the deterministic mode reports a time grant only once every behavior is
        caught up with it). A command held at the time gate (before_command) waits for time, so
        it counts as caught up."""
        with self._lock:
            worker = self._worker
            if worker is not None and worker.gated:
                return True
            if self._commands or (worker is not None and (worker.commanding or worker.ticking)):
                return False
            return self._state != _ACTIVE or self._next_tick > t

    def idle(self):
        """Whether nothing runs until a call from outside: no command waits or runs, no tick
        runs, and the behavior is not active (the deterministic mode does not wait for an idle
        system)."""
        with self._lock:
            worker = self._worker
            busy = worker is not None and (worker.gated or worker.commanding or worker.ticking)
            return not self._commands and not busy and self._state != _ACTIVE

    # Blocking conveniences; they wait at most `timeout` seconds of wall time.

    def activate_and_wait(self, parameters, request_id="", timeout=5.0):
        return _wait(self.activate(parameters, request_id), timeout)

    def deactivate_and_wait(self, activation_id="", timeout=5.0):
        return _wait(self.deactivate(activation_id), timeout)

    def pause_and_wait(self, activation_id="", timeout=5.0):
        return _wait(self.pause(activation_id), timeout)

    def resume_and_wait(self, activation_id="", timeout=5.0):
        return _wait(self.resume(activation_id), timeout)

    def modify_and_wait(self, update, activation_id="", timeout=5.0):
        return _wait(self.modify(update, activation_id), timeout)

    def check_situation_and_wait(self, timeout=5.0):
        return _wait(self.check_situation(), timeout)

    # ---- The worker ----

    def _new_worker_locked(self):
        worker = _Worker()
        worker.thread = threading.Thread(target=self._run, args=(worker,), daemon=True,
                                         name=f"behavior-{self.name}")
        self._worker = worker
        return worker

    def _running(self):
        return self._state in (_ACTIVE, _PAUSED)

    def _post(self, run, cancel):
        """Queues a command for the worker; once the worker has ended, `cancel` answers the
        caller instead, so that every caller gets an answer."""
        with self._lock:
            if not self._exited:
                self._commands.append(_Command(run, cancel))
                self._wake.notify_all()
                return
        if cancel is not None:
            cancel()

    def _cancel_with(self, future):
        def cancel():
            future.set_exception(_error(grpc.StatusCode.UNAVAILABLE,
                                        f"{self.name} is shutting down",
                                        errors_pb2.SHUTTING_DOWN, {"behavior": self.name}))
        return cancel

    def _set_stopping(self):
        with self._lock:
            self._stopping = True
            self._wake.notify_all()

    def _schedule(self, inbox):
        with self._lock:
            if self._exited or self._stopping:
                return
            self._ready.append(inbox)
            self._wake.notify_all()

    def _inbox_generation(self):
        with self._lock:
            return self._generation if self._activation_id else 0

    def _run(self, worker):
        try:
            self._loop(worker)
        except _Abandoned:
            pass  # the watchdog (or stop) gave this worker up; another serves the behavior

    def _loop(self, worker):
        left = []
        self._lock.acquire()
        try:
            while not worker.retired and not self._stopping:
                if self._commands:
                    command = self._commands.popleft()
                    if self._context.before_command is not None:
                        worker.gated = True
                        self._lock.release()
                        try:
                            self._context.before_command()
                        finally:
                            self._lock.acquire()
                            worker.gated = False
                        if worker.retired:  # stop() gave up waiting while it was held
                            left.append(command)
                            break
                    worker.commanding = True
                    self._lock.release()
                    try:
                        command.run()
                    finally:
                        self._lock.acquire()
                        worker.commanding = False
                    continue
                if self._ready:
                    inbox = self._ready.popleft()
                    self._lock.release()
                    try:
                        self._deliver(inbox)
                    finally:
                        self._lock.acquire()
                    continue
                seen = self._wakes

                def woken():
                    return (self._stopping or worker.retired or bool(self._commands)
                            or bool(self._ready) or self._wakes != seen)

                if self._state == _ACTIVE:
                    clock = self._context.clock
                    if not clock.valid():
                        self._wake.wait_for(woken, 0.05)
                        continue
                    now = clock.now()
                    if now >= self._next_tick:
                        self._next_tick += self._period
                        # Never burst to catch up: a late tick moves the schedule.
                        if self._next_tick <= now:
                            self._next_tick = now + self._period
                        worker.ticking = True
                        self._lock.release()
                        try:
                            self._execute()
                        finally:
                            self._lock.acquire()
                            worker.ticking = False
                        continue
                    self._wake.wait_for(woken, clock.wall_wait_for(self._next_tick - now))
                else:
                    self._wake.wait_for(woken)  # inactive: no CPU until a command arrives
            if not worker.retired:
                self._exited = True
                left.extend(self._commands)
                self._commands.clear()
                self._ready.clear()
                self._wake.notify_all()
        finally:
            self._lock.release()
        for command in left:
            if command.cancel is not None:
                command.cancel()

    def _guarded(self, function, f, abandoned=None):
        """Runs user code `f(call)` under the watchdog: None when it returned, else the failure
        message ("check_goal threw: ValueError: bad index"). When the watchdog abandoned it
        meanwhile, raises _Abandoned to end this worker."""
        call = _Call(function, abandoned)
        with self._lock:
            self._call = call
        failure = None
        try:
            f(call)
        except BaseException as error:  # user code: whatever it raises ends the activation
            failure = f"{call.function} threw: {_exception_text(error)}"
        with self._lock:
            fired = call.fired
            if self._call is call:
                self._call = None
        if fired:
            self._unblock(call.function)
            raise _Abandoned
        return failure

    def _unblock(self, function):
        """On the abandoned worker, once the stuck `function` returned: on_deactivate() (unless
        it was the stuck one), then INACTIVE, accepting activations again (C++'s guarded())."""
        if function != "on_deactivate":
            try:
                self._behavior.on_deactivate()
            except BaseException:  # user code: the activation has already ended
                pass
        with self._lock:
            self._state = _INACTIVE
            self._activation_id = ""
            self._parameters = None
            self._generation += 1
        self._report_active(False)
        if self._context.observer is not None:
            self._context.observer.on_blocked(False)

    def _blocked_error_locked(self):
        """BEHAVIOR_BLOCKED while a stuck function has not returned, else None."""
        if self._state != _BLOCKED:
            return None
        return _error(grpc.StatusCode.FAILED_PRECONDITION,
                      f"{self.name} is blocked: user code of its previous activation has not "
                      "returned yet (stopped by the watchdog); try again later",
                      errors_pb2.BEHAVIOR_BLOCKED, {"behavior": self.name})

    def _refused_while_blocked(self, future):
        """Sets BEHAVIOR_BLOCKED on `future` and returns True while blocked."""
        with self._lock:
            error = self._blocked_error_locked()
        if error is not None:
            future.set_exception(error)
        return error is not None

    def _hook_or_abort(self, function, hook, future):
        """Runs a lifecycle hook; if it fails, ends the activation with PROCESS_FAILURE,
        answers ABORTED and returns False."""
        def abandoned():
            future.set_exception(StatusError(
                grpc.StatusCode.ABORTED, f"{self.name}: stopped by the watchdog; the activation "
                                         "ended with PROCESS_FAILURE"))

        failure = self._guarded(function, lambda _: hook(), abandoned)
        if failure is None:
            return True
        self._finish(_PROCESS_FAILURE, failure)
        future.set_exception(StatusError(
            grpc.StatusCode.ABORTED,
            f"{self.name}: {failure}; the activation ended with PROCESS_FAILURE"))
        return False

    @staticmethod
    def _recover(call):
        """On the new worker, after the watchdog abandoned `call` (the activation has ended,
        the behavior is BLOCKED): answers the caller that waited on the stuck function."""
        if call.abandoned is not None:
            call.abandoned()

    def _deliver(self, inbox):
        with self._lock:
            stale = (inbox.generation not in (0, self._generation)
                     or self._state == _BLOCKED)
            active = self._running()
        if stale:
            inbox.discard()
            return
        failure = self._guarded("a sample handler (on_worker)", lambda _: inbox.drain())
        if failure is not None and active:
            self._finish(_PROCESS_FAILURE, failure)

    def _execute(self):
        """One tick: the four checks, the time-out, then on_execute() (the paper's execute())."""
        started = time.monotonic_ns()
        cpu_started = time.thread_time_ns()
        behavior = self._behavior
        cause = _UNSPECIFIED
        message = ""
        situation = None

        def monitoring(call):
            nonlocal cause, message, situation
            call.function = "check_processes"
            verdict = _verdict(behavior.check_processes(), "check_processes")
            if verdict.finishes:
                cause, message = _PROCESS_FAILURE, verdict.message
                return
            call.function = "check_situation"
            situation = _situation(behavior.check_situation())
            if not situation.feasible:
                cause, message = _SITUATION_CHANGE, _join_reasons(situation.reasons)
                return
            call.function = "check_goal"
            verdict = _verdict(behavior.check_goal(), "check_goal")
            if verdict.finishes:
                cause, message = _GOAL_ACHIEVED, verdict.message
                return
            call.function = "check_progress"
            verdict = _verdict(behavior.check_progress(), "check_progress")
            if verdict.finishes:
                cause, message = _WRONG_PROGRESS, verdict.message

        failure = self._guarded("monitoring", monitoring)
        if failure is not None:
            self._finish(_PROCESS_FAILURE, failure)
            return
        if (cause == _UNSPECIFIED and self._maximum_execution_time > 0
                and self._active_time() >= self._maximum_execution_time):
            cause = _TIME_OUT
            message = self._time_out_reason or (
                "not finished within maximum_execution_time "
                f"{_seconds_text(self._maximum_execution_time)} of active time")
        observer = self._context.observer
        if observer is not None:
            observer.on_monitoring(time.monotonic_ns() - started,
                                   time.thread_time_ns() - cpu_started)
        if cause != _UNSPECIFIED:
            self._finish(cause, message)
            return
        if (abs(situation.performance_ratio - self._reported_performance)
                >= self._options.situation_report_threshold
                or situation.reasons != self._reported_reasons
                or situation.codes != self._reported_codes):
            with self._lock:
                self._reported_performance = situation.performance_ratio
                self._reported_reasons = list(situation.reasons)
                self._reported_codes = list(situation.codes)
                event = self._new_event_locked()
                changed = event.situation_changed
                changed.feasible = True
                changed.performance_ratio = situation.performance_ratio
                _add_reasons(situation, changed)
                self._context.events.append(event)
            if observer is not None:
                observer.on_situation(situation.performance_ratio)
        failure = self._guarded("on_execute", lambda _: behavior.on_execute())
        if self._first_execute_pending:
            self._first_execute_pending = False
            if observer is not None:
                observer.on_first_execute(time.monotonic_ns() - self._activate_received)
        if failure is not None:
            self._finish(_PROCESS_FAILURE, failure)

    def _finish(self, cause, message, abandoned=None):
        """Ends the current activation (worker, lock not held): on_deactivate(), then the
        finished event. `abandoned` answers the waiting caller if on_deactivate gets stuck."""
        failure = self._guarded("on_deactivate", lambda _: self._behavior.on_deactivate(),
                                abandoned)
        if failure is not None:
            message += ("; " if message else "") + failure
        with self._lock:
            if not self._running():
                return
            self._end_locked(cause, message)
        self._report_active(False)

    def _end_locked(self, cause, message):
        """Emits the finished event and clears the activation."""
        self._record_finished_locked(cause, message)
        self._state = _INACTIVE
        self._activation_id = ""
        self._parameters = None
        self._generation += 1

    def _record_finished_locked(self, cause, message):
        event = self._new_event_locked()
        finished = event.finished
        finished.cause = cause
        finished.message = message
        finished.active_duration.CopyFrom(
            _duration(self._active_time_locked(self._context.clock.now())))
        if self._parameters is not None:
            finished.parameters.CopyFrom(to_struct(self._parameters))
        self._wants_ticks = False
        self._finished.append((self._activation_id, cause))
        # Metrics first, so that a client that sees the event reads updated counters.
        if self._context.observer is not None:
            self._context.observer.on_finished(cause)
        self._context.events.append(event)

    def _new_event_locked(self):
        return behavior_pb2.BehaviorEvent(behavior=self.name, activation_id=self._activation_id,
                                          time=_timestamp(self._context.clock.now()))

    def _report_active(self, active):
        if self._context.on_active_changed is not None:
            self._context.on_active_changed(active)
        with self._lock:
            self._watchdog_wake.notify_all()

    def _active_time_locked(self, now):
        if self._state == _ACTIVE:
            return self._active_accumulated + (now - self._active_since)
        return self._active_accumulated

    def _active_time(self):
        now = self._context.clock.now()
        with self._lock:
            return self._active_time_locked(now)

    def _watchdog_loop(self):
        """Polls the running user function while an activation runs, at a quarter of the
        timeout (between 5 ms and 1 s); sleeps while none does."""
        period = min(1.0, max(0.005, self._options.watchdog_timeout / _NANOS / 4))
        with self._lock:
            while not self._watchdog_stop:
                if not self._running():
                    self._watchdog_wake.wait()
                    continue
                self._watchdog_wake.wait(period)
                if self._watchdog_stop:
                    break
                self._lock.release()
                try:
                    self.watchdog_check()
                finally:
                    self._lock.acquire()

    def _wrong_type(self):
        return _error(grpc.StatusCode.INVALID_ARGUMENT,
                      f"{self.name} takes parameters of type "
                      f"{self.parameters_type.DESCRIPTOR.full_name}",
                      errors_pb2.INVALID_REQUEST, {"behavior": self.name})

    def _check_activation_id_locked(self, activation_id, verb):
        """The refusal of a call that names `activation_id` (or none), or None."""
        running = self._running()
        if activation_id and (not running or activation_id != self._activation_id):
            current = self._activation_id if running else "none"
            return _error(grpc.StatusCode.ABORTED,
                          f"cannot {verb} activation {activation_id} of {self.name}: it is not "
                          f"the current activation (current: {current})",
                          errors_pb2.ACTIVATION_MISMATCH,
                          {"behavior": self.name, "activation_id": activation_id,
                           "current_activation_id": current})
        if not running:
            return _error(grpc.StatusCode.FAILED_PRECONDITION,
                          f"cannot {verb} {self.name}: it is not active",
                          errors_pb2.BEHAVIOR_NOT_ACTIVE, {"behavior": self.name})
        return None

    def _do_activate(self, parameters, request_id, received, future):
        replay = refusal = None
        with self._lock:
            wall_now = time.monotonic()
            while (self._request_id_order
                   and wall_now - self._request_id_order[0][0] > self.REQUEST_ID_WINDOW_S):
                self._request_ids.pop(self._request_id_order.popleft()[1], None)
            if request_id and request_id in self._request_ids:
                replay = behavior_pb2.ActivateResponse()
                replay.CopyFrom(self._request_ids[request_id])
                replay.replayed = True
            elif self._state == _BLOCKED:
                refusal = self._blocked_error_locked()
            elif self._state != _INACTIVE:
                refusal = _error(grpc.StatusCode.FAILED_PRECONDITION,
                                 f"{self.name} is already active (activation "
                                 f"{self._activation_id}); deactivate it first, or use Modify "
                                 "to change its parameters", errors_pb2.BEHAVIOR_ALREADY_ACTIVE,
                                 {"behavior": self.name,
                                  "current_activation_id": self._activation_id})
            elif not self._context.clock.valid():
                refusal = _error(grpc.StatusCode.FAILED_PRECONDITION,
                                 "the behavior clock has no time yet; is the simulator "
                                 "publishing on the 'clock' topic?", errors_pb2.CLOCK_NOT_READY,
                                 {"behavior": self.name})
        if replay is not None or refusal is not None:
            _answer(future, replay, refusal)
            return
        situation = None

        def check(_):
            nonlocal situation
            situation = _situation(self._behavior.check_situation())

        failure = self._guarded("check_situation", check)
        if failure is not None:
            future.set_exception(_error(grpc.StatusCode.FAILED_PRECONDITION,
                                        f"{self.name} cannot be activated: {failure}",
                                        errors_pb2.BEHAVIOR_FAILED, {"behavior": self.name}))
            return
        if not situation.feasible:
            future.set_exception(_error(
                grpc.StatusCode.FAILED_PRECONDITION,
                f"{self.name} cannot be activated in the current situation: "
                f"{_join_reasons(situation.reasons)}", errors_pb2.SITUATION_NOT_SUITABLE,
                {"behavior": self.name, "situation_reasons": _code_names(situation)}))
            return
        now = self._context.clock.now()
        with self._lock:
            self._parameters = parameters
            self._activation_counter += 1
            self._activation_id = (f"{self.name}-{self._context.events.incarnation[:8]}-"
                                   f"{self._activation_counter}")
            self._generation += 1
            self._maximum_execution_time = self._options.maximum_execution_time
            self._time_out_reason = ""
            self._activation_time = now
            self._active_since = now
            self._active_accumulated = 0
        refusal = None

        def on_activate(_):
            nonlocal refusal
            try:
                self._behavior.on_activate()
            except StatusError as refused:
                refusal = refused

        failure = self._guarded("on_activate", on_activate)
        if failure is not None:
            refusal = StatusError(grpc.StatusCode.INTERNAL, failure)
        if refusal is not None:
            with self._lock:
                self._parameters = None
                self._activation_id = ""
                self._generation += 1
            future.set_exception(StatusError(
                refusal.code, f"{self.name} refused activation: {refusal.message}"))
            return
        with self._lock:
            self._state = _ACTIVE
            self._next_tick = now
            self._first_execute_pending = True
            self._activate_received = received
            self._reported_performance = situation.performance_ratio
            self._reported_reasons = list(situation.reasons)
            self._reported_codes = list(situation.codes)
            response = behavior_pb2.ActivateResponse(activation_id=self._activation_id,
                                                     activation_time=_timestamp(now),
                                                     parameters=to_struct(parameters))
            if self._context.observer is not None:
                self._context.observer.on_activated(time.monotonic_ns() - received)
            event = self._new_event_locked()
            event.activated.parameters.CopyFrom(response.parameters)
            self._context.events.append(event)
            if request_id:
                remembered = behavior_pb2.ActivateResponse()
                remembered.CopyFrom(response)
                self._request_ids[request_id] = remembered
                self._request_id_order.append((time.monotonic(), request_id))
            self._wants_ticks = True
        self._report_active(True)
        future.set_result(response)


def _answer(future, response, error):
    if error is not None:
        future.set_exception(error)
    else:
        future.set_result(response)


def _wait(future, timeout):
    """The future's result, raising its StatusError; BEHAVIOR_UNRESPONSIVE after `timeout`."""
    try:
        return future.result(timeout)
    except concurrent.futures.TimeoutError:
        raise StatusError(grpc.StatusCode.DEADLINE_EXCEEDED,
                          "the behavior did not answer in time (blocked user code?)",
                          reason=errors_pb2.BEHAVIOR_UNRESPONSIVE) from None
