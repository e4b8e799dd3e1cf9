"""A Python behavior system for the deterministic mode's tests (test_system_time_follower.py,
test_system_launcher.py), run as a program like any system:

    python deterministic_wait_system.py --robot-id drone1 --channel 127.0.0.1:50051 \\
        --clock sim --follow-time 127.0.0.1:50070 --listen 127.0.0.1:0 --port-file w.ports

It hosts TEST_WAIT, a WAIT (GOAL_ACHIEVED after duration_s of active time) that measures at
each tick what the time grants promise, and says it in its finished message as JSON:
  - ticks: how many on_execute ran, and gaps_ns: the distinct times between two of them (one
    tick period each when no tick was missed);
  - moved_during_execute: ticks during which the clock moved (a behavior clock following the
    grants does not move under a running tick, however long it sleeps: execute_sleep_s);
  - max_pose_lag_ns: the largest age of the newest ground-truth pose at a tick (the simulator
    publishes it every quantum; the data barrier has it in before the tick: 0);
  - max_echo_lag_ns: at each tick from the third on, how far the newest sample of the system's
    own echo topic (published at every tick, read back through the broker) lags behind the
    previous tick (the report of a grant names what was published, the next grant waits for
    it: 0). Not at the second tick: the activation ran while the system was idle (not waited
    for), so the grant after the one it ran at may have been made before the report that named
    the first echo;
  - wall_s: the activation's wall time.
It registers as "python_deterministic_waits", not as its file's name: the launcher must learn
the name from the process.
"""

import json
import sys
import time

from behaviorlib.system import Behavior, Verdict, run_system, seconds
from behaviorlib.system.declare import Field, declare_parameters
from behaviorlib.v1 import types_pb2

SYSTEM = "python_deterministic_waits"

TestWaitParameters = declare_parameters(
    "TestWaitParameters", package="behaviorlib.tests.v1", behavior="TEST_WAIT",
    doc="Stays active for duration_s of the behavior clock's time, measuring its ticks.",
    fields=[
        Field("duration_s", "double", range=(0, 3600), default=1.0,
              doc="Active time before GOAL_ACHIEVED, in seconds of the behavior clock."),
        Field("execute_sleep_s", "double", range=(0, 0.5), default=0.0,
              doc="Wall time each on_execute sleeps, in seconds (a slow behavior)."),
    ])


def _ns(stamp):
    return stamp.seconds * 1_000_000_000 + stamp.nanos


class TestWait(Behavior):
    """TEST_WAIT (the module's docstring says what it measures)."""

    Parameters = TestWaitParameters

    def __init__(self, channel, robot_id):
        super().__init__()
        self._channel = channel
        self._echo_topic = f"robots/{robot_id}/test/echo"
        # The newest stamps, written by the subscriptions' reader threads (an int assignment:
        # the worker reads them without a lock).
        self._pose_ns = None
        self._echo_ns = None
        channel.subscribe(f"robots/{robot_id}/ground_truth/pose", types_pb2.PoseStamped,
                          self._on_pose)
        channel.subscribe(self._echo_topic, types_pb2.PoseStamped, self._on_echo)

    def _on_pose(self, pose):
        self._pose_ns = _ns(pose.header.stamp)

    def _on_echo(self, echo):
        self._echo_ns = _ns(echo.header.stamp)

    def on_activate(self):
        self._ticks = 0
        self._gaps = set()
        self._moved = 0
        self._pose_lag = 0
        self._echo_lag = 0
        self._last_tick = None
        self._wall_start = time.monotonic()

    def on_execute(self):
        now = self.now()
        if self._pose_ns is not None:
            self._pose_lag = max(self._pose_lag, now - self._pose_ns)
        if self._last_tick is not None:
            self._gaps.add(now - self._last_tick)
        if self._ticks >= 2:
            echoed = self._echo_ns if self._echo_ns is not None else 0
            self._echo_lag = max(self._echo_lag, self._last_tick - echoed)
        echo = types_pb2.PoseStamped()
        echo.header.stamp.seconds, echo.header.stamp.nanos = divmod(now, 1_000_000_000)
        self._channel.publish(self._echo_topic, echo)
        time.sleep(self.parameters.execute_sleep_s)
        if self.now() != now:
            self._moved += 1
        self._last_tick = now
        self._ticks += 1

    def check_goal(self):
        if self.active_time() < seconds(self.parameters.duration_s):
            return Verdict.keep_going()
        return Verdict.finish(json.dumps({
            "ticks": self._ticks, "gaps_ns": sorted(self._gaps),
            "moved_during_execute": self._moved, "max_pose_lag_ns": self._pose_lag,
            "max_echo_lag_ns": self._echo_lag, "wall_s": time.monotonic() - self._wall_start}))


def behaviors(context):
    if context.channel is None:
        raise SystemExit(f"{SYSTEM} measures the data channel: give --channel")
    return [TestWait(context.channel, context.robot_id)]


if __name__ == "__main__":
    sys.exit(run_system(behaviors, system=SYSTEM))
