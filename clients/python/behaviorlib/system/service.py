"""The gRPC services of a Python behavior system: a port of
services/behaviorlib/server/behavior_system_service.cc, typed_behavior_service.h and
lifecycle_calls.cc, over the behaviors' engines (engine.ExecutionManager).

    host = BehaviorHost(behaviors, robot_id="drone1", system="my_behaviors", clock=clock)
    host.start()
    gate = AcceptGate()
    system = BehaviorSystemService(host, gate, stream_slots)
    typed = TypedServices(host, gate)
    server.add_generic_rpc_handlers([system.handler(), *typed.handlers()])

What a client sees is what a C++ system serves:
  - behaviorlib.v1.BehaviorSystem: ListBehaviors (each behavior's description: its typed
    service, description and kind from the service's (behaviorlib.v1.behavior) option, the
    parameter schema of parameters.describe, maximum_execution_time, frequency_hz, state;
    paginated as server_kit/pagination.h), WatchEvents (the WatchEventsStart, then the resumable
    log's events one per message or in batches of max_events_per_message, ended
    RESOURCE_EXHAUSTED for a subscriber too slow and UNAVAILABLE at shutdown, both with the
    resume point), and the lifecycle calls by behavior name with parameters as a Struct;
  - per behavior whose parameters message declares it, the typed service the C++ build
    generates (typed.py): Activate and Modify take the behavior's own parameter message.
Refusals carry the C++ codes, messages and details (an unknown behavior is NOT_FOUND
UNKNOWN_BEHAVIOR naming what the system hosts; a Struct that does not fit is INVALID_ARGUMENT
naming the parameter; a process shutting down refuses lifecycle calls UNAVAILABLE
SHUTTING_DOWN). Under an access policy (access_policy.py), a caller bound to another robot
than the system's is refused the calls that command a behavior (activate, deactivate, pause,
resume, modify) PERMISSION_DENIED ROBOT_NOT_PERMITTED, as by lifecycle_calls.cc; the roles
themselves are checked before any handler runs (security.CallGuard).

Threads. grpcio runs each call on a thread of the server's pool. A lifecycle call waits there
for its behavior's worker (as the C++ reactor waits for its callback), but no longer than the
call lives. A WatchEvents stream holds its thread for its life, so streams are bounded
(_protocol.StreamSlots); one beyond the bound is refused RESOURCE_EXHAUSTED LIMIT_EXCEEDED.
"""

import base64
import binascii
import threading
import time

import grpc

from behaviorlib.v1 import behavior_pb2, errors_pb2, options_pb2

from . import _protocol, typed
from .access_policy import robot_scope_of
from .engine import BehaviorContext, EventLog, ExecutionManager
from .parameters import StatusError, describe, from_struct, leading_comment

# WatchEventsRequest.max_events_per_message is capped here.
MAX_EVENTS_PER_MESSAGE = 1024
# ListBehaviors pages (server_kit::PageLimits).
DEFAULT_PAGE_SIZE = 500
MAX_PAGE_SIZE = 1000
_PAGE_TOKEN_PREFIX = "k1."
_MAX_PAGE_TOKEN = 4096

_SYSTEM_SERVICE = behavior_pb2.DESCRIPTOR.services_by_name["BehaviorSystem"]


class AcceptGate:
    """Refuses lifecycle calls once the process is shutting down and, under an access policy
    (access_policy.AccessPolicy), the commands of a caller bound to another robot than
    `robot_id`, the robot whose behaviors the process hosts."""

    def __init__(self, robot_id="", policy=None):
        self._accepting = True
        self.robot_id = robot_id
        self._policy = policy

    @property
    def accepting(self):
        return self._accepting

    def close(self):
        self._accepting = False

    def refusal(self, context, what):
        """Why a call that commands a behavior (`what`: "activate behaviors") is refused, as a
        StatusError, or None (lifecycle_calls.cc refusal)."""
        if not self._accepting:
            return _shutting_down()
        if not self.robot_id or self._policy is None:
            return None
        return robot_scope_of(context, self._policy).permits(self.robot_id, what)


class BehaviorHost:
    """The behaviors of one process, each in its engine, sharing the process's event log and
    clock (services/behaviorlib/core/behavior_host.cc). `observer_factory`, when given, makes
    each behavior's BehaviorObserver (the metrics) from its ExecutionManager; `before_command`,
    when given, is every behavior's BehaviorContext.before_command (the deterministic mode's
    time gate, TimeFollower.await_turn). Two behaviors of one name are refused (StatusError
    INVALID_ARGUMENT)."""

    def __init__(self, behaviors, *, robot_id, system, clock, observer_factory=None,
                 before_command=None):
        self.robot_id = robot_id
        self.system = system
        self.clock = clock
        self._before_command = before_command
        self.events = EventLog(robot_id=robot_id, system=system)
        self.engines = [ExecutionManager(behavior) for behavior in behaviors]
        self._observer_factory = observer_factory
        self._started = []
        names = [engine.name for engine in self.engines]
        for name in names:
            if names.count(name) > 1:
                raise StatusError(grpc.StatusCode.INVALID_ARGUMENT,
                                  f"behavior {name} is registered twice")

    def start(self):
        """Starts every engine (on_configure runs, with its configuration's defaults); on a
        refusal (StatusError) stops those started and raises it."""
        for engine in self.engines:
            observer = self._observer_factory(engine) if self._observer_factory else None
            context = BehaviorContext(clock=self.clock, events=self.events, observer=observer,
                                      robot_id=self.robot_id,
                                      before_command=self._before_command)
            try:
                engine.start(context)
            except StatusError:
                self.stop()
                raise
            self._started.append(engine)

    def stop(self):
        """Stops the engines: running activations end INTERRUPTED ("process shutting down")."""
        for engine in self._started:
            engine.stop()
        self._started = []

    def find(self, name):
        return next((engine for engine in self.engines if engine.name == name), None)

    def names(self):
        return [engine.name for engine in self.engines]


def _shutting_down():
    return StatusError(grpc.StatusCode.UNAVAILABLE, "the behavior system is shutting down",
                       reason=errors_pb2.SHUTTING_DOWN)


class _Lifecycle:
    """The uniform interface of one behavior over gRPC (lifecycle_calls.cc): each call checks the
    gate, starts the call on the behavior's engine and answers what the engine answers."""

    def __init__(self, gate):
        self._gate = gate

    def _run(self, context, what, start):
        """`what` names a command for the robot scope's refusal ("activate behaviors"); None
        for a call that commands nothing (CheckSituation), which only the shutdown refuses."""
        refusal = (self._gate.refusal(context, what) if what
                   else None if self._gate.accepting else _shutting_down())
        if refusal is not None:
            _protocol.abort(context, refusal)
        return _protocol.answer(start(), context)

    def activate(self, context, engine, parameters, request_id):
        received = time.monotonic_ns()
        return self._run(context, "activate behaviors",
                         lambda: engine.activate(parameters, request_id, received))

    def deactivate(self, context, engine, activation_id):
        return self._run(context, "deactivate behaviors",
                         lambda: engine.deactivate(activation_id))

    @staticmethod
    def check_activation(engine):
        return engine.check_activation()

    def check_situation(self, context, engine):
        return self._run(context, None, engine.check_situation)

    def pause(self, context, engine, activation_id):
        return self._run(context, "pause behaviors", lambda: engine.pause(activation_id))

    def resume(self, context, engine, activation_id):
        return self._run(context, "resume behaviors", lambda: engine.resume(activation_id))

    def modify(self, context, engine, activation_id, update):
        return self._run(context, "modify behaviors",
                         lambda: engine.modify(update, activation_id))


# ---- The generic BehaviorSystem service ----------------------------------------------------------

def _encode_page_token(last_key):
    encoded = base64.urlsafe_b64encode(last_key.encode("utf-8")).decode("ascii").rstrip("=")
    return _PAGE_TOKEN_PREFIX + encoded


def _decode_page_token(token):
    """The key a page_token carries, or None for a token this server did not make."""
    if not token.startswith(_PAGE_TOKEN_PREFIX) or len(token) > _MAX_PAGE_TOKEN:
        return None
    body = token[len(_PAGE_TOKEN_PREFIX):]
    try:
        return base64.b64decode(body + "=" * (-len(body) % 4), altchars=b"-_",
                                validate=True).decode("utf-8")
    except (binascii.Error, ValueError):
        return None


def _page(request):
    """(size, the key after which the page starts or None) of a paginated request
    (server_kit::paginate); raises StatusError for a bad page_size or page_token."""
    if request.page_size < 0:
        message = "page_size must not be negative"
        raise StatusError(grpc.StatusCode.INVALID_ARGUMENT, message,
                          reason=errors_pb2.INVALID_REQUEST,
                          field_violations=[("page_size", message)])
    after = None
    if request.page_token:
        after = _decode_page_token(request.page_token)
        if after is None:
            raise StatusError(grpc.StatusCode.INVALID_ARGUMENT,
                              "page_token is not a token this server gave (next_page_token)",
                              reason=errors_pb2.INVALID_PAGE_TOKEN)
    size = DEFAULT_PAGE_SIZE if request.page_size == 0 else min(request.page_size, MAX_PAGE_SIZE)
    return size, after


class BehaviorSystemService:
    """behaviorlib.v1.BehaviorSystem over a BehaviorHost. `typed_services` maps a behavior's
    name to the full name of its typed service (TypedServices.names)."""

    def __init__(self, host, gate, stream_slots, typed_services):
        self._host = host
        self._lifecycle = _Lifecycle(gate)
        self._slots = stream_slots
        self._typed_services = dict(typed_services)
        self._streams_lock = threading.Lock()
        self._streams = set()  # the wake events of the open WatchEvents streams
        self._shutting_down = False

    def handler(self):
        """The grpc.GenericRpcHandler to add to the server."""
        return _protocol.serve_service(_SYSTEM_SERVICE, {
            "ListBehaviors": self.list_behaviors,
            "WatchEvents": self.watch_events,
            "ActivateBehavior": self.activate_behavior,
            "DeactivateBehavior": self.deactivate_behavior,
            "CheckBehaviorActivation": self.check_behavior_activation,
            "CheckBehaviorSituation": self.check_behavior_situation,
            "PauseBehavior": self.pause_behavior,
            "ResumeBehavior": self.resume_behavior,
            "ModifyBehavior": self.modify_behavior,
        })

    def shutdown_streams(self):
        """Ends every WatchEvents stream once the events queued for it are sent (UNAVAILABLE
        SHUTTING_DOWN with the resume point: the client may resume elsewhere with since_seq)."""
        with self._streams_lock:
            self._shutting_down = True
            streams = list(self._streams)
        for wake in streams:
            wake.set()

    def _lookup(self, name, context):
        engine = self._host.find(name)
        if engine is None:
            host = self._host
            _protocol.abort(context, StatusError(
                grpc.StatusCode.NOT_FOUND,
                f"unknown behavior '{name}'; {host.system} hosts: {', '.join(host.names())}",
                reason=errors_pb2.UNKNOWN_BEHAVIOR,
                metadata={"robot": host.robot_id, "system": host.system, "behavior": name}))
        return engine

    @staticmethod
    def _from_struct(engine, values, context):
        try:
            return from_struct(values, engine.parameters_type)
        except StatusError as error:
            _protocol.abort(context, error)

    def _describe(self, engine):
        out = behavior_pb2.BehaviorDescription(
            name=engine.name, parameters_type=engine.parameters_type.DESCRIPTOR.full_name)
        service_name = self._typed_services.get(engine.name)
        if service_name is not None:
            out.service = service_name
            service = typed.find_service(service_name)
            info = service.GetOptions().Extensions[options_pb2.behavior]
            out.description = info.description or leading_comment(service_name)
            out.kind = info.kind
        describe(engine.parameters_type.DESCRIPTOR, out.parameters)
        out.maximum_execution_time.FromNanoseconds(engine.options.maximum_execution_time)
        out.frequency_hz = engine.options.frequency_hz
        out.state = engine.state()
        return out

    def list_behaviors(self, request, context):
        # A bad page request costs no description.
        try:
            size, after = _page(request)
        except StatusError as error:
            _protocol.abort(context, error)
        host = self._host
        response = behavior_pb2.ListBehaviorsResponse(
            robot_id=host.robot_id, system=host.system, incarnation=host.events.incarnation)
        engines = sorted((engine for engine in host.engines
                          if after is None or engine.name > after), key=lambda e: e.name)
        for engine in engines[:size]:
            response.behaviors.append(self._describe(engine))
        if len(engines) > size:
            response.next_page_token = _encode_page_token(engines[size - 1].name)
        return response

    def watch_events(self, request, context):
        if not self._slots.take():
            _protocol.abort(context, StatusError(
                grpc.StatusCode.RESOURCE_EXHAUSTED,
                f"too many streams open on this behavior system (at most {self._slots.limit}); "
                "close one and watch again", reason=errors_pb2.LIMIT_EXCEEDED))
        wake = threading.Event()
        subscription = self._host.events.subscribe(
            since_seq=request.since_seq, incarnation=request.incarnation,
            behaviors=list(request.behaviors), wake=wake.set)
        with self._streams_lock:
            self._streams.add(wake)
            if self._shutting_down:
                wake.set()
        try:
            yield from self._stream(subscription, wake, request, context)
        finally:
            with self._streams_lock:
                self._streams.discard(wake)
            subscription.cancel()
            self._slots.give_back()

    def _stream(self, subscription, wake, request, context):
        """The LogStreamWriter's protocol: the start message, then the queued events; at an
        overflow or at shutdown, once drained, the end with the resume point."""
        batch = min(request.max_events_per_message, MAX_EVENTS_PER_MESSAGE)
        context.add_callback(wake.set)  # a cancelled call wakes the stream, which then ends
        yield behavior_pb2.WatchEventsResponse(start=subscription.start)
        while context.is_active():
            wake.clear()
            events = subscription.pop_up_to(batch if batch > 1 else 1)
            if events:
                if batch > 1:
                    yield behavior_pb2.WatchEventsResponse(
                        events=behavior_pb2.BehaviorEventBatch(events=events))
                else:
                    yield behavior_pb2.WatchEventsResponse(event=events[0])
                continue
            resume = (f"resume with since_seq={subscription.last_popped_seq()} and "
                      f"incarnation={subscription.start.incarnation}")
            if subscription.overflowed():
                _protocol.abort(context, StatusError(
                    grpc.StatusCode.RESOURCE_EXHAUSTED,
                    "subscriber too slow: events were produced faster than it read them; "
                    + resume, reason=errors_pb2.LIMIT_EXCEEDED))
            with self._streams_lock:
                shutting_down = self._shutting_down
            if shutting_down:
                _protocol.abort(context, StatusError(
                    grpc.StatusCode.UNAVAILABLE,
                    f"the behavior system is shutting down; {resume}",
                    reason=errors_pb2.SHUTTING_DOWN))
            wake.wait()

    def activate_behavior(self, request, context):
        engine = self._lookup(request.behavior, context)
        parameters = self._from_struct(engine, request.parameters, context)
        return self._lifecycle.activate(context, engine, parameters, request.request_id)

    def deactivate_behavior(self, request, context):
        engine = self._lookup(request.behavior, context)
        return self._lifecycle.deactivate(context, engine, request.activation_id)

    def check_behavior_activation(self, request, context):
        return self._lifecycle.check_activation(self._lookup(request.behavior, context))

    def check_behavior_situation(self, request, context):
        engine = self._lookup(request.behavior, context)
        return self._lifecycle.check_situation(context, engine)

    def pause_behavior(self, request, context):
        engine = self._lookup(request.behavior, context)
        return self._lifecycle.pause(context, engine, request.activation_id)

    def resume_behavior(self, request, context):
        engine = self._lookup(request.behavior, context)
        return self._lifecycle.resume(context, engine, request.activation_id)

    def modify_behavior(self, request, context):
        engine = self._lookup(request.behavior, context)
        update = self._from_struct(engine, request.parameters, context)
        return self._lifecycle.modify(context, engine, request.activation_id, update)


# ---- The typed services --------------------------------------------------------------------------

class TypedServices:
    """The typed service of every behavior of `host` whose parameters message declares it
    (typed_behavior_service.h), built at run time (typed.py). A behavior given another name
    than its message declares is served by BehaviorSystem only. `documented` maps file names
    to FileDescriptorProtos with source info (the comments of the declaring files); the
    generated files, with their comments, are in `files` afterwards, for reflection. A
    declaration the C++ generator would refuse is refused here (StatusError
    INVALID_ARGUMENT)."""

    def __init__(self, host, gate, documented=None):
        self._lifecycle = _Lifecycle(gate)
        self.names = {}  # behavior name -> typed service full name
        self.files = {}  # generated file name -> FileDescriptorProto with source info
        self._handlers = []
        documented = documented or {}
        for engine in host.engines:
            descriptor = engine.parameters_type.DESCRIPTOR
            message_options = descriptor.GetOptions()
            if (not message_options.HasExtension(options_pb2.declare)
                    or message_options.Extensions[options_pb2.declare].name != engine.name):
                continue
            try:
                file, proto = typed.add_services_file(descriptor.file,
                                                      documented.get(descriptor.file.name))
            except ValueError as error:
                raise StatusError(grpc.StatusCode.INVALID_ARGUMENT, str(error)) from error
            self.files[file.name] = proto
            name = typed.service_name(descriptor)
            service = typed.find_service(name)
            info = service.GetOptions().Extensions[options_pb2.behavior]
            if info.name != engine.name or info.parameters_type != descriptor.full_name:
                # A file of that name was in the pool already, with other services.
                raise StatusError(grpc.StatusCode.INVALID_ARGUMENT,
                                  f"behavior {engine.name} takes {descriptor.full_name} but "
                                  f"service {name} declares behavior '{info.name}' with "
                                  f"{info.parameters_type}")
            self.names[engine.name] = name
            self._handlers.append(_protocol.serve_service(service, self._methods(engine)))

    def handlers(self):
        """The grpc.GenericRpcHandlers to add to the server, one per typed service."""
        return list(self._handlers)

    def _methods(self, engine):
        lifecycle = self._lifecycle
        return {
            "Activate": lambda request, context: lifecycle.activate(
                context, engine, request.parameters, request.request_id),
            "Deactivate": lambda request, context: lifecycle.deactivate(
                context, engine, request.activation_id),
            "CheckActivation": lambda request, context: lifecycle.check_activation(engine),
            "CheckSituation": lambda request, context: lifecycle.check_situation(context, engine),
            "Pause": lambda request, context: lifecycle.pause(
                context, engine, request.activation_id),
            "Resume": lambda request, context: lifecycle.resume(
                context, engine, request.activation_id),
            "Modify": lambda request, context: lifecycle.modify(
                context, engine, request.activation_id, request.parameters),
        }
