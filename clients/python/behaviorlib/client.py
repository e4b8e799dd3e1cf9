"""The synchronous client.

    from behaviorlib import Fleet

    with Fleet("127.0.0.1:50060") as fleet:
        drone = fleet.robot("drone1")
        drone.self_localize_with_ground_truth.start()
        result = drone.take_off(altitude_m=1.5)      # waits for the termination
        print(result.cause, result.message)
        status = fleet.missions.run(file="deploy/missions/demo.yaml", robot_id="drone1")

Every failed call raises a behaviorlib.Error subclass (errors.py).
"""

import threading
import time

import grpc

from behaviorlib import _core
from behaviorlib.errors import (Cancelled, DeadlineExceeded, Error, FailedPrecondition, NotFound,
                               Unavailable, from_rpc_error)
from behaviorlib.v1 import coordinator_pb2, coordinator_pb2_grpc

Termination = _core.Termination


def _call(method, request, credentials, timeout_s=_core.DEFAULT_TIMEOUT_S):
    try:
        return method(request, timeout=timeout_s, metadata=credentials.metadata())
    except grpc.RpcError as error:
        raise from_rpc_error(error) from None


def _pages(method, request, items, credentials):
    """Every item of a paginated List call."""
    request.page_size = _core.PAGE_SIZE
    out = []
    while True:
        reply = _call(method, request, credentials)
        out += list(getattr(reply, items))
        if not reply.next_page_token:
            return out
        request.page_token = reply.next_page_token


def _resuming(fleet, open_stream, ends=lambda reply: False, closed=lambda: False):
    """The replies of the stream that `open_stream()` opens, opened again
    after a back-off when it breaks with a retryable code (the coordinator
    restarted) or ends early; stops after the reply for which `ends(reply)`
    is true, or quietly once the fleet is closed or `closed()` is true (the
    caller cancelled the stream)."""
    backoff = _core.Backoff()

    def over():
        return fleet.closed or closed()

    while not over():
        try:
            for reply in open_stream():
                backoff.reset()
                yield reply
                if ends(reply):
                    return
        except grpc.RpcError as error:
            if over():
                return
            if not _core.retryable(error):
                raise from_rpc_error(error) from None
        if over():
            return
        time.sleep(backoff.next_delay_s())


class _EventPump:
    """One WatchEvents stream of the whole fleet, kept open on a thread and
    resumed after a coordinator restart, feeding the finished activations to
    the callers waiting for them. A refusal that retrying cannot cure (e.g.
    PERMISSION_DENIED) is raised to every waiter."""

    def __init__(self, fleet):
        self._fleet = fleet
        self._cursor = _core.EventCursor()
        self._terminations = _core.Terminations()
        self._changed = threading.Condition()
        self._started = False
        self._error = None
        self._call = None
        self._thread = threading.Thread(target=self._run, name="behaviorlib-events", daemon=True)
        self._thread.start()

    def _over(self):
        return self._error is not None or self._fleet.closed

    def _raise_over(self):
        if self._error is not None:
            raise self._error
        raise Cancelled(grpc.StatusCode.CANCELLED, "the client was closed")

    def wait_started(self, timeout_s):
        """Blocks until the stream has its start message: from then on every
        new finished event reaches the index."""
        with self._changed:
            if not self._changed.wait_for(lambda: self._started or self._over(), timeout_s):
                raise Unavailable(grpc.StatusCode.UNAVAILABLE,
                                  f"the coordinator's event stream did not start within {timeout_s} s")
            if not self._started:
                self._raise_over()

    def wait(self, activation_id, timeout_s):
        with self._changed:
            done = self._changed.wait_for(
                lambda: self._terminations.get(activation_id) is not None or self._over(),
                timeout_s)
            termination = self._terminations.get(activation_id)
        if termination is not None:
            return termination
        if not done:
            raise DeadlineExceeded(grpc.StatusCode.DEADLINE_EXCEEDED,
                                   f"activation {activation_id} did not finish within "
                                   f"{timeout_s} s")
        self._raise_over()

    def _open(self):
        self._call = self._fleet._stub.WatchEvents(self._cursor.request(),
                                                   metadata=self._fleet._credentials.metadata())
        return self._call

    def _run(self):
        try:
            for response in _resuming(self._fleet, self._open):
                fresh = self._cursor.accept(response)
                with self._changed:
                    self._started = self._started or response.WhichOneof("kind") == "start"
                    for event in fresh:
                        self._terminations.add(event)
                    self._changed.notify_all()
        except Error as error:
            with self._changed:
                self._error = error
                self._changed.notify_all()

    def close(self):
        """After the fleet is marked closed: ends the stream and the thread."""
        with self._changed:
            self._changed.notify_all()
        if self._call is not None:
            self._call.cancel()
        self._thread.join(timeout=5)


class Activation:
    """One activation of a behavior: its id and reply, and what can be done
    with it until it finishes."""

    def __init__(self, robot, behavior, reply):
        self.robot = robot
        self.behavior = behavior
        # The coordinator's ActivateFleetBehaviorResponse.
        self.reply = reply
        self.id = reply.activation.activation_id
        self.parameters = _core.from_struct(reply.activation.parameters)

    def wait(self, timeout_s=None):
        """Its Termination, once its finished event arrived."""
        return self.robot.fleet._pump().wait(self.id, timeout_s)

    def deactivate(self):
        return self.robot.deactivate(self.behavior, activation_id=self.id)

    def pause(self):
        return self.robot.pause(self.behavior, activation_id=self.id)

    def resume(self):
        return self.robot.resume(self.behavior, activation_id=self.id)

    def modify(self, **parameters):
        """Changes the given parameters; the others keep their values."""
        return self.robot.modify(self.behavior, parameters, activation_id=self.id)

    def check(self):
        """The behavior's CheckActivationResponse (state, parameters, ...)."""
        return self.robot.check_activation(self.behavior)

    def __repr__(self):
        return f"Activation({self.robot.id}/{self.behavior} {self.id})"


class BehaviorMethod:
    """A robot's behavior as a method: calling it activates the behavior and
    waits for its termination; .start() activates it and returns the
    Activation. Made from the behavior's descriptor (_core.BehaviorSpec)."""

    def __init__(self, robot, spec):
        self._robot = robot
        self.spec = spec
        self.__name__ = spec.method
        self.__signature__ = spec.signature()
        self.__doc__ = spec.doc("Returns the Termination (cause, message, ...).")

    def __call__(self, **parameters):
        return self.start(**parameters).wait()

    def start(self, **parameters):
        return self._robot.activate(self.spec.name, self.spec.bind(parameters), wait=False)

    def check_situation(self):
        return self._robot.check_situation(self.spec.name)

    def check_activation(self):
        return self._robot.check_activation(self.spec.name)

    def __repr__(self):
        return f"<behavior {self._robot.id}.{self.spec.method}{self.__signature__}>"


class Samples:
    """A vehicle's samples as they come (Robot.subscribe): an iterator of
    the API's messages that ends cleanly once close() is called (or the fleet
    is closed), and opens its stream again after a coordinator restart.

        with drone.subscribe("imu", max_rate_hz=20) as imu:
            for sample in imu:
                ...

    `dropped` counts the samples skipped so far (the rate limit, or a slow
    reader); `last` is the newest VehicleSample (its age and topic_seq)."""

    def __init__(self, fleet, request):
        self._fleet = fleet
        self._request = request
        self._lock = threading.Lock()
        self._call = None
        self._closed = False
        self.dropped = 0
        self.last = None
        self._replies = _resuming(fleet, self._open, closed=lambda: self._closed)

    def _open(self):
        with self._lock:
            if self._closed:
                return iter(())
            self._call = self._fleet._stub.WatchVehicle(
                self._request, metadata=self._fleet._credentials.metadata())
            return self._call

    def __iter__(self):
        return self

    def __next__(self):
        reply = next(self._replies)
        self.dropped = reply.dropped_count
        self.last = reply.sample
        return _core.unpack_sample(reply.sample)

    def close(self):
        """Ends the stream; the iteration then stops."""
        with self._lock:
            self._closed = True
            if self._call is not None:
                self._call.cancel()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class Robot(_core.RobotMethods):
    """One robot of the fleet: a method per behavior its systems host
    (TAKE_OFF -> take_off), its safety actions, and its vehicle's state
    (pose, twist, flight_state, battery, subscribe)."""

    def __init__(self, fleet, robot_id, specs):
        super().__init__(fleet, robot_id, specs, BehaviorMethod)

    def refresh(self):
        """Reads the robot's behaviors again (a system registered since)."""
        fresh = self.fleet.robot(self.id)
        self.behaviors, self._methods = fresh.behaviors, fresh._methods
        for method in self._methods.values():
            method._robot = self

    def activate(self, behavior, parameters=None, *, wait=True, timeout_s=None, request_id="",
                 skip_plan=False):
        """Activates `behavior` with the catalog's plan. wait=True: returns
        its Termination; wait=False: the Activation."""
        # The fleet's event stream is open before the activation, so its
        # finished event reaches the index even when it comes at once.
        self.fleet._pump().wait_started(_core.DEFAULT_TIMEOUT_S)
        reply = _call(self.fleet._stub.ActivateBehavior,
                      _core.activate_request(self.id, behavior, parameters, request_id, skip_plan),
                      self.fleet._credentials)
        activation = Activation(self, behavior, reply)
        return activation.wait(timeout_s) if wait else activation

    def plan(self, behavior, parameters=None):
        """The catalog's plan for activating `behavior` (a dry run)."""
        request = _core.activate_request(self.id, behavior, parameters, dry_run=True)
        return list(_call(self.fleet._stub.ActivateBehavior, request, self.fleet._credentials).plan)

    def deactivate(self, behavior, activation_id=""):
        request = coordinator_pb2.DeactivateFleetBehaviorRequest(
            robot_id=self.id, behavior=behavior, activation_id=activation_id)
        return _call(self.fleet._stub.DeactivateBehavior, request, self.fleet._credentials).result

    def check_situation(self, behavior):
        request = coordinator_pb2.CheckFleetBehaviorSituationRequest(robot_id=self.id,
                                                                     behavior=behavior)
        return _call(self.fleet._stub.CheckBehaviorSituation, request,
                     self.fleet._credentials).situation

    def _robot_call(self, name, behavior, **arguments):
        method, request, field = _core.robot_call(name, self.id, behavior, **arguments)
        reply = _call(getattr(self.fleet._stub, method), request, self.fleet._credentials)
        return getattr(reply, field)

    def pause(self, behavior, activation_id=""):
        """Pauses the behavior's activation; returns the PauseResponse."""
        return self._robot_call("pause", behavior, activation_id=activation_id)

    def resume(self, behavior, activation_id=""):
        """Resumes the behavior's paused activation; returns the ResumeResponse."""
        return self._robot_call("resume", behavior, activation_id=activation_id)

    def modify(self, behavior, parameters, activation_id=""):
        """Changes some parameters of the behavior's activation (a dict; the
        others keep their values); returns the ModifyResponse."""
        return self._robot_call("modify", behavior, activation_id=activation_id,
                                parameters=parameters)

    def check_activation(self, behavior):
        """Whether the behavior is active, with which parameters, since when
        (a CheckActivationResponse)."""
        return self._robot_call("check_activation", behavior)

    def emergency_land(self, reason=""):
        """Hover and land now: every behavior deactivated, the mission
        aborted. Returns what was done."""
        request = coordinator_pb2.SafetyActionRequest(robot_id=self.id, reason=reason)
        return _call(self.fleet._stub.EmergencyLand, request, self.fleet._credentials).message

    def kill(self, reason="", *, confirm=False):
        """Motors off: the vehicle falls. Refused unless confirm=True."""
        if not confirm:
            raise FailedPrecondition(grpc.StatusCode.FAILED_PRECONDITION,
                                     "kill turns the motors off; call it with confirm=True")
        request = coordinator_pb2.SafetyActionRequest(robot_id=self.id, confirm=True,
                                                      reason=reason)
        return _call(self.fleet._stub.Kill, request, self.fleet._credentials).message

    def run_mission(self, **source):
        """Starts a mission for this robot and waits for its end (see
        Missions.run)."""
        return self.fleet.missions.run(robot_id=self.id, **source)

    def sample(self, name, *, max_age_s=_core.DEFAULT_MAX_AGE_S):
        """The newest VehicleSample of `name` ("pose", "twist",
        "flight_state", "battery", "imu", "gps", "baro", "linear_speed",
        "ground_truth_pose", "ground_truth_twist"), with its stamp and its age
        in the vehicles' time. NotFound when there is none yet; Stale when it
        is older than max_age_s (None: no limit)."""
        return _call(self.fleet._stub.GetVehicleSample,
                     _core.sample_request(self.id, name, max_age_s),
                     self.fleet._credentials).sample

    def pose(self, *, max_age_s=_core.DEFAULT_MAX_AGE_S):
        """The pose estimate (PoseStamped) of the robot's localization."""
        return _core.unpack_sample(self.sample("pose", max_age_s=max_age_s))

    def twist(self, *, max_age_s=_core.DEFAULT_MAX_AGE_S):
        """The velocity estimate (TwistStamped)."""
        return _core.unpack_sample(self.sample("twist", max_age_s=max_age_s))

    def flight_state(self, *, max_age_s=_core.DEFAULT_MAX_AGE_S):
        """The platform's FlightStatus (state, lease holder, battery ratio)."""
        return _core.unpack_sample(self.sample("flight_state", max_age_s=max_age_s))

    def battery(self, *, max_age_s=_core.DEFAULT_MAX_AGE_S):
        """The BatteryState (charge_ratio, voltage_v, current_a)."""
        return _core.unpack_sample(self.sample("battery", max_age_s=max_age_s))

    def subscribe(self, name, *, max_rate_hz=10.0, latest_first=True):
        """The samples of `name` as they come, at most max_rate_hz a second
        (0: the coordinator's default; at most 200): a Samples iterator."""
        return Samples(self.fleet, _core.watch_vehicle_request(self.id, name, max_rate_hz,
                                                               latest_first))

    def __repr__(self):
        return f"Robot({self.id!r}, behaviors={sorted(self.behaviors)})"


class Missions:
    """Missions run by the coordinator."""

    def __init__(self, fleet):
        self._fleet = fleet

    def start(self, *, file=None, text=None, server_file=None, robot_id="", mission_id="",
              source_name=""):
        """Starts a mission from a local `file`, its `text`, or a
        `server_file` in the coordinator's --mission-dir; returns its
        MissionStatus."""
        request = _core.mission_request(file, text, server_file, robot_id, mission_id,
                                        source_name)
        return _call(self._fleet._stub.StartMission, request, self._fleet._credentials).status

    def check(self, *, file=None, text=None, server_file=None, robot_id="", source_name=""):
        """Checks a mission without starting it; returns the
        CheckMissionResponse: every problem (`problems`, each with its file,
        line and field; empty when the mission would start) and each step's
        plan (`plans`)."""
        request = _core.mission_request(file, text, server_file, robot_id, "", source_name,
                                        check=True)
        return _call(self._fleet._stub.CheckMission, request, self._fleet._credentials)

    def get(self, mission_id):
        request = coordinator_pb2.GetMissionRequest(mission_id=mission_id)
        return _call(self._fleet._stub.GetMission, request, self._fleet._credentials).status

    def list(self):
        return _pages(self._fleet._stub.ListMissions, coordinator_pb2.ListMissionsRequest(),
                      "missions", self._fleet._credentials)

    def watch(self, mission_id, timeout_s=None):
        """Its MissionStatus after each change, until it has ended; the stream
        is opened again after a coordinator restart (the mission is kept in
        its journal). DeadlineExceeded after `timeout_s` (None: no limit)."""
        request = coordinator_pb2.WatchMissionRequest(mission_id=mission_id)
        metadata = self._fleet._credentials.metadata()
        deadline = None if timeout_s is None else time.monotonic() + timeout_s

        def open_stream():
            remaining = None if deadline is None else max(0.0, deadline - time.monotonic())
            return self._fleet._stub.WatchMission(request, metadata=metadata, timeout=remaining)

        try:
            yield from (reply.status for reply in _resuming(
                self._fleet, open_stream,
                ends=lambda reply: reply.status.state in _core.MISSION_ENDED))
        except DeadlineExceeded:
            raise DeadlineExceeded(grpc.StatusCode.DEADLINE_EXCEEDED,
                                   f"mission {mission_id} did not end within {timeout_s} s") \
                from None

    def wait(self, mission_id, timeout_s=None):
        """Its final MissionStatus; DeadlineExceeded after `timeout_s`."""
        last = None
        for status in self.watch(mission_id, timeout_s):
            last = status
        if last is None or last.state not in _core.MISSION_ENDED:
            raise Error(grpc.StatusCode.UNKNOWN, f"mission {mission_id}'s stream ended early")
        return last

    def run(self, *, timeout_s=None, **source):
        """start() then wait(): the final MissionStatus."""
        status = self.start(**source)
        return self.wait(status.mission_id, timeout_s)

    def _control(self, method, mission_id, reason):
        request = coordinator_pb2.MissionControlRequest(mission_id=mission_id, reason=reason)
        return _call(method, request, self._fleet._credentials).status

    def pause(self, mission_id, reason=""):
        return self._control(self._fleet._stub.PauseMission, mission_id, reason)

    def resume(self, mission_id, reason=""):
        return self._control(self._fleet._stub.ResumeMission, mission_id, reason)

    def abort(self, mission_id, reason=""):
        return self._control(self._fleet._stub.AbortMission, mission_id, reason)


class Beliefs:
    """The coordinator's belief memory. Values are plain Python (what JSON
    holds) or protobuf messages (stored in their JSON form)."""

    def __init__(self, fleet):
        self._fleet = fleet

    def read(self, key):
        """The Belief (value: Beliefs.value(belief))."""
        request = coordinator_pb2.ReadBeliefRequest(key=key)
        return _call(self._fleet._stub.ReadBelief, request, self._fleet._credentials).belief

    def get(self, key, default=None):
        """The value of `key`, or `default` when there is no such belief."""
        try:
            return self.value(self.read(key))
        except Error as error:
            if error.code == grpc.StatusCode.NOT_FOUND:
                return default
            raise

    @staticmethod
    def value(belief):
        return _core.from_value(belief.value)

    def write(self, key, value, *, type="", writer=""):  # noqa: A002 (the proto's name)
        request = coordinator_pb2.WriteBeliefRequest(key=key, value=_core.to_value(value),
                                                     type=type, writer=writer)
        return _call(self._fleet._stub.WriteBelief, request, self._fleet._credentials).belief

    def delete(self, key, writer=""):
        request = coordinator_pb2.DeleteBeliefRequest(key=key, writer=writer)
        _call(self._fleet._stub.DeleteBelief, request, self._fleet._credentials)

    def list(self, prefix=""):
        return _pages(self._fleet._stub.ListBeliefs, coordinator_pb2.ListBeliefsRequest(
            prefix=prefix), "beliefs", self._fleet._credentials)

    def watch(self, prefix="", since_version=0):
        """Every change (Belief, deleted=True for a removal) under `prefix`:
        first the current beliefs (since_version=0), then each write; the
        stream is opened again after a coordinator restart, from the last
        version seen."""
        version = since_version
        metadata = self._fleet._credentials.metadata()

        def open_stream():
            return self._fleet._stub.WatchBeliefs(
                coordinator_pb2.WatchBeliefsRequest(prefix=prefix, since_version=version),
                metadata=metadata)

        for reply in _resuming(self._fleet, open_stream):
            if reply.belief.version and reply.belief.version <= version:
                continue
            version = max(version, reply.belief.version)
            yield reply.belief


class Fleet:
    """The fleet, through its coordinator at `target` ("host:port").

    TLS: ca_file, cert_file and key_file (PEM, as the servers' --tls-*
    flags); a bearer token with token=... (both may be given)."""

    def __init__(self, target, *, ca_file="", cert_file="", key_file="", token="",
                 server_name=""):
        self.target = target
        # True once close() was called: the streams then end quietly.
        self.closed = False
        self._credentials = _core.Credentials(ca_file, cert_file, key_file, token, server_name)
        self._channel = _core.open_channel(grpc, target, self._credentials)
        self._stub = coordinator_pb2_grpc.CoordinatorStub(self._channel)
        self._pump_lock = threading.Lock()
        self._event_pump = None
        self.missions = Missions(self)
        self.beliefs = Beliefs(self)

    def _pump(self):
        with self._pump_lock:
            if self._event_pump is None:
                self._event_pump = _EventPump(self)
            return self._event_pump

    def robot(self, robot_id):
        """The Robot, with a method per behavior its systems host now."""
        specs = _core.specs_of(self.behaviors(robot_id), robot_id)
        if not specs:
            raise NotFound(grpc.StatusCode.NOT_FOUND,
                           f"robot {robot_id!r} has no behavior system registered")
        return Robot(self, robot_id, specs)

    def systems(self, robot_id=""):
        return _pages(self._stub.ListSystems, coordinator_pb2.ListSystemsRequest(
            robot_id=robot_id), "systems", self._credentials)

    def robots(self):
        return sorted({s.robot_id for s in self.systems()})

    def behaviors(self, robot_id="", behavior=""):
        """The coordinator's FleetBehaviors (every page)."""
        return _pages(self._stub.ListBehaviors, coordinator_pb2.ListFleetBehaviorsRequest(
            robot_id=robot_id, behavior=behavior), "behaviors", self._credentials)

    def events(self, robot_ids=(), behaviors=(), *, since_seq=0, incarnation="",
               cursor=None):
        """FleetEvents, replayed then live, forever: the stream is opened
        again after a coordinator restart and resumes without a gap or a
        duplicate (_core.EventCursor; pass your own `cursor` to read where it
        is)."""
        cursor = cursor or _core.EventCursor(robot_ids, behaviors, since_seq, incarnation)
        for response in _resuming(self, lambda: self._stub.WatchEvents(
                cursor.request(), metadata=self._credentials.metadata())):
            yield from cursor.accept(response)

    def close(self):
        self.closed = True
        if self._event_pump is not None:
            self._event_pump.close()
        self._channel.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
