"""Clocks that Python behaviors take time from: a port of
services/behaviorlib/core/include/behaviorlib/clock.h (and clock.cc).

A behavior never reads the host clock directly. Its ticks, its time-out and its active time all
use the injected Clock, so that simulated missions and unit tests run fast and
deterministically:

    clock = FakeClock()              # starts at the epoch plus one hour
    clock.advance(seconds(1))        # wakes every waiter at once

Time is an int of nanoseconds, as the C++ Duration and TimePoint are: a time point counts
nanoseconds since the Unix epoch (a simulated epoch for simulated time) and a duration counts
nanoseconds. Integers keep time exact (no float rounding when ticks add up over hours), and they
convert to google.protobuf Timestamp and Duration without loss. `seconds()` and `to_seconds()`
convert from and to SI seconds as floats.
"""

import threading
import time

NANOS_PER_SECOND = 1_000_000_000


def seconds(s):
    """A duration in nanoseconds from seconds given as a float (a parameter such as
    `duration_s`), rounded toward zero to the nanosecond like the C++ `seconds(1.5)`."""
    return int(s * NANOS_PER_SECOND)


def to_seconds(ns):
    """The inverse: a duration in nanoseconds as float seconds."""
    return ns / NANOS_PER_SECOND


class ClockListener:
    """Notified when a non-wall clock's time moves forward, so that threads waiting for a
    deadline on that clock check it again at once."""

    def on_clock_advanced(self):
        """Called from the thread that advanced the clock; must not block."""

    def caught_up(self, t):
        """Work a listener does on this clock outside the behaviors' ticks (a lease renewal):
        whether everything it had due up to time point `t` has run. The deterministic mode
        reports a granted time only once every listener has (Clock.listeners_caught_up).
        Must not block."""
        return True


class Clock:
    """Source of time for behaviors. Thread-safe. Subclasses implement now() and
    wall_wait_for(); those whose time jumps (simulated, fake) call _notify_listeners() after
    it moved."""

    def __init__(self):
        self._listeners_lock = threading.Lock()
        self._listeners = []

    def now(self):
        """The current time point, in nanoseconds since the epoch."""
        raise NotImplementedError

    def wall_wait_for(self, remaining):
        """The longest wall time, in float seconds, that a waiter may sleep before reading
        now() again when `remaining` nanoseconds of this clock's time are left until its
        deadline. A wall clock returns the remaining time itself; a clock that notifies its
        listeners may return a bounded value as a safety net."""
        raise NotImplementedError

    def valid(self):
        """Whether the clock has a time yet (a simulated clock that has not received the
        simulator's time has none). Behaviors do not tick on an invalid clock."""
        return True

    def add_listener(self, listener):
        """Registers a ClockListener, notified whenever time advances."""
        with self._listeners_lock:
            self._listeners.append(listener)

    def remove_listener(self, listener):
        with self._listeners_lock:
            self._listeners = [x for x in self._listeners if x is not listener]

    def listeners_caught_up(self, t):
        """Whether every listener ran what it had due up to `t` (ClockListener.caught_up)."""
        with self._listeners_lock:
            listeners = list(self._listeners)
        return all(listener.caught_up(t) for listener in listeners)

    def _notify_listeners(self):
        """For subclasses: call after the time advanced."""
        with self._listeners_lock:
            listeners = list(self._listeners)
        for listener in listeners:
            listener.on_clock_advanced()


class SteadyClock(Clock):
    """The host's monotonic time, offset once at construction so that it reads as Unix time (for
    timestamps) while never jumping: the clock of a real robot."""

    def __init__(self):
        super().__init__()
        self._offset = time.time_ns() - time.monotonic_ns()

    def now(self):
        return time.monotonic_ns() + self._offset

    def wall_wait_for(self, remaining):
        return max(0.0, remaining / NANOS_PER_SECOND)


class FakeClock(Clock):
    """Manually driven time for unit tests. Starts at `start` nanoseconds (default: the epoch
    plus one hour, so that zero never looks like a valid stamp)."""

    # A waiter is woken by advance(); this bound only guards against a missed notification.
    _SAFETY_WAIT_S = 0.05

    def __init__(self, start=3600 * NANOS_PER_SECOND):
        super().__init__()
        self._lock = threading.Lock()
        self._now = int(start)

    def now(self):
        with self._lock:
            return self._now

    def wall_wait_for(self, remaining):
        return self._SAFETY_WAIT_S

    def advance(self, delta):
        """Moves time forward by `delta` nanoseconds and wakes every waiter."""
        with self._lock:
            self._now += int(delta)
        self._notify_listeners()

    def set(self, t):
        """Sets the time to `t` (ignored if it would go backwards) and wakes every waiter."""
        with self._lock:
            if t > self._now:
                self._now = int(t)
        self._notify_listeners()
