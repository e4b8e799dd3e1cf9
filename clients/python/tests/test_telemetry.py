"""The vehicles' state through the client (GetVehicleSample, WatchVehicle),
against the real stack (conftest.py): the simulator's vehicles in the
deterministic mode, their samples read through the coordinator."""

import asyncio
import math
import re
import statistics
import time
import urllib.request

import grpc
import pytest

import behaviorlib
from behaviorlib import Fleet, aio
from behaviorlib import numpy_helpers as nph
from behaviorlib.v1 import coordinator_pb2, platform_pb2

from conftest import wait_until

# What a read must come back within on loopback (median of many), seconds:
# the figure docs/python-client.md states. Only an upper bound on a median,
# which a busy machine moves far less than one call.
READ_MEDIAN_LIMIT_S = 0.010


@pytest.fixture(scope="module")
def fleet(coordinator):
    with Fleet(coordinator) as fleet:
        yield fleet


def test_the_vehicle_is_read_with_its_stamp_and_age(fleet):
    drone = fleet.robot("drone2")
    truth = drone.sample("ground_truth_pose")
    assert truth.robot_id == "drone2" and truth.topic == "robots/drone2/ground_truth/pose"
    assert truth.kind == coordinator_pb2.VEHICLE_SAMPLE_KIND_GROUND_TRUTH_POSE
    pose = behaviorlib._core.unpack_sample(truth)
    assert pose.header.stamp == truth.stamp and truth.stamp.seconds + truth.stamp.nanos > 0
    # The coordinator follows the vehicles' time (--clock sim): the age is
    # in that time, within the default limit (or the read would be Stale).
    assert truth.HasField("age") and truth.age.ToTimedelta().total_seconds() <= 1.0
    position = nph.position(pose)
    assert position.shape == (3,) and abs(position[2]) < 0.5, position  # on the ground
    state = drone.flight_state()
    assert isinstance(state, platform_pb2.FlightStatus)
    assert 0.0 < state.battery_ratio <= 1.0
    battery = drone.battery()
    assert 0.0 < battery.charge_ratio <= 1.0 and battery.voltage_v > 0


def test_the_pose_estimate_follows_the_flight_and_goes_stale_after(fleet):
    drone = fleet.robot("drone2")
    localize = drone.self_localize_with_ground_truth.start()
    try:
        estimate = wait_until(lambda: _or_none(drone.pose), 30, "a fresh pose estimate")
        truth = drone.sample("ground_truth_pose")
        assert nph.position(estimate) == pytest.approx(
            nph.position(behaviorlib._core.unpack_sample(truth)), abs=0.05)
        assert -math.pi < nph.yaw(estimate) <= math.pi
        up = drone.take_off.start(altitude_m=1.5)
        heights = []
        with drone.subscribe("pose", max_rate_hz=50) as poses:
            for pose in poses:
                heights.append(nph.position(pose)[2])
                if heights[-1] > 1.0:
                    poses.close()
            # After close() the iteration has ended.
            assert list(poses) == []
        assert heights[0] < heights[-1] and heights[-1] > 1.0, heights
        assert up.wait(120).cause == "GOAL_ACHIEVED"
        twist = drone.twist()
        assert nph.velocity(twist).shape == (3,)
        assert drone.land().cause == "GOAL_ACHIEVED"
    finally:
        localize.deactivate()
    # Nothing publishes the estimate any more: once it is older than the
    # limit, a read is refused as stale, and still given without a limit.
    error = wait_until(lambda: _stale(lambda: drone.pose(max_age_s=0.5)), 60, "a stale estimate")
    assert isinstance(error, behaviorlib.FailedPrecondition)
    assert error.reason == "SAMPLE_STALE"
    assert error.metadata["topic"] == "robots/drone2/self_localization/pose"
    assert float(error.metadata["age_s"]) > float(error.metadata["max_age_s"]) == 0.5
    assert drone.pose(max_age_s=None).header.robot_id == "drone2"


def test_bad_requests_get_a_status_with_details(fleet):
    drone = fleet.robot("drone1")
    with pytest.raises(ValueError, match="imu"):
        drone.sample("thermometer")
    stub = fleet._stub
    with pytest.raises(grpc.RpcError) as raw:
        stub.GetVehicleSample(coordinator_pb2.GetVehicleSampleRequest(robot_id="drone1", kind=99))
    error = behaviorlib.errors.from_rpc_error(raw.value)
    assert isinstance(error, behaviorlib.InvalidArgument)
    assert [field for field, _ in error.field_violations] == ["kind"]
    # A robot the coordinator does not know (fleet.robot() would refuse it
    # first: the call is made as it would be).
    with pytest.raises(behaviorlib.NotFound) as unknown:
        behaviorlib.client._call(
            stub.GetVehicleSample,
            coordinator_pb2.GetVehicleSampleRequest(
                robot_id="drone9", kind=coordinator_pb2.VEHICLE_SAMPLE_KIND_POSE),
            fleet._credentials)
    assert unknown.value.reason == "UNKNOWN_ROBOT" and unknown.value.metadata["robot"] == "drone9"
    with pytest.raises(behaviorlib.InvalidArgument) as rate:
        list(drone.subscribe("imu", max_rate_hz=1000))
    assert [field for field, _ in rate.value.field_violations] == ["max_rate_hz"]


def test_watches_are_bounded_per_caller_and_a_closed_one_frees_its_place(fleet, stack):
    drone = fleet.robot("drone1")
    # The coordinator's default --max-vehicle-watches is 64: a caller (here
    # its address) may hold 16.
    watches = [drone.subscribe("flight_state", max_rate_hz=1) for _ in range(16)]
    try:
        for watch in watches:
            assert next(watch).header.robot_id == "drone1"
        extra = drone.subscribe("flight_state", max_rate_hz=1)
        with pytest.raises(behaviorlib.ResourceExhausted) as refused:
            next(extra)
        assert refused.value.reason == "LIMIT_EXCEEDED" and refused.value.metadata["limit"] == "16"
        watches.pop().close()
        # The slot is freed once the coordinator saw the cancellation.
        again = wait_until(lambda: _opened(drone), 10, "a watch after one was closed")
        watches.append(again)
        assert _open_watches(stack) == 16
    finally:
        for watch in watches:
            watch.close()
    # Every subscription has ended (the coordinator's gauge): nothing leaks.
    wait_until(lambda: _open_watches(stack) == 0, 30, "every watch ended")


def test_a_watch_is_rate_limited_and_reads_come_back_quickly(fleet):
    drone = fleet.robot("drone1")
    # The deterministic mode runs faster than the wall clock: far more
    # than 10 samples a wall second are published, and the rate caps them.
    with drone.subscribe("ground_truth_pose", max_rate_hz=10) as poses:
        next(poses)
        start = time.monotonic()
        count = 0
        for _ in poses:
            count += 1
            if time.monotonic() - start >= 1.0:
                break
    elapsed = time.monotonic() - start
    assert 1 <= count <= 10 * elapsed + 2, (count, elapsed)
    durations = []
    for _ in range(100):
        begin = time.perf_counter()
        drone.sample("ground_truth_pose")
        durations.append(time.perf_counter() - begin)
    assert statistics.median(durations) <= READ_MEDIAN_LIMIT_S, sorted(durations)[50]


def test_the_asyncio_client_reads_and_subscribes(coordinator):
    async def main():
        async with aio.Fleet(coordinator) as fleet:
            drone = await fleet.robot("drone1")
            state = await drone.flight_state()
            battery = await drone.battery()
            got = []
            poses = drone.subscribe("ground_truth_pose", max_rate_hz=20)

            async def read():
                async for pose in poses:
                    got.append(pose)
            reader = asyncio.get_running_loop().create_task(read())
            while len(got) < 3:
                await asyncio.sleep(0.05)
            await poses.close()
            await asyncio.wait_for(reader, 10)  # the iteration ended cleanly
            with pytest.raises(ValueError):
                await drone.sample("thermometer")
            return state, battery, got

    state, battery, got = asyncio.run(asyncio.wait_for(main(), 60))
    assert state.header.robot_id == "drone1" and 0 < battery.charge_ratio <= 1
    assert len(got) >= 3 and all(p.header.robot_id == "drone1" for p in got)


def _or_none(read):
    try:
        return read()
    except (behaviorlib.NotFound, behaviorlib.Stale):
        return None


def _stale(read):
    try:
        read()
    except behaviorlib.Stale as error:
        return error
    return None


def _open_watches(stack):
    """The coordinator's behaviorlib_coordinator_vehicle_watches gauge."""
    port = stack.ports("coordinator")["metrics_port"]
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=10) as reply:
        text = reply.read().decode()
    match = re.search(r"^behaviorlib_coordinator_vehicle_watches (\S+)$", text, re.M)
    assert match, "no vehicle_watches gauge"
    return int(float(match.group(1)))


def _opened(drone):
    watch = drone.subscribe("flight_state", max_rate_hz=1)
    try:
        next(watch)
    except behaviorlib.ResourceExhausted:
        watch.close()
        return None
    return watch
