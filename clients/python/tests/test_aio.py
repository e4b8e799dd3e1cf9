"""The asyncio client against the real stack (conftest.py): two vehicles
flown at once, beliefs and a mission, with coroutines."""

import asyncio
import inspect

import pytest

import behaviorlib
from behaviorlib import aio


def run(coroutine):
    return asyncio.run(asyncio.wait_for(coroutine, 240))


def test_two_vehicles_take_off_and_land_at_once(coordinator):
    async def fly(fleet, robot_id):
        drone = await fleet.robot(robot_id)
        assert inspect.signature(drone.take_off).parameters["altitude_m"].default == 1.0
        localize = await drone.self_localize_with_ground_truth.start()
        up = await drone.take_off(altitude_m=1.2)
        down = await drone.land()
        await localize.deactivate()
        return up, down

    async def main():
        async with aio.Fleet(coordinator) as fleet:
            return await asyncio.gather(fly(fleet, "drone1"), fly(fleet, "drone2"))

    for robot_id, (up, down) in zip(("drone1", "drone2"), run(main())):
        assert (up.robot_id, up.cause, up.parameters) == (robot_id, "GOAL_ACHIEVED",
                                                          {"altitude_m": 1.2}), up
        assert (down.robot_id, down.cause) == (robot_id, "GOAL_ACHIEVED"), down


def test_errors_are_raised_as_behaviorlib_errors(coordinator):
    async def main():
        async with aio.Fleet(coordinator) as fleet:
            with pytest.raises(behaviorlib.NotFound):
                await fleet.robot("drone9")
            drone = await fleet.robot("drone1")
            with pytest.raises(behaviorlib.InvalidArgument, match="altitude_m"):
                await drone.take_off(altitude_m=1000)
            with pytest.raises(TypeError, match="height"):
                await drone.take_off(height=1)
            with pytest.raises(behaviorlib.FailedPrecondition):
                await drone.kill()

    run(main())


def test_beliefs_and_a_mission(coordinator):
    async def main():
        async with aio.Fleet(coordinator) as fleet:
            first = await fleet.beliefs.write("pytest/aio/x", [1, 2], writer="pytest")
            assert await fleet.beliefs.get("pytest/aio/x") == [1, 2]
            watched = []

            async def watch():
                async for belief in fleet.beliefs.watch("pytest/aio/", first.version):
                    watched.append(belief)
                    if belief.deleted:
                        return

            watcher = asyncio.get_running_loop().create_task(watch())
            second = await fleet.beliefs.write("pytest/aio/x", "y", writer="pytest")
            while not any(b.version == second.version for b in watched):
                await asyncio.sleep(0.05)
            await fleet.beliefs.delete("pytest/aio/x", writer="pytest")
            await asyncio.wait_for(watcher, 30)
            assert [(aio.Beliefs.value(b), b.deleted) for b in watched] == [("y", False),
                                                                            (None, True)]

            text = "{name: short_wait, steps: [{behavior: WAIT, parameters: {duration_s: 0.5}}]}"
            status = await fleet.missions.run(text=text, robot_id="drone2", timeout_s=120)
            assert behaviorlib.mission_state(status) == "SUCCEEDED", status
            assert [s.behavior for s in status.steps] == ["WAIT"]
            listed = [m.mission_id for m in await fleet.missions.list()]
            assert status.mission_id in listed

    run(main())
