"""What the sync client (client.py) and the asyncio client (aio.py) share:
channel set-up, request building, behavior methods made from the behavior
descriptors, the event stream's resume position, the index of finished
activations, and the vehicle samples' kinds. No I/O here."""

import collections
import dataclasses
import inspect
import json
import os
import re

import grpc
from google.protobuf import json_format, struct_pb2
from google.protobuf import message as protobuf_message

from behaviorlib.v1 import behavior_pb2, coordinator_pb2, mission_pb2, platform_pb2, types_pb2

# Default deadline of a unary call, seconds.
DEFAULT_TIMEOUT_S = 10.0
# Pages of List* calls (AIP-158): the servers' maximum.
PAGE_SIZE = 1000
# How many events one WatchEvents message may carry.
EVENTS_PER_MESSAGE = 256
# How many delivered behavior events the resume position remembers, to drop
# the ones a restarted coordinator replays again.
REMEMBERED_EVENTS = 65536
# How many finished activations the index keeps for late waiters.
REMEMBERED_TERMINATIONS = 4096
# Reconnection back-off of resuming streams, seconds.
FIRST_RETRY_S = 0.1
MAX_RETRY_S = 2.0
# gRPC codes after which a stream is opened again (the coordinator restarts,
# or its connection broke).
RETRYABLE = (grpc.StatusCode.UNAVAILABLE, grpc.StatusCode.UNKNOWN, grpc.StatusCode.INTERNAL)

MISSION_ENDED = (mission_pb2.MISSION_STATE_SUCCEEDED, mission_pb2.MISSION_STATE_FAILED,
                 mission_pb2.MISSION_STATE_ABORTED)


@dataclasses.dataclass(frozen=True)
class Credentials:
    """Mutual TLS (PEM files, as the servers' --tls-ca, --tls-cert and
    --tls-key) and/or a bearer token (sent as `authorization: Bearer ...`)."""

    ca_file: str = ""
    cert_file: str = ""
    key_file: str = ""
    token: str = ""
    # Overrides the name checked in the server's certificate.
    server_name: str = ""

    def channel_credentials(self):
        if not self.ca_file:
            if self.cert_file or self.key_file:
                raise ValueError("a client certificate needs the CA (ca_file) too")
            return None

        def read(path):
            if not path:
                return None
            with open(path, "rb") as f:
                return f.read()

        return grpc.ssl_channel_credentials(root_certificates=read(self.ca_file),
                                            private_key=read(self.key_file),
                                            certificate_chain=read(self.cert_file))

    def metadata(self):
        return (("authorization", f"Bearer {self.token}"),) if self.token else ()

    def channel_options(self):
        options = [("grpc.max_receive_message_length", 16 * 1024 * 1024)]
        if self.server_name:
            options.append(("grpc.ssl_target_name_override", self.server_name))
        return options


def open_channel(module, target, credentials):
    """A channel to `target` from `module` (grpc or grpc.aio)."""
    channel_credentials = credentials.channel_credentials()
    options = credentials.channel_options()
    if channel_credentials is None:
        return module.insecure_channel(target, options=options)
    return module.secure_channel(target, channel_credentials, options=options)


# --- values -------------------------------------------------------------------


def to_plain(value):
    """A Python value for a Struct or Value field: messages in their JSON
    form, tuples as lists, dicts and lists converted deeply."""
    if isinstance(value, protobuf_message.Message):
        return json_format.MessageToDict(value, preserving_proto_field_name=True)
    if isinstance(value, dict):
        return {str(k): to_plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_plain(v) for v in value]
    return value


def to_struct(parameters):
    struct = struct_pb2.Struct()
    struct.update(to_plain(dict(parameters or {})))
    return struct


def to_value(value):
    return json_format.ParseDict(to_plain(value), struct_pb2.Value())


def _sorted(value):
    """Dicts with their keys in order, deeply: a Struct is a map, whose order
    protobuf does not keep."""
    if isinstance(value, dict):
        return {k: _sorted(value[k]) for k in sorted(value)}
    if isinstance(value, list):
        return [_sorted(v) for v in value]
    return value


def from_struct(struct):
    """A Struct as a dict (numbers are floats, as in JSON), keys sorted."""
    return _sorted(json_format.MessageToDict(struct))


def from_value(value):
    """A Value as plain Python (numbers are floats, as in JSON), keys sorted."""
    return _sorted(json_format.MessageToDict(value))


def duration_s(duration):
    return duration.seconds + duration.nanos * 1e-9


def enum_field_name(message, field, prefix):
    """The name of an enum field's value without its prefix."""
    enum = message.DESCRIPTOR.fields_by_name[field].enum_type
    value = enum.values_by_number.get(getattr(message, field))
    name = value.name if value is not None else str(getattr(message, field))
    return name[len(prefix):] if name.startswith(prefix) else name


def short_enum(enum_type, number, prefix):
    """TERMINATION_CAUSE_GOAL_ACHIEVED -> GOAL_ACHIEVED."""
    name = enum_type.Name(number)
    return name[len(prefix):] if name.startswith(prefix) else name


# --- behaviors ----------------------------------------------------------------


def method_name(behavior):
    """The Python method of a behavior: TAKE_OFF -> take_off."""
    name = re.sub(r"[^0-9a-zA-Z_]", "_", behavior).lower()
    return name if name.isidentifier() and not name[0].isdigit() else "b_" + name


_PY_TYPES = {"number": float, "integer": int, "boolean": bool, "string": str, "enum": str,
             "object": dict, "bytes": bytes}


@dataclasses.dataclass(frozen=True)
class Parameter:
    """One parameter of a behavior, from its ParameterSchema."""

    name: str
    type: str
    repeated: bool
    unit: str
    required: bool
    default: object
    description: str
    minimum: object = None
    maximum: object = None
    enum_values: tuple = ()

    @staticmethod
    def from_schema(schema):
        default = json.loads(schema.default_json) if schema.default_json else None
        minimum = maximum = None
        if schema.HasField("range"):
            minimum, maximum = schema.range.min, schema.range.max
        # value_type; its text form `type` from a system that predates it.
        type_name = (short_enum(behavior_pb2.ParameterType, schema.value_type,
                                "PARAMETER_TYPE_").lower()
                     if schema.value_type else schema.type)
        return Parameter(schema.name, type_name, schema.repeated, schema.unit, schema.required,
                         default, schema.description, minimum, maximum,
                         tuple(schema.enum_values))

    def annotation(self):
        base = _PY_TYPES.get(self.type, object)
        return list[base] if self.repeated else base

    def doc(self):
        parts = [f"{self.name} ({self.type}{'[]' if self.repeated else ''}"
                 f"{', ' + self.unit if self.unit else ''})"]
        if self.required:
            parts.append("required")
        if self.minimum is not None:
            parts.append(f"in [{self.minimum:g}, {self.maximum:g}]")
        if self.default is not None:
            parts.append(f"default {json.dumps(self.default)}")
        if self.enum_values:
            parts.append("one of " + ", ".join(self.enum_values))
        return "; ".join(parts) + (f": {self.description}" if self.description else "")


@dataclasses.dataclass(frozen=True)
class BehaviorSpec:
    """What a robot's behavior takes, from its BehaviorDescription (the
    descriptor its system serves): the method's name, signature and
    documentation are made from it, so a new behavior needs no code here."""

    name: str
    method: str
    description: str
    kind: str
    parameters: tuple
    maximum_execution_time_s: float

    @staticmethod
    def from_description(description):
        return BehaviorSpec(
            name=description.name, method=method_name(description.name),
            description=description.description,
            kind=enum_field_name(description, "kind", "BEHAVIOR_KIND_"),
            parameters=tuple(Parameter.from_schema(p) for p in description.parameters),
            maximum_execution_time_s=duration_s(description.maximum_execution_time))

    def signature(self):
        """Keyword-only parameters: required ones without a default, the
        others with the behavior's default (None when it declares none:
        the parameter is then left unset)."""
        return inspect.Signature([
            inspect.Parameter(p.name, inspect.Parameter.KEYWORD_ONLY,
                              default=(inspect.Parameter.empty if p.required else p.default),
                              annotation=p.annotation())
            for p in self.parameters
        ])

    def doc(self, returns):
        title = self.description if self.description.startswith(self.name) else \
            f"{self.name}: {self.description}".rstrip(": ")
        lines = [title, ""]
        if self.parameters:
            lines.append("Parameters:")
            lines += [f"    {p.doc()}" for p in self.parameters]
        if self.maximum_execution_time_s:
            lines.append(f"Times out after {self.maximum_execution_time_s:g} s of active time.")
        lines.append(returns)
        return "\n".join(lines)

    def bind(self, arguments):
        """The parameters to send: the keyword arguments checked against the
        schema (an unknown name or a missing required one is a TypeError, as
        for any Python call); None leaves a parameter to its default. Values
        and ranges are checked by the behavior's system."""
        known = {p.name for p in self.parameters}
        unknown = sorted(set(arguments) - known)
        if unknown:
            raise TypeError(f"{self.method}() got unexpected parameter(s) {', '.join(unknown)}; "
                            f"{self.name} takes: {', '.join(sorted(known)) or 'none'}")
        missing = [p.name for p in self.parameters if p.required and arguments.get(p.name) is None]
        if missing:
            raise TypeError(f"{self.method}() is missing required parameter(s) "
                            f"{', '.join(missing)}")
        return {k: v for k, v in arguments.items() if v is not None}


class RobotMethods:
    """A robot's behaviors as attributes (TAKE_OFF -> take_off), shared by
    the sync and asyncio clients' Robot: `method_type(robot, spec)` makes
    each one."""

    def __init__(self, fleet, robot_id, specs, method_type):
        self.fleet = fleet
        self.id = robot_id
        # BehaviorSpec by behavior name.
        self.behaviors = specs
        self._methods = {spec.method: method_type(self, spec) for spec in specs.values()}

    def __getattr__(self, name):
        methods = self.__dict__.get("_methods", {})
        if name in methods:
            return methods[name]
        raise AttributeError(f"robot {self.__dict__.get('id')!r} has no behavior method {name!r} "
                             f"(its behaviors: {', '.join(sorted(methods)) or 'none'})")

    def __dir__(self):
        return sorted(set(super().__dir__()) | set(self._methods))


def specs_of(fleet_behaviors, robot_id):
    """BehaviorSpecs by name of the FleetBehaviors of one robot."""
    return {b.description.name: BehaviorSpec.from_description(b.description)
            for b in fleet_behaviors if b.robot_id == robot_id}


# --- terminations ---------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Termination:
    """How an activation ended (its finished event)."""

    robot_id: str
    behavior: str
    activation_id: str
    # GOAL_ACHIEVED, TIME_OUT, WRONG_PROGRESS, SITUATION_CHANGE,
    # PROCESS_FAILURE or INTERRUPTED.
    cause: str
    message: str
    active_duration_s: float
    parameters: dict
    # True when the coordinator made the event itself: the hosting system
    # went down or restarted during the activation.
    synthesized: bool = False

    @property
    def succeeded(self):
        return self.cause == "GOAL_ACHIEVED"

    @staticmethod
    def from_event(fleet_event):
        event = fleet_event.behavior_event
        return Termination(
            robot_id=event.robot_id, behavior=event.behavior, activation_id=event.activation_id,
            cause=short_enum(behavior_pb2.TerminationCause, event.finished.cause,
                             "TERMINATION_CAUSE_"),
            message=event.finished.message,
            active_duration_s=duration_s(event.finished.active_duration),
            parameters=from_struct(event.finished.parameters),
            synthesized=fleet_event.synthesized)


class Terminations:
    """Finished activations by id, the newest REMEMBERED_TERMINATIONS, fed
    from the fleet's event stream; a waiter asks after its Activate returns,
    so the event may already be here."""

    def __init__(self, capacity=REMEMBERED_TERMINATIONS):
        self._capacity = capacity
        self._by_activation = collections.OrderedDict()

    def add(self, fleet_event):
        """Records a finished event; returns its Termination (None for other
        events)."""
        if fleet_event.WhichOneof("kind") != "behavior_event":
            return None
        if fleet_event.behavior_event.WhichOneof("kind") != "finished":
            return None
        termination = Termination.from_event(fleet_event)
        self._by_activation[termination.activation_id] = termination
        self._by_activation.move_to_end(termination.activation_id)
        while len(self._by_activation) > self._capacity:
            self._by_activation.popitem(last=False)
        return termination

    def get(self, activation_id):
        return self._by_activation.get(activation_id)


# --- the resumable event stream -------------------------------------------------


class EventCursor:
    """Where a fleet event stream is, so that it resumes without a gap or a
    duplicate.

    Within one coordinator incarnation the stream resumes after the last
    coordinator seq delivered. A restarted coordinator has a new incarnation
    and replays every event it has retained, which it read again from the
    systems: their behavior events keep the system's own (incarnation, seq),
    so the ones already delivered are recognised and dropped. Synthesized
    finished events (seq 0) are recognised by their activation."""

    def __init__(self, robot_ids=(), behaviors=(), since_seq=0, incarnation=""):
        self.robot_ids = list(robot_ids)
        self.behaviors = list(behaviors)
        self.since_seq = since_seq
        self.incarnation = incarnation
        # Events the coordinator said were no longer retained when resuming.
        self.dropped_count = 0
        self.restarts_seen = 0
        self._seen = collections.OrderedDict()

    def request(self):
        return coordinator_pb2.WatchFleetEventsRequest(
            since_seq=self.since_seq, incarnation=self.incarnation, robot_ids=self.robot_ids,
            behaviors=self.behaviors, max_events_per_message=EVENTS_PER_MESSAGE)

    @staticmethod
    def _identity(fleet_event):
        if fleet_event.WhichOneof("kind") != "behavior_event":
            return None
        event = fleet_event.behavior_event
        if fleet_event.synthesized:
            return ("synthesized", event.incarnation, event.activation_id)
        return (event.incarnation, event.seq)

    def accept(self, response):
        """The new events of one WatchEvents message, in order (the start
        message gives none)."""
        kind = response.WhichOneof("kind")
        if kind == "start":
            start = response.start
            if self.incarnation and start.incarnation != self.incarnation:
                self.restarts_seen += 1
            if start.events_dropped:
                self.dropped_count += start.dropped_count
            self.incarnation = start.incarnation
            return []
        events = [response.event] if kind == "event" else list(response.events.events)
        fresh = []
        for event in events:
            self.since_seq = event.seq
            self.incarnation = event.incarnation
            identity = self._identity(event)
            if identity is not None:
                if identity in self._seen:
                    continue
                self._seen[identity] = None
                while len(self._seen) > REMEMBERED_EVENTS:
                    self._seen.popitem(last=False)
            fresh.append(event)
        return fresh


class Backoff:
    """Delays between reconnection attempts: doubling from FIRST_RETRY_S up to
    MAX_RETRY_S, back to the start after a success."""

    def __init__(self):
        self._next = FIRST_RETRY_S

    def reset(self):
        self._next = FIRST_RETRY_S

    def next_delay_s(self):
        delay = self._next
        self._next = min(self._next * 2, MAX_RETRY_S)
        return delay


def retryable(error):
    return isinstance(error, grpc.RpcError) and error.code() in RETRYABLE


# --- requests -------------------------------------------------------------------


def activate_request(robot_id, behavior, parameters, request_id="", skip_plan=False,
                     dry_run=False):
    return coordinator_pb2.ActivateFleetBehaviorRequest(
        robot_id=robot_id, behavior=behavior, parameters=to_struct(parameters),
        request_id=request_id, skip_plan=skip_plan, dry_run=dry_run)


# The coordinator's calls on one robot's behavior beside activation:
# (method, request type, reply field).
ROBOT_CALLS = {
    "pause": ("PauseFleetBehavior", "PauseFleetBehaviorRequest", "result"),
    "resume": ("ResumeFleetBehavior", "ResumeFleetBehaviorRequest", "result"),
    "modify": ("ModifyFleetBehavior", "ModifyFleetBehaviorRequest", "result"),
    "check_activation": ("CheckFleetBehaviorActivation", "CheckFleetBehaviorActivationRequest",
                         "activation"),
}


def robot_call(name, robot_id, behavior, activation_id="", parameters=None):
    """(method, request, reply field) of one of ROBOT_CALLS."""
    method, request_type, field = ROBOT_CALLS[name]
    request = getattr(coordinator_pb2, request_type)(robot_id=robot_id, behavior=behavior)
    if activation_id:
        request.activation_id = activation_id
    if parameters is not None:
        request.parameters.CopyFrom(to_struct(parameters))
    return method, request, field


def mission_request(file=None, text=None, server_file=None, robot_id="", mission_id="",
                    source_name="", check=False):
    """StartMissionRequest (CheckMissionRequest with `check`) from exactly
    one of: `file` (a local file, read here and sent as text), `text`, or
    `server_file` (a path in the coordinator's --mission-dir)."""
    given = [x for x in (file, text, server_file) if x is not None]
    if len(given) != 1:
        raise ValueError("give exactly one of file, text and server_file")
    if check:
        request = coordinator_pb2.CheckMissionRequest(robot_id=robot_id)
    else:
        request = coordinator_pb2.StartMissionRequest(robot_id=robot_id, mission_id=mission_id)
    if file is not None:
        with open(file, encoding="utf-8") as f:
            request.text = f.read()
        request.source_name = source_name or os.path.basename(os.fspath(file))
    elif text is not None:
        request.text = text
        request.source_name = source_name
    else:
        request.file_path = os.fspath(server_file)
    return request


def mission_state(status):
    """RUNNING, PAUSED, SUCCEEDED, FAILED or ABORTED."""
    return short_enum(mission_pb2.MissionState, status.state, "MISSION_STATE_")


# --- the vehicles' state (telemetry) ---------------------------------------------

# What a telemetry call may read, by the name a script uses: the
# coordinator's VehicleSampleKind, and the message each carries.
SAMPLE_KINDS = {
    "pose": (coordinator_pb2.VEHICLE_SAMPLE_KIND_POSE, types_pb2.PoseStamped),
    "twist": (coordinator_pb2.VEHICLE_SAMPLE_KIND_TWIST, types_pb2.TwistStamped),
    "flight_state": (coordinator_pb2.VEHICLE_SAMPLE_KIND_FLIGHT_STATE, platform_pb2.FlightStatus),
    "battery": (coordinator_pb2.VEHICLE_SAMPLE_KIND_BATTERY, types_pb2.BatteryState),
    "imu": (coordinator_pb2.VEHICLE_SAMPLE_KIND_IMU, types_pb2.Imu),
    "gps": (coordinator_pb2.VEHICLE_SAMPLE_KIND_GPS, types_pb2.PositionFix),
    "baro": (coordinator_pb2.VEHICLE_SAMPLE_KIND_BARO, types_pb2.Altitude),
    "linear_speed": (coordinator_pb2.VEHICLE_SAMPLE_KIND_LINEAR_SPEED, types_pb2.TwistStamped),
    "ground_truth_pose": (coordinator_pb2.VEHICLE_SAMPLE_KIND_GROUND_TRUTH_POSE,
                          types_pb2.PoseStamped),
    "ground_truth_twist": (coordinator_pb2.VEHICLE_SAMPLE_KIND_GROUND_TRUTH_TWIST,
                           types_pb2.TwistStamped),
}
# A sample older than this (seconds of the vehicles' time) is refused as
# stale unless the call says otherwise: the flight behaviors' limit.
DEFAULT_MAX_AGE_S = 1.0


def sample_kind(name):
    """The VehicleSampleKind of `name` ("pose", "imu", ...); ValueError,
    listing the names, for another."""
    try:
        return SAMPLE_KINDS[name][0]
    except (KeyError, TypeError):
        raise ValueError(f"no vehicle sample named {name!r}: use one of "
                         f"{', '.join(SAMPLE_KINDS)}") from None


def sample_request(robot_id, name, max_age_s):
    """GetVehicleSampleRequest; max_age_s None means no limit."""
    return coordinator_pb2.GetVehicleSampleRequest(
        robot_id=robot_id, kind=sample_kind(name),
        max_age_s=-1.0 if max_age_s is None else float(max_age_s))


def watch_vehicle_request(robot_id, name, max_rate_hz, latest_first):
    return coordinator_pb2.WatchVehicleRequest(robot_id=robot_id, kind=sample_kind(name),
                                               max_rate_hz=float(max_rate_hz),
                                               send_latest_first=latest_first)


def unpack_sample(sample):
    """The API's own message (PoseStamped, FlightStatus, ...) of a
    VehicleSample."""
    for kind, message_type in SAMPLE_KINDS.values():
        if kind == sample.kind:
            message = message_type()
            if not sample.sample.Unpack(message):
                raise ValueError(f"{sample.topic} carries {sample.sample.type_url}, not "
                                 f"{message_type.DESCRIPTOR.full_name}")
            return message
    raise ValueError(f"unknown vehicle sample kind {sample.kind}")
