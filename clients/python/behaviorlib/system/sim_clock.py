"""Simulated time from the data channel's `clock` topic (behaviorlib.v1.Clock samples that the
simulator publishes): a port of services/channel/sim_clock.cc, the clock of a behavior system
started with --clock sim.

Free-running, the simulator publishes its time line (a simulated time, the host wall time it held
at, and the time scale) only when the line changes and once a wall second; SimClock extrapolates
the line on the host's monotonic clock, so a process needs no message per tick to know the time
(decision 16). In lock-step (time scale 0) time moves only with samples. The time reached so far
stays reached: a late sample of an older time moves nothing back, and a new epoch (a Reset, a
restarted simulator) starts again.

    clock = SimClock()
    clock.follow(channel)            # a behaviorlib.system.channel.DataChannel
    clock.valid()                    # False until the first sample
    clock.now()                      # int nanoseconds of simulated time

Unit tests feed it with on_clock_sample() and fake host clocks.
"""

import threading
import time

from behaviorlib.system.clock import NANOS_PER_SECOND, Clock
from behaviorlib.v1 import types_pb2

CLOCK_TOPIC = "clock"
# Upper bound of a waiter's sleep, seconds: listeners are woken on every sample; the bound covers
# a missed notification or a dead simulator.
MAX_WALL_WAIT_S = 0.05
# Time scales below this count as this, so that a tiny scale cannot turn a short simulated wait
# into an enormous wall wait.
MIN_TIME_SCALE = 1e-3
# A sample's wall_time older than this (or in the future) is taken as its time of arrival: the
# publisher's host clock disagrees with ours.
MAX_SAMPLE_AGE_NS = 5 * NANOS_PER_SECOND


def _ns(timestamp):
    return timestamp.seconds * NANOS_PER_SECOND + timestamp.nanos


class SimClock(Clock):
    """A Clock following the simulator's time. Thread-safe. `steady` and `system` are the host
    clocks (int nanoseconds) it reads; tests fake them."""

    def __init__(self, steady=time.monotonic_ns, system=time.time_ns):
        super().__init__()
        self._steady = steady
        self._system = system
        self._lock = threading.Lock()
        self._valid = False
        self._floor = 0
        self._anchor_time = 0
        self._anchor_steady = 0
        self._time_scale = 0.0
        self._paused = False
        self._epoch = 0
        self._samples = 0
        self._last_steady_update = 0
        self._subscription = None

    def follow(self, channel):
        """Subscribes to the `clock` topic of `channel` (newest sample first, then each)."""
        self._subscription = channel.subscribe(CLOCK_TOPIC, types_pb2.Clock,
                                               self.on_clock_sample, latest_first=True)

    def close(self):
        if self._subscription is not None:
            self._subscription.close()

    def _line_at(self, at):
        if self._paused or not self._time_scale > 0.0 or at <= self._anchor_steady:
            return self._anchor_time
        return self._anchor_time + int((at - self._anchor_steady) * self._time_scale)

    def now(self):
        with self._lock:
            if not self._valid:
                return 0
            self._floor = max(self._floor, self._line_at(self._steady()))
            return self._floor

    def wall_wait_for(self, remaining):
        if remaining <= 0:
            return 0.0
        with self._lock:
            scale = 0.0 if self._paused else self._time_scale
        if scale <= 0:
            return MAX_WALL_WAIT_S  # lock-step: time moves only with samples
        return min(MAX_WALL_WAIT_S, remaining / max(scale, MIN_TIME_SCALE) / NANOS_PER_SECOND)

    def valid(self):
        with self._lock:
            return self._valid

    def stale(self, wall_limit_s):
        """No sample for `wall_limit_s` of host time (or none yet): the simulator may be gone."""
        with self._lock:
            return (not self._valid or
                    self._steady() - self._last_steady_update > wall_limit_s * NANOS_PER_SECOND)

    def time_scale(self):
        with self._lock:
            return self._time_scale

    def sample_count(self):
        with self._lock:
            return self._samples

    def on_clock_sample(self, sample):
        """Takes one Clock sample (the subscription's callback)."""
        steady_now = self._steady()
        system_now = self._system()
        # Where the sample's time held on our monotonic clock: its wall_time when our host
        # clock agrees, else now (a publisher of every tick sets none).
        anchor = steady_now
        if sample.HasField("wall_time"):
            age = system_now - _ns(sample.wall_time)
            if 0 < age <= MAX_SAMPLE_AGE_NS:
                anchor = steady_now - age
        with self._lock:
            if not self._valid or sample.epoch != self._epoch:
                self._floor = 0  # time restarted
            else:
                self._floor = max(self._floor, self._line_at(steady_now))
            self._anchor_time = _ns(sample.time)
            self._anchor_steady = anchor
            self._time_scale = sample.time_scale
            self._paused = sample.paused
            self._epoch = sample.epoch
            self._valid = True
            self._samples += 1
            self._last_steady_update = steady_now
        self._notify_listeners()
