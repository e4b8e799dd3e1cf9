"""behaviorlib.system.sim_clock.SimClock on fake host clocks (no server): the time line
extrapolated at its scale, lock-step, a late sample, a new epoch, and the listeners woken."""

from behaviorlib.system.clock import NANOS_PER_SECOND, ClockListener
from behaviorlib.system.sim_clock import MAX_WALL_WAIT_S, SimClock
from behaviorlib.v1 import types_pb2

S = NANOS_PER_SECOND


class Host:
    def __init__(self):
        self.steady = 1000 * S
        self.system = 1_700_000_000 * S


def sample(time_s, scale, epoch=1, wall_ns=None, paused=False):
    message = types_pb2.Clock(time_scale=scale, epoch=epoch, paused=paused)
    message.time.seconds, message.time.nanos = divmod(int(time_s * S), S)
    if wall_ns is not None:
        message.wall_time.seconds, message.wall_time.nanos = divmod(wall_ns, S)
    return message


def make():
    host = Host()
    return host, SimClock(steady=lambda: host.steady, system=lambda: host.system)


def test_no_time_before_the_first_sample():
    _, clock = make()
    assert not clock.valid() and clock.now() == 0 and clock.stale(1.0)


def test_the_line_is_extrapolated_at_its_scale_from_its_wall_time():
    host, clock = make()
    # The line held 100 s at a wall time 0.5 s ago, at 10x: now it is at 105 s.
    clock.on_clock_sample(sample(100, 10.0, wall_ns=host.system - S // 2))
    assert clock.valid() and clock.now() == 105 * S
    host.steady += S
    assert clock.now() == 115 * S
    assert clock.wall_wait_for(S) == min(MAX_WALL_WAIT_S, 0.1)  # 1 s at 10x, bounded


def test_lock_step_moves_only_with_samples_and_never_back():
    host, clock = make()
    clock.on_clock_sample(sample(10, 0.0))
    host.steady += 5 * S
    assert clock.now() == 10 * S
    assert clock.wall_wait_for(S) == MAX_WALL_WAIT_S
    clock.on_clock_sample(sample(10.01, 0.0))
    assert clock.now() == int(10.01 * S)
    clock.on_clock_sample(sample(9, 0.0))  # a late sample of an older time
    assert clock.now() == int(10.01 * S)


def test_a_new_epoch_starts_again_and_listeners_are_woken():
    _, clock = make()
    woken = []

    class Listener(ClockListener):
        def on_clock_advanced(self):
            woken.append(clock.now())
    clock.add_listener(Listener())
    clock.on_clock_sample(sample(50, 0.0, epoch=1))
    clock.on_clock_sample(sample(3, 0.0, epoch=2))  # Reset: time restarts
    assert woken == [50 * S, 3 * S]


def test_a_paused_simulation_holds_its_time():
    host, clock = make()
    clock.on_clock_sample(sample(20, 1.0, paused=True))
    host.steady += 3 * S
    assert clock.now() == 20 * S
