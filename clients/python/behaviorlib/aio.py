"""The asyncio client (grpc.aio): the same API as behaviorlib.Fleet, with
coroutines.

    from behaviorlib import aio

    async with aio.Fleet("127.0.0.1:50060") as fleet:
        drone = await fleet.robot("drone1")
        await drone.self_localize_with_ground_truth.start()
        result = await drone.take_off(altitude_m=1.5)
        async for status in fleet.missions.watch(mission_id):
            ...
"""

import asyncio

import grpc
from grpc import aio as grpc_aio

from behaviorlib import _core
from behaviorlib.errors import (Cancelled, DeadlineExceeded, Error, FailedPrecondition, NotFound,
                                Unavailable, from_rpc_error)
from behaviorlib.v1 import coordinator_pb2, coordinator_pb2_grpc

Termination = _core.Termination


async def _call(method, request, credentials, timeout_s=_core.DEFAULT_TIMEOUT_S):
    try:
        return await method(request, timeout=timeout_s, metadata=credentials.metadata())
    except grpc.RpcError as error:
        raise from_rpc_error(error) from None


async def _pages(method, request, items, credentials):
    request.page_size = _core.PAGE_SIZE
    out = []
    while True:
        reply = await _call(method, request, credentials)
        out += list(getattr(reply, items))
        if not reply.next_page_token:
            return out
        request.page_token = reply.next_page_token


async def _resuming(fleet, open_stream, ends=lambda reply: False):
    """The replies of the stream that `open_stream()` opens, opened again
    after a back-off when it breaks with a retryable code (the coordinator
    restarted) or ends early; stops after the reply for which `ends(reply)`
    is true, or quietly once the fleet is closed."""
    backoff = _core.Backoff()
    while not fleet.closed:
        try:
            async for reply in open_stream():
                backoff.reset()
                yield reply
                if ends(reply):
                    return
        except grpc.RpcError as error:
            if fleet.closed:
                return
            if not _core.retryable(error):
                raise from_rpc_error(error) from None
        await asyncio.sleep(backoff.next_delay_s())


class _EventPump:
    """As client._EventPump, as a task of the running event loop."""

    def __init__(self, fleet):
        self._fleet = fleet
        self._cursor = _core.EventCursor()
        self._terminations = _core.Terminations()
        self._changed = asyncio.Condition()
        self._started = False
        self._error = None
        self._task = asyncio.get_running_loop().create_task(self._run(),
                                                            name="behaviorlib-events")

    def _over(self):
        return self._error is not None or self._fleet.closed

    def _raise_over(self):
        if self._error is not None:
            raise self._error
        raise Cancelled(grpc.StatusCode.CANCELLED, "the client was closed")

    async def wait_started(self, timeout_s):
        async with self._changed:
            try:
                await asyncio.wait_for(
                    self._changed.wait_for(lambda: self._started or self._over()), timeout_s)
            except asyncio.TimeoutError:
                raise Unavailable(grpc.StatusCode.UNAVAILABLE,
                                  "the coordinator's event stream did not start within "
                                  f"{timeout_s} s") from None
            if not self._started:
                self._raise_over()

    async def wait(self, activation_id, timeout_s):
        async with self._changed:
            try:
                await asyncio.wait_for(self._changed.wait_for(
                    lambda: self._terminations.get(activation_id) is not None or self._over()),
                    timeout_s)
            except asyncio.TimeoutError:
                raise DeadlineExceeded(grpc.StatusCode.DEADLINE_EXCEEDED,
                                       f"activation {activation_id} did not finish within "
                                       f"{timeout_s} s") from None
            termination = self._terminations.get(activation_id)
        if termination is None:
            self._raise_over()
        return termination

    def _open(self):
        return self._fleet._stub.WatchEvents(self._cursor.request(),
                                             metadata=self._fleet._credentials.metadata())

    async def _run(self):
        try:
            async for response in _resuming(self._fleet, self._open):
                fresh = self._cursor.accept(response)
                async with self._changed:
                    self._started = self._started or response.WhichOneof("kind") == "start"
                    for event in fresh:
                        self._terminations.add(event)
                    self._changed.notify_all()
        except Error as error:
            async with self._changed:
                self._error = error
                self._changed.notify_all()

    async def close(self):
        """After the fleet is marked closed: wakes the waiters, ends the task."""
        async with self._changed:
            self._changed.notify_all()
        self._task.cancel()
        try:
            await self._task
        except asyncio.CancelledError:
            pass


class Activation:
    """One activation of a behavior (see client.Activation)."""

    def __init__(self, robot, behavior, reply):
        self.robot = robot
        self.behavior = behavior
        self.reply = reply
        self.id = reply.activation.activation_id
        self.parameters = _core.from_struct(reply.activation.parameters)

    async def wait(self, timeout_s=None):
        return await (await self.robot.fleet._pump()).wait(self.id, timeout_s)

    async def deactivate(self):
        return await self.robot.deactivate(self.behavior, activation_id=self.id)

    async def pause(self):
        return await self.robot.pause(self.behavior, activation_id=self.id)

    async def resume(self):
        return await self.robot.resume(self.behavior, activation_id=self.id)

    async def modify(self, **parameters):
        return await self.robot.modify(self.behavior, parameters, activation_id=self.id)

    async def check(self):
        return await self.robot.check_activation(self.behavior)

    def __repr__(self):
        return f"Activation({self.robot.id}/{self.behavior} {self.id})"


class BehaviorMethod:
    """A robot's behavior as a coroutine method (see client.BehaviorMethod)."""

    def __init__(self, robot, spec):
        self._robot = robot
        self.spec = spec
        self.__name__ = spec.method
        self.__signature__ = spec.signature()
        self.__doc__ = spec.doc("Returns (awaited) the Termination (cause, message, ...).")

    async def __call__(self, **parameters):
        return await (await self.start(**parameters)).wait()

    async def start(self, **parameters):
        return await self._robot.activate(self.spec.name, self.spec.bind(parameters), wait=False)

    async def check_situation(self):
        return await self._robot.check_situation(self.spec.name)

    async def check_activation(self):
        return await self._robot.check_activation(self.spec.name)

    def __repr__(self):
        return f"<behavior {self._robot.id}.{self.spec.method}{self.__signature__}>"


class Samples:
    """As client.Samples, an async iterator:

        async with drone.subscribe("imu", max_rate_hz=20) as imu:
            async for sample in imu:
                ...
    """

    def __init__(self, fleet, request):
        self._fleet = fleet
        self._request = request
        self._call = None
        self._closed = False
        self.dropped = 0
        self.last = None
        self._replies = _resuming(fleet, self._open, ends=lambda reply: self._closed)

    def _open(self):
        self._call = self._fleet._stub.WatchVehicle(self._request,
                                                    metadata=self._fleet._credentials.metadata())
        return self._call

    def __aiter__(self):
        return self

    async def __anext__(self):
        if self._closed:
            raise StopAsyncIteration
        try:
            reply = await self._replies.__anext__()
        except (asyncio.CancelledError, grpc.RpcError, Cancelled):
            if self._closed:
                raise StopAsyncIteration from None
            raise
        if self._closed:
            raise StopAsyncIteration
        self.dropped = reply.dropped_count
        self.last = reply.sample
        return _core.unpack_sample(reply.sample)

    async def close(self):
        """Ends the stream: an iteration waiting in another task stops."""
        self._closed = True
        if self._call is not None:
            self._call.cancel()

    async def __aenter__(self):
        return self

    async def __aexit__(self, *exc):
        await self.close()


class Robot(_core.RobotMethods):
    """One robot: a coroutine method per behavior, its safety actions, and
    its vehicle's state."""

    def __init__(self, fleet, robot_id, specs):
        super().__init__(fleet, robot_id, specs, BehaviorMethod)

    async def activate(self, behavior, parameters=None, *, wait=True, timeout_s=None,
                       request_id="", skip_plan=False):
        await (await self.fleet._pump()).wait_started(_core.DEFAULT_TIMEOUT_S)
        reply = await _call(self.fleet._stub.ActivateBehavior,
                            _core.activate_request(self.id, behavior, parameters, request_id,
                                                   skip_plan),
                            self.fleet._credentials)
        activation = Activation(self, behavior, reply)
        return await activation.wait(timeout_s) if wait else activation

    async def plan(self, behavior, parameters=None):
        request = _core.activate_request(self.id, behavior, parameters, dry_run=True)
        return list((await _call(self.fleet._stub.ActivateBehavior, request,
                                 self.fleet._credentials)).plan)

    async def deactivate(self, behavior, activation_id=""):
        request = coordinator_pb2.DeactivateFleetBehaviorRequest(
            robot_id=self.id, behavior=behavior, activation_id=activation_id)
        return (await _call(self.fleet._stub.DeactivateBehavior, request,
                            self.fleet._credentials)).result

    async def check_situation(self, behavior):
        request = coordinator_pb2.CheckFleetBehaviorSituationRequest(robot_id=self.id,
                                                                     behavior=behavior)
        return (await _call(self.fleet._stub.CheckBehaviorSituation, request,
                            self.fleet._credentials)).situation

    async def _robot_call(self, name, behavior, **arguments):
        method, request, field = _core.robot_call(name, self.id, behavior, **arguments)
        reply = await _call(getattr(self.fleet._stub, method), request, self.fleet._credentials)
        return getattr(reply, field)

    async def pause(self, behavior, activation_id=""):
        return await self._robot_call("pause", behavior, activation_id=activation_id)

    async def resume(self, behavior, activation_id=""):
        return await self._robot_call("resume", behavior, activation_id=activation_id)

    async def modify(self, behavior, parameters, activation_id=""):
        return await self._robot_call("modify", behavior, activation_id=activation_id,
                                      parameters=parameters)

    async def check_activation(self, behavior):
        return await self._robot_call("check_activation", behavior)

    async def emergency_land(self, reason=""):
        request = coordinator_pb2.SafetyActionRequest(robot_id=self.id, reason=reason)
        return (await _call(self.fleet._stub.EmergencyLand, request,
                            self.fleet._credentials)).message

    async def kill(self, reason="", *, confirm=False):
        if not confirm:
            raise FailedPrecondition(grpc.StatusCode.FAILED_PRECONDITION,
                                     "kill turns the motors off; call it with confirm=True")
        request = coordinator_pb2.SafetyActionRequest(robot_id=self.id, confirm=True,
                                                      reason=reason)
        return (await _call(self.fleet._stub.Kill, request, self.fleet._credentials)).message

    async def run_mission(self, **source):
        return await self.fleet.missions.run(robot_id=self.id, **source)

    async def sample(self, name, *, max_age_s=_core.DEFAULT_MAX_AGE_S):
        """The newest VehicleSample of `name` (see client.Robot.sample)."""
        return (await _call(self.fleet._stub.GetVehicleSample,
                            _core.sample_request(self.id, name, max_age_s),
                            self.fleet._credentials)).sample

    async def pose(self, *, max_age_s=_core.DEFAULT_MAX_AGE_S):
        return _core.unpack_sample(await self.sample("pose", max_age_s=max_age_s))

    async def twist(self, *, max_age_s=_core.DEFAULT_MAX_AGE_S):
        return _core.unpack_sample(await self.sample("twist", max_age_s=max_age_s))

    async def flight_state(self, *, max_age_s=_core.DEFAULT_MAX_AGE_S):
        return _core.unpack_sample(await self.sample("flight_state", max_age_s=max_age_s))

    async def battery(self, *, max_age_s=_core.DEFAULT_MAX_AGE_S):
        return _core.unpack_sample(await self.sample("battery", max_age_s=max_age_s))

    def subscribe(self, name, *, max_rate_hz=10.0, latest_first=True):
        """The samples of `name` as they come: an async iterator (see
        client.Robot.subscribe) that ends once close() is called."""
        return Samples(self.fleet, _core.watch_vehicle_request(self.id, name, max_rate_hz,
                                                               latest_first))

    def __repr__(self):
        return f"Robot({self.id!r}, behaviors={sorted(self.behaviors)})"


class Missions:
    """Missions run by the coordinator (see client.Missions)."""

    def __init__(self, fleet):
        self._fleet = fleet

    async def start(self, *, file=None, text=None, server_file=None, robot_id="", mission_id="",
                    source_name=""):
        request = _core.mission_request(file, text, server_file, robot_id, mission_id,
                                        source_name)
        return (await _call(self._fleet._stub.StartMission, request,
                            self._fleet._credentials)).status

    async def check(self, *, file=None, text=None, server_file=None, robot_id="",
                    source_name=""):
        request = _core.mission_request(file, text, server_file, robot_id, "", source_name,
                                        check=True)
        return await _call(self._fleet._stub.CheckMission, request, self._fleet._credentials)

    async def get(self, mission_id):
        request = coordinator_pb2.GetMissionRequest(mission_id=mission_id)
        return (await _call(self._fleet._stub.GetMission, request, self._fleet._credentials)).status

    async def list(self):
        return await _pages(self._fleet._stub.ListMissions, coordinator_pb2.ListMissionsRequest(),
                            "missions", self._fleet._credentials)

    async def watch(self, mission_id):
        request = coordinator_pb2.WatchMissionRequest(mission_id=mission_id)
        metadata = self._fleet._credentials.metadata()
        async for reply in _resuming(self._fleet,
                                lambda: self._fleet._stub.WatchMission(request, metadata=metadata),
                                ends=lambda reply: reply.status.state in _core.MISSION_ENDED):
            yield reply.status

    async def wait(self, mission_id, timeout_s=None):
        async def last_status():
            last = None
            async for status in self.watch(mission_id):
                last = status
            return last

        try:
            status = await asyncio.wait_for(last_status(), timeout_s)
        except asyncio.TimeoutError:
            raise DeadlineExceeded(grpc.StatusCode.DEADLINE_EXCEEDED,
                                   f"mission {mission_id} did not end within {timeout_s} s") \
                from None
        if status is None or status.state not in _core.MISSION_ENDED:
            raise Error(grpc.StatusCode.UNKNOWN, f"mission {mission_id}'s stream ended early")
        return status

    async def run(self, *, timeout_s=None, **source):
        status = await self.start(**source)
        return await self.wait(status.mission_id, timeout_s)

    async def _control(self, method, mission_id, reason):
        request = coordinator_pb2.MissionControlRequest(mission_id=mission_id, reason=reason)
        return (await _call(method, request, self._fleet._credentials)).status

    async def pause(self, mission_id, reason=""):
        return await self._control(self._fleet._stub.PauseMission, mission_id, reason)

    async def resume(self, mission_id, reason=""):
        return await self._control(self._fleet._stub.ResumeMission, mission_id, reason)

    async def abort(self, mission_id, reason=""):
        return await self._control(self._fleet._stub.AbortMission, mission_id, reason)


class Beliefs:
    """The coordinator's belief memory (see client.Beliefs)."""

    def __init__(self, fleet):
        self._fleet = fleet

    async def read(self, key):
        request = coordinator_pb2.ReadBeliefRequest(key=key)
        return (await _call(self._fleet._stub.ReadBelief, request, self._fleet._credentials)).belief

    async def get(self, key, default=None):
        try:
            return self.value(await self.read(key))
        except NotFound:
            return default

    @staticmethod
    def value(belief):
        return _core.from_value(belief.value)

    async def write(self, key, value, *, type="", writer=""):  # noqa: A002 (the proto's name)
        request = coordinator_pb2.WriteBeliefRequest(key=key, value=_core.to_value(value),
                                                     type=type, writer=writer)
        return (await _call(self._fleet._stub.WriteBelief, request,
                            self._fleet._credentials)).belief

    async def delete(self, key, writer=""):
        request = coordinator_pb2.DeleteBeliefRequest(key=key, writer=writer)
        await _call(self._fleet._stub.DeleteBelief, request, self._fleet._credentials)

    async def list(self, prefix=""):
        return await _pages(self._fleet._stub.ListBeliefs,
                            coordinator_pb2.ListBeliefsRequest(prefix=prefix), "beliefs",
                            self._fleet._credentials)

    async def watch(self, prefix="", since_version=0):
        version = since_version
        metadata = self._fleet._credentials.metadata()

        def open_stream():
            return self._fleet._stub.WatchBeliefs(
                coordinator_pb2.WatchBeliefsRequest(prefix=prefix, since_version=version),
                metadata=metadata)

        async for reply in _resuming(self._fleet, open_stream):
            if reply.belief.version and reply.belief.version <= version:
                continue
            version = max(version, reply.belief.version)
            yield reply.belief


class Fleet:
    """The fleet through its coordinator (see client.Fleet). Create it inside
    the event loop that uses it."""

    def __init__(self, target, *, ca_file="", cert_file="", key_file="", token="",
                 server_name=""):
        self.target = target
        # True once close() was called: the streams then end quietly.
        self.closed = False
        self._credentials = _core.Credentials(ca_file, cert_file, key_file, token, server_name)
        self._channel = _core.open_channel(grpc_aio, target, self._credentials)
        self._stub = coordinator_pb2_grpc.CoordinatorStub(self._channel)
        self._event_pump = None
        self.missions = Missions(self)
        self.beliefs = Beliefs(self)

    async def _pump(self):
        if self._event_pump is None:
            self._event_pump = _EventPump(self)
        return self._event_pump

    async def robot(self, robot_id):
        specs = _core.specs_of(await self.behaviors(robot_id), robot_id)
        if not specs:
            raise NotFound(grpc.StatusCode.NOT_FOUND,
                           f"robot {robot_id!r} has no behavior system registered")
        return Robot(self, robot_id, specs)

    async def systems(self, robot_id=""):
        return await _pages(self._stub.ListSystems,
                            coordinator_pb2.ListSystemsRequest(robot_id=robot_id), "systems",
                            self._credentials)

    async def robots(self):
        return sorted({s.robot_id for s in await self.systems()})

    async def behaviors(self, robot_id="", behavior=""):
        return await _pages(self._stub.ListBehaviors, coordinator_pb2.ListFleetBehaviorsRequest(
            robot_id=robot_id, behavior=behavior), "behaviors", self._credentials)

    async def events(self, robot_ids=(), behaviors=(), *, since_seq=0, incarnation="",
                     cursor=None):
        cursor = cursor or _core.EventCursor(robot_ids, behaviors, since_seq, incarnation)
        async for response in _resuming(self, lambda: self._stub.WatchEvents(
                cursor.request(), metadata=self._credentials.metadata())):
            for event in cursor.accept(response):
                yield event

    async def close(self):
        self.closed = True
        if self._event_pump is not None:
            await self._event_pump.close()
        await self._channel.close()

    async def __aenter__(self):
        return self

    async def __aexit__(self, *exc):
        await self.close()
