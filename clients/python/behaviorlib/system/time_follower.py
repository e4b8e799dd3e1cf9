"""A Python behavior system's side of the deterministic mode (simulator --time-scale max, the
system's --follow-time SIMULATOR_ADDR): a port of services/behaviorlib/server/time_follower.cc.

It follows the simulator's time grants (behaviorlib.v1.Simulator.FollowTime): each granted time
goes into the system's SimClock, and once every behavior has run everything due up to it
(`caught_up`), the time is reported back, and only then does the simulator go on. So a starved
system slows the simulation instead of missing its deadlines.

    clock = SimClock()                 # not following the channel's clock topic: grants are time
    follower = TimeFollower("127.0.0.1:50070", "my_behaviors/drone1", clock, channel, "drone1")
    host = BehaviorHost(..., before_command=follower.await_turn)
    ... host.start() ...
    follower.start(lambda t: all(e.caught_up(t) for e in host.engines)
                   and clock.listeners_caught_up(t),
                   lambda: all(e.idle() for e in host.engines))
    ...
    follower.stop()                    # leaves the barrier; await_turn() no longer waits

With a data channel, grants are also a data barrier (channel.py):
  - before the clock moves, the follower waits until each of the channel's subscriptions has
    processed the sample the grant names for its topic (FollowTimeResponse.topic_seqs; at most
    2 s of wall time, told once: a restarted broker numbers anew, and a dropped sample never
    comes);
  - before a report, what the behaviors published is synced with the broker, and the report
    names the topic_seq of the last sample on each topic (FollowTimeRequest.topic_seqs), so that
    the next grants to every follower name it;
  - the join, and every report after they changed, name the topics the barrier waits on
    (FollowTimeRequest.awaited_topics): the grants then name only theirs.

A report also says whether the system is idle (no behavior active, no command queued): the
simulator does not wait for an idle system, and sends it a grant only about once a simulated
second, so its clock lags. A command from outside (an activation, a CheckSituation) therefore
first waits in await_turn() (the engine's before_command): it wakes the system
(FollowTimeRequest.wake), and runs once an "awaited" grant (one the simulator waits for) has
moved the clock, so that it starts at the simulation's time and the simulator waits for the
system from then on.

When the grants end (the simulator went away), time runs on in real time from the last grant, so
that the behaviors' staleness checks notice instead of waiting for a grant that may never come;
the follower joins again (backing off from 0.1 s to 2 s) while it lives. A simulator that is
not in the deterministic mode refuses (FAILED_PRECONDITION, told once) and is asked again.

What the C++ follower has and this one has not: the SetpointLedger (a report's
setpoints_written; Python behaviors stream no setpoints through this package), and
ChannelClient::bufferUntilSync (grpcio's request iterators have no buffer hint: each sample is
written at once, which changes how many socket writes a quantum takes, not what the barrier
guarantees).
"""

import queue
import sys
import threading
import time

import grpc

from behaviorlib.v1 import simulator_pb2, simulator_pb2_grpc, types_pb2

from .clock import NANOS_PER_SECOND
from .parameters import StatusError
from .registration import (INITIAL_BACKOFF_S, MAX_BACKOFF_S,  # the same retry period
                           RECONNECTING_CHANNEL_OPTIONS)
from .security import open_channel

# How often the behaviors' progress is looked at while catching up.
CATCH_UP_POLL_S = 100e-6
# How often a wait for data looks whether the follower is stopping.
STOP_POLL_S = 0.05
# The longest wait for a granted sample (wall time).
DATA_WAIT_LIMIT_S = 2.0
# The longest wait of a command for its turn (wall time): the simulator may be held up by
# another follower, for at most its --follower-timeout-s.
TURN_LIMIT_S = 6.0
_END = object()


def _ns(timestamp):
    return timestamp.seconds * NANOS_PER_SECOND + timestamp.nanos


def _say(text):
    print(text, file=sys.stderr, flush=True)


class TimeFollower:
    """Follows the time grants of the simulator at `simulator_address` as `participant` (e.g.
    "my_behaviors/drone1": the simulator's logs name it). `clock` is the system's SimClock,
    which takes each grant; `channel` (a DataChannel, or None) is the data barrier's, and
    `robot_id` names the vehicle whose broker it is (FollowTimeRequest.robot_id);
    `channel_credentials` (the process's TLS, security.TransportSecurity) makes the channel to
    the simulator TLS."""

    def __init__(self, simulator_address, participant, clock, channel=None, robot_id="",
                 channel_credentials=None):
        self._participant = participant
        self._robot_id = robot_id
        self._clock = clock
        self._data = channel
        self._grpc_channel = open_channel(simulator_address, channel_credentials,
                                          RECONNECTING_CHANNEL_OPTIONS)
        self._caught_up = None
        self._idle = None
        self._thread = None
        # await_turn() waits on _cond for the gate or the stop. The gate: a grant was applied
        # on the current stream (_streaming); the applied grant was "awaited" and no idle report
        # went since (_awaited: the simulator waits for us); a wake was sent since the last
        # grant (_wake_sent); how to send one on the current stream (_send_wake).
        self._cond = threading.Condition()
        self._call = None
        self._stopping = False
        self._streaming = False
        self._awaited = False
        self._wake_sent = False
        self._send_wake = None
        self._told_turn_timeout = False
        # Serializes writes on the stream (reports from the thread, wakes from await_turn) and
        # names the stream generation whose writes are open. Taken before _cond, never after.
        self._write_lock = threading.Lock()
        self._open_stream = 0

    def start(self, caught_up, idle):
        """Joins the simulator's grants and follows them on a thread of its own. caught_up(t):
        everything due up to time point t (int nanoseconds) ran; idle(): nothing runs until a
        call from outside. At most once."""
        with self._cond:
            if self._thread is not None or self._stopping:
                return
            self._caught_up = caught_up
            self._idle = idle
            self._thread = threading.Thread(target=self._run, name="time follower", daemon=True)
            self._thread.start()

    def stop(self):
        """Cancels the stream and joins the thread; idempotent. await_turn() no longer waits."""
        with self._cond:
            self._stopping = True
            if self._call is not None:
                self._call.cancel()
            self._cond.notify_all()
            thread = self._thread
        if thread is not None:
            thread.join()
        self._grpc_channel.close()

    def await_turn(self):
        """The time gate of commands from outside (BehaviorContext.before_command): returns at
        once while the simulator waits for this system, or no grants are followed; otherwise
        wakes the system (a FollowTimeRequest.wake) and waits (at most TURN_LIMIT_S of wall
        time, told once) until an "awaited" grant moved the clock. The caller must make idle()
        false before it calls (the engine does: a command held here is not idle)."""
        def ready():
            return self._stopping or not self._streaming or self._awaited

        with self._cond:
            if ready():
                return
            send = None
            if not self._wake_sent and self._send_wake is not None:
                # The simulator may not be sending us grants (idle): ask for one.
                self._wake_sent = True
                send = self._send_wake
        if send is not None:
            send()  # outside _cond: it takes the write lock, which comes first
        with self._cond:
            if self._cond.wait_for(ready, TURN_LIMIT_S) or self._told_turn_timeout:
                return
            self._told_turn_timeout = True
        _say(f"{self._participant}: a command waited {TURN_LIMIT_S * 1000:.0f} ms for the "
             "simulator's next time grant; running it at the last granted time (told once)")

    def _is_stopping(self):
        with self._cond:
            return self._stopping

    def _await_until(self, done):
        """Waits until done() (polling), or the stop; False when stopping."""
        while not done():
            with self._cond:
                if self._cond.wait_for(lambda: self._stopping, CATCH_UP_POLL_S):
                    return False
        return True

    def _set_streaming(self, streaming, write):
        with self._cond:
            self._streaming = streaming
            self._awaited = False
            self._wake_sent = False
            self._send_wake = (
                (lambda: write(simulator_pb2.FollowTimeRequest(wake=True))) if streaming else None)
            self._cond.notify_all()

    def _awaited_topics(self):
        return self._data.awaited_topics() if self._data is not None else []

    def _wait_for_data(self, grant, told):
        """The data barrier before the clock moves: each subscription's granted sample, at most
        DATA_WAIT_LIMIT_S. Returns (stopping, told: whether the time-out was told)."""
        seqs = dict(grant.topic_seqs)
        give_up = time.monotonic() + DATA_WAIT_LIMIT_S
        while not self._data.wait_delivered(seqs, STOP_POLL_S):
            if self._is_stopping():
                return True, told
            if time.monotonic() >= give_up:
                if not told:
                    _say(f"{self._participant}: a granted sample did not arrive within "
                         f"{DATA_WAIT_LIMIT_S * 1000:.0f} ms; going on without it (told once)")
                return False, True
        return False, told

    def _run(self):
        stub = simulator_pb2_grpc.SimulatorStub(self._grpc_channel)
        backoff = INITIAL_BACKOFF_S
        told_refusal = told_sync_failure = told_data_timeout = False
        while True:
            requests = queue.SimpleQueue()
            with self._cond:
                if self._stopping:
                    return
                call = stub.FollowTime(iter(requests.get, _END))
                self._call = call
            with self._write_lock:
                self._open_stream += 1
                generation = self._open_stream

            def write_locked(message, generation=generation, requests=requests):
                # Queues a message for this stream (the write lock held); none once it is
                # closed (a wake sent late, by a command that took the gate before).
                if self._open_stream == generation:
                    requests.put(message)

            def write(message, write_locked=write_locked):
                with self._write_lock:
                    write_locked(message)

            # The topics the data barrier waits on, named in the join and again whenever they
            # changed: the grants name only theirs. An empty list is named too (grants then
            # name no topic); an unnamed one would mean every topic.
            join = simulator_pb2.FollowTimeRequest(participant=self._participant,
                                                   robot_id=self._robot_id)
            awaited_topics = self._awaited_topics()
            join.awaited_topics.SetInParent()
            join.awaited_topics.topics.extend(awaited_topics)
            last_granted = None
            write(join)
            try:
                for grant in call:
                    backoff = INITIAL_BACKOFF_S
                    # The data barrier: what was published up to the grant is in before the
                    # behaviors run.
                    if self._data is not None and grant.topic_seqs:
                        stopping, told_data_timeout = self._wait_for_data(grant,
                                                                          told_data_timeout)
                        if stopping:
                            break
                    # Time does not move under a command or a tick still running for the
                    # previous grant (an idle system is not waited for, so grants may arrive
                    # while an activation runs: its start and its first tick would read
                    # different times).
                    if last_granted is not None:
                        previous = _ns(last_granted.time)
                        if not self._await_until(lambda: self._caught_up(previous)):
                            break
                    self._clock.on_clock_sample(grant.clock)
                    if last_granted is None:
                        self._set_streaming(True, write)
                    last_granted = types_pb2.Clock()
                    last_granted.CopyFrom(grant.clock)
                    with self._cond:
                        # "Awaited": the simulator waits for our report of this grant, and the
                        # clock is current; a command held in await_turn() may run.
                        self._awaited = grant.awaited
                        self._wake_sent = False
                        self._cond.notify_all()
                    granted = _ns(grant.clock.time)
                    if not self._await_until(lambda: self._caught_up(granted)):
                        break
                    # What the behaviors published reaches the broker before the report, so
                    # that the next grant's topic_seqs include it.
                    if self._data is not None:
                        try:
                            self._data.sync(if_published=True)
                        except StatusError as error:
                            if not told_sync_failure:
                                _say(f"{self._participant}: publishing before a time report "
                                     f"failed: {error.message}")
                                told_sync_failure = True
                    # Every grant is reported (the simulator sends the next one then); an idle
                    # system's reports are not waited for.
                    report = simulator_pb2.FollowTimeRequest()
                    report.caught_up_to.CopyFrom(grant.clock.time)
                    if self._data is not None:
                        report.topic_seqs.update(self._data.accepted_seqs())
                    topics = self._awaited_topics()
                    if topics != awaited_topics:
                        awaited_topics = topics
                        report.awaited_topics.SetInParent()
                        report.awaited_topics.topics.extend(topics)
                    with self._write_lock:
                        # Decided and written as one with respect to the gate: a command that
                        # checks await_turn() after this sees _awaited false and wakes the
                        # simulator, its wake written after this report; one that checked
                        # before has made idle() false. (A stream that broke is seen by the
                        # next read: writes only queue.)
                        with self._cond:
                            idle = self._idle()
                            if idle:
                                self._awaited = False
                            report.idle = idle
                        write_locked(report)
            except grpc.RpcError:
                pass  # the stream ended: its status is read below
            self._set_streaming(False, write)
            with self._write_lock:
                # No wake is written once this returns.
                self._open_stream += 1
                requests.put(_END)  # half-closes the stream
            call.cancel()  # a no-op once the simulator ended it
            code, details = call.code(), call.details() or ""
            if last_granted is not None and not self._is_stopping():
                # The simulator went away: time runs on in real time from the last grant (as
                # SimClock runs on at the last scale when free running), so that the
                # behaviors' staleness checks notice (PROCESS_FAILURE) instead of waiting for
                # a grant that may never come.
                run_on = types_pb2.Clock()
                run_on.CopyFrom(last_granted)
                run_on.time_scale = 1.0
                run_on.wall_time.GetCurrentTime()
                self._clock.on_clock_sample(run_on)
                _say(f"{self._participant}: the time grants ended ({details}); time runs on in "
                     "real time")
            if code == grpc.StatusCode.FAILED_PRECONDITION and not told_refusal:
                _say(f"{self._participant}: the simulator gives no time grants ({details}); "
                     "asking again")
                told_refusal = True
            with self._cond:
                self._call = None
                # Until stopped, at most backoff.
                if self._cond.wait_for(lambda: self._stopping, backoff):
                    return
            backoff = min(backoff * 2, MAX_BACKOFF_S)
