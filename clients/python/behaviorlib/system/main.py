"""The main() of a Python behavior system: a port of
services/behaviorlib/server/behavior_system_main.cc, so that a process hosting Python behaviors
serves what a C++ behavior system serves, on one port, and registers with the coordinator.

    # my_behaviors.py
    from behaviorlib.system import run_system
    from my_package import Wait

    if __name__ == "__main__":
        raise SystemExit(run_system([Wait()], system="my_behaviors"))

    python3 my_behaviors.py --robot-id drone1 --listen 127.0.0.1:0 --port-file my.ports \\
        --coordinator 127.0.0.1:50060

It serves, on --listen: behaviorlib.v1.BehaviorSystem and each behavior's typed service
(service.py), grpc.health.v1.Health (health.py) and server reflection v1 and v1alpha
(reflection.py); on --metrics-listen, /metrics (metrics.py); it registers with --coordinator
and sends heartbeats (registration.py). --port-file gets "grpc_port=N" and "metrics_port=M"
lines, written atomically once it serves, as the C++ systems write them (the local launcher and
the tests read it). SIGTERM or SIGINT shut it down in the C++ order: the time grants left
(--follow-time), lifecycle calls refused, active behaviors ended INTERRUPTED (their events reach
the subscribers and the coordinator), UnregisterSystem naming the last event, event streams
ended once drained (UNAVAILABLE with the resume point), every service NOT_SERVING, the server
stopped after a 0.5 s grace; exit 0.

The flags are the C++ systems' (hyphens or underscores alike): --robot-id, --listen, --advertise,
--metrics-listen, --port-file, --coordinator, --channel (the data channel, given to behaviors
as SystemContext.channel), --clock steady|sim (sim: the channel's `clock` topic, sim_clock.py),
--follow-time SIMULATOR_ADDR (the deterministic mode, simulator --time-scale max: the system
follows the simulator's time grants, time_follower.py, and the simulator waits until every
behavior ran what was due; needs --clock sim, and then the grants are the clock, the `clock`
topic is not read), --flight-controller (given to behaviors, with the process's credentials:
SystemContext.dial), --insecure, --grpc-metrics; --descriptor-set, a FileDescriptorSet with
source info (protoc --include_imports --include_source_info) whose comments describe the
behaviors of protos compiled outside this package, in ListBehaviors and reflection (the
package's own behaviorlib/v1/descriptors.binpb is read first); and the security of decisions 23
and 24 (security.py, access_policy.py, audit.py):
  - --tls-cert, --tls-key, --tls-ca: mutual TLS on the server (a client certificate from the CA
    required) and on every channel the process opens (coordinator, channel broker, simulator,
    flight controller); without TLS the process listens only on loopback unless --insecure;
  - --access-policy: the roles of the C++ servers' policy file, checked on every call before
    any handler, and the robot scope of the lifecycle calls; it needs TLS;
  - --audit-log, --audit-log-max-bytes, --audit-log-keep: every control call and every refusal,
    one JSON line each, rotated by size; behaviorlib_audited_calls_total counts them with or
    without a file.
Not built yet, and refused with a message saying so rather than ignored: --config (the YAML of
decision 45), --link-loss-timeout-s and --link-loss-action. A refused or inconsistent command
line, and TLS files or a policy that cannot be read, stop the start with exit code 2 and one line
saying why, in the C++ systems' words (which exit 1 for the TLS, policy and listen refusals).

Call run_system from the main thread, first thing: it blocks SIGTERM and SIGINT in every thread
it starts and waits for them with sigwait, as the C++ runtime does.
"""

import argparse
import concurrent.futures
import dataclasses
import os
import signal
import sys

import grpc
from google.protobuf import descriptor_pb2
from google.protobuf.message import DecodeError

import behaviorlib.v1

from . import health as health_module
from . import parameters
from ._protocol import StreamSlots
from .access_policy import AccessPolicy
from .audit import DEFAULT_KEEP, DEFAULT_MAX_BYTES, AuditLog
from .channel import DataChannel
from .clock import SteadyClock
from .metrics import SystemMetrics
from .parameters import StatusError
from .reflection import ReflectionService
from .registration import CoordinatorRegistration, advertised_address
from .security import CallGuard, TransportSecurity, open_channel
from .service import AcceptGate, BehaviorHost, BehaviorSystemService, TypedServices
from .sim_clock import SimClock
from .time_follower import TimeFollower

# A grpcio server runs each call on a thread of its pool; streams (event and health watches,
# reflection) may hold at most half of them, so that unary calls (health checks among them)
# always find one.
MAX_WORKERS = 64
MAX_STREAMS = 32
# The C++ servers' limits (server_kit/server_runtime.h ServerLimits).
SERVER_OPTIONS = (
    ("grpc.max_receive_message_length", 4 << 20),
    ("grpc.max_send_message_length", 16 << 20),
    ("grpc.max_concurrent_streams", 256),
    ("grpc.max_metadata_size", 16 << 10),
    ("grpc.keepalive_time_ms", 30_000),
    ("grpc.keepalive_timeout_ms", 10_000),
    ("grpc.http2.min_recv_ping_interval_without_data_ms", 10_000),
    ("grpc.http2.max_ping_strikes", 2),
    # A second server must not share a port already in use: a clear failure instead.
    ("grpc.so_reuseport", 0),
)
SHUTDOWN_GRACE_S = 0.5
_SYSTEM_SERVICE = "behaviorlib.v1.BehaviorSystem"
_NOT_YET = {
    "config": "--config (the system's YAML configuration)",
    "link_loss_timeout_s": "--link-loss-timeout-s (the link-loss action)",
    "link_loss_action": "--link-loss-action",
}


@dataclasses.dataclass
class SystemContext:
    """What the process offers its behaviors beyond their BehaviorContext, for a behaviors
    factory (run_system's `behaviors` given as a callable)."""
    system: str
    robot_id: str
    clock: object
    # The data channel (--channel), a channel.DataChannel; None without one.
    channel: object = None
    # --flight-controller: the FlightController's address ("host:port"), "" when not given.
    flight_controller: str = ""
    # The process's TLS client credentials (--tls-cert, --tls-key, --tls-ca); None without TLS.
    channel_credentials: object = None

    def dial(self, address, options=()):
        """A grpc.Channel to `address` (the flight controller's, another server's) with the
        process's credentials: mutual TLS when the process has TLS, as every channel of a C++
        system."""
        return open_channel(address, self.channel_credentials, options)


@dataclasses.dataclass
class SystemOptions:
    """A Python behavior system's settings: its command line, parsed."""
    system: str
    robot_id: str = "drone1"
    listen: str = "127.0.0.1:50061"
    advertise: str = ""
    metrics_listen: str = "127.0.0.1:0"
    coordinator: str = ""
    channel: str = ""
    clock: str = "steady"
    # The simulator whose time grants the system follows (the deterministic mode); "": none.
    follow_time: str = ""
    flight_controller: str = ""
    insecure: bool = False
    grpc_metrics: bool = True
    descriptor_sets: tuple = ()
    # Mutual TLS: this process's certificate, its key, the CA (all three, or none).
    tls_cert: str = ""
    tls_key: str = ""
    tls_ca: str = ""
    # The roles' policy file (needs TLS); "": every caller may call anything.
    access_policy: str = ""
    # The audit log ("": the metric only) and its rotation.
    audit_log: str = ""
    audit_log_max_bytes: int = DEFAULT_MAX_BYTES
    audit_log_keep: int = DEFAULT_KEEP


def _flag_bool(text):
    value = text.lower()
    if value in ("true", "1", "t", "yes"):
        return True
    if value in ("false", "0", "f", "no"):
        return False
    raise argparse.ArgumentTypeError(f"not a boolean: {text!r}")


def _parser(system):
    parser = argparse.ArgumentParser(
        prog=system, allow_abbrev=False,
        description=f"behavior system {system}: hosts its Python behaviors as gRPC services "
                    "(typed per behavior, plus behaviorlib.v1.BehaviorSystem)")

    def flag(name, **kwargs):
        names = [f"--{name}"] + ([f"--{name.replace('-', '_')}"] if "-" in name else [])
        parser.add_argument(*names, dest=name.replace("-", "_"), **kwargs)

    flag("robot-id", default="drone1", help="robot this process serves")
    flag("listen", default="127.0.0.1:50061",
         help="gRPC address host:port (port 0 picks a free port)")
    flag("advertise", default="",
         help="the host:port the coordinator dials to reach this system, when not the --listen "
              "address; empty: --listen's host and bound port")
    flag("metrics-listen", default="127.0.0.1:0",
         help="Prometheus /metrics address host:port (port 0 picks a free port; empty disables)")
    flag("port-file", default="", help="write the bound ports here (grpc_port=, metrics_port=)")
    flag("coordinator", default="",
         help="coordinator address host:port: register there (retrying until it is up), send "
              "heartbeats, register again after a coordinator restart, unregister on SIGTERM; "
              "empty: no registration")
    flag("channel", default="", help="data channel broker address host:port")
    flag("clock", default="steady",
         help="behavior clock: 'steady' (host monotonic time) or 'sim' (the channel's 'clock' "
              "topic, published by the simulator)")
    flag("follow-time", default="",
         help="simulator address host:port: follow its time grants (deterministic mode, "
              "simulator --time-scale max): each granted time is reported back once every "
              "behavior ran what was due, and the simulator waits for it; needs --clock sim")
    flag("flight-controller", default="",
         help="FlightController address host:port, given to the behaviors")
    flag("insecure", type=_flag_bool, nargs="?", const=True, default=False,
         help="allow plaintext gRPC on an address other than loopback: anyone who can reach "
              "the port can then command, land or kill the vehicles")
    flag("tls-cert", default="",
         help="PEM certificate of this process; with --tls-key and --tls-ca, the server and "
              "every client channel of the process use mutual TLS (scripts/make-dev-certs.sh "
              "makes a set)")
    flag("tls-key", default="", help="PEM private key of --tls-cert")
    flag("tls-ca", default="",
         help="PEM CA certificates that every peer's certificate must chain to")
    flag("access-policy", default="",
         help="YAML file mapping certificate names and bearer tokens to roles (viewer, "
              "operator, safety, system, admin); needs TLS; empty: every peer with a "
              "certificate from the CA may call anything")
    flag("audit-log", default="",
         help="file that every control call and every refused call is appended to (JSON lines)")
    flag("audit-log-max-bytes", type=int, default=DEFAULT_MAX_BYTES,
         help="the audit log is rotated (FILE -> FILE.1 -> FILE.2 ...) when it passes this size")
    flag("audit-log-keep", type=int, default=DEFAULT_KEEP,
         help="rotated audit log files kept (FILE.1 .. FILE.N)")
    flag("grpc-metrics", type=_flag_bool, nargs="?", const=True, default=True,
         help="count and time every call by service, method and status code (grpc_server_*)")
    flag("descriptor-set", action="append", default=[],
         help="a FileDescriptorSet with source info (protoc --include_imports "
              "--include_source_info) describing behaviors compiled outside this package; "
              "may be repeated")
    for name in ("config", "link-loss-timeout-s", "link-loss-action"):
        flag(name, default=None, help=argparse.SUPPRESS)
    return parser


def parse_flags(argv, system):
    """(SystemOptions, the --port-file path) from a command line (without the program name).
    Raises StatusError INVALID_ARGUMENT for a flag refused."""
    try:
        args = _parser(system).parse_args(argv)
    except SystemExit as done:
        if done.code == 0:  # --help
            raise
        raise StatusError(grpc.StatusCode.INVALID_ARGUMENT, "bad command line (see --help)")
    for name, what in _NOT_YET.items():
        if getattr(args, name) is not None:
            raise StatusError(grpc.StatusCode.INVALID_ARGUMENT,
                              f"{what} is not supported by Python behavior systems yet")
    if args.follow_time and args.clock != "sim":
        raise StatusError(grpc.StatusCode.INVALID_ARGUMENT,
                          "--follow-time needs --clock sim (the grants set simulated time)")
    if args.clock not in ("steady", "sim"):
        raise StatusError(grpc.StatusCode.INVALID_ARGUMENT,
                          f"--clock must be 'steady' or 'sim', not '{args.clock}'")
    if args.clock == "sim" and not args.channel:
        raise StatusError(grpc.StatusCode.INVALID_ARGUMENT,
                          "--clock sim needs --channel (simulated time comes from its 'clock' "
                          "topic)")
    options = SystemOptions(
        system=system, robot_id=args.robot_id, listen=args.listen, advertise=args.advertise,
        metrics_listen=args.metrics_listen, coordinator=args.coordinator, channel=args.channel,
        clock=args.clock, follow_time=args.follow_time,
        flight_controller=args.flight_controller, insecure=args.insecure,
        grpc_metrics=args.grpc_metrics, descriptor_sets=tuple(args.descriptor_set),
        tls_cert=args.tls_cert, tls_key=args.tls_key, tls_ca=args.tls_ca,
        access_policy=args.access_policy, audit_log=args.audit_log,
        audit_log_max_bytes=args.audit_log_max_bytes, audit_log_keep=args.audit_log_keep)
    return options, args.port_file


def _security(o, registry):
    """(TransportSecurity, AccessPolicy or None, AuditLog) of the options, checked in the C++
    order (ServerRuntime::startServer): the listen address, the TLS files, the policy (which
    needs TLS), the audit log. Raises StatusError INVALID_ARGUMENT with the C++ message."""
    security = TransportSecurity(o.tls_cert, o.tls_key, o.tls_ca, insecure=o.insecure)
    security.check_listen(o.listen)
    security.load()
    policy = None
    if o.access_policy:
        if not security.tls:
            raise StatusError(grpc.StatusCode.INVALID_ARGUMENT,
                              "--access-policy needs TLS (--tls-cert, --tls-key, --tls-ca): roles "
                              "are given to certificates and to bearer tokens sent over TLS")
        try:
            policy = AccessPolicy.load(o.access_policy)
        except StatusError as error:
            raise error.rewrap(f"--access-policy: {error.message}") from error
    try:
        audit = AuditLog(o.audit_log, registry, o.audit_log_max_bytes, o.audit_log_keep)
    except StatusError as error:
        raise error.rewrap(f"--audit-log: {error.message}") from error
    return security, policy, audit


def _documented_files(paths):
    """File name -> FileDescriptorProto with source info, from the package's descriptor set
    and then `paths` (a later file of the same name replaces an earlier one); their comments go
    to parameters.leading_comment too."""
    parameters.leading_comment("")  # loads the package's own set first: the paths' come after
    sets = []
    package_set = os.path.join(os.path.dirname(behaviorlib.v1.__file__), "descriptors.binpb")
    if os.path.exists(package_set):
        with open(package_set, "rb") as f:
            sets.append(f.read())
    for path in paths:
        try:
            with open(path, "rb") as f:
                data = f.read()
            descriptor_pb2.FileDescriptorSet.FromString(data)
        except (OSError, DecodeError) as error:
            raise StatusError(grpc.StatusCode.INVALID_ARGUMENT,
                              f"--descriptor-set {path}: {error}") from error
        parameters.load_descriptor_set(data)
        sets.append(data)
    documented = {}
    for data in sets:
        for file in descriptor_pb2.FileDescriptorSet.FromString(data).file:
            documented[file.name] = file
    return documented


class BehaviorSystemProcess:
    """A behavior-system process as a class: its clock, behaviors, services, metrics and
    registration, serving on one port. run_system() runs one until a shutdown signal."""

    def __init__(self, options, behaviors):
        """Starts everything. `behaviors` is a list of Behavior objects, or a callable that
        makes it from a SystemContext. Raises StatusError: INVALID_ARGUMENT for inconsistent
        options or behaviors that do not start (on_configure), UNAVAILABLE when a port cannot
        be bound. Whatever it started is stopped again when it raises."""
        self.options = options
        self._stopped = False
        self._channel = None
        self._clock = None
        self._host = None
        self._server = None
        self._registration = None
        self._follower = None
        self._audit = None
        try:
            self._start(options, behaviors)
        except BaseException:
            self.shutdown()
            raise

    def _start(self, o, behaviors):
        self.metrics = SystemMetrics(o.robot_id, o.system)
        security, policy, self._audit = _security(o, self.metrics.registry)
        credentials = security.channel_credentials
        documented = _documented_files(o.descriptor_sets)
        if o.channel:
            self._channel = DataChannel(o.channel, channel_credentials=credentials)
        if o.clock == "sim":
            self._clock = SimClock()
            # Following the time grants, the grants are the time: the clock topic would only
            # repeat them.
            if not o.follow_time:
                self._clock.follow(self._channel)
        else:
            self._clock = SteadyClock()
        if callable(behaviors):
            behaviors = behaviors(SystemContext(
                system=o.system, robot_id=o.robot_id, clock=self._clock, channel=self._channel,
                flight_controller=o.flight_controller, channel_credentials=credentials))
        if o.follow_time:
            self._follower = TimeFollower(o.follow_time, f"{o.system}/{o.robot_id}", self._clock,
                                          self._channel, o.robot_id,
                                          channel_credentials=credentials)
        host = BehaviorHost(list(behaviors), robot_id=o.robot_id, system=o.system,
                            clock=self._clock, observer_factory=self.metrics.observer_factory,
                            before_command=self._follower.await_turn if self._follower else None)
        self.metrics_port = 0
        if o.metrics_listen:
            try:
                self.metrics_port = self.metrics.serve(o.metrics_listen)
            except OSError as error:
                raise StatusError(grpc.StatusCode.UNAVAILABLE, str(error)) from error
        try:
            host.start()
        except StatusError as error:
            raise error.rewrap(f"cannot start behaviors: {error.message}",
                               grpc.StatusCode.INVALID_ARGUMENT) from error
        self._host = host

        self._gate = AcceptGate(o.robot_id, policy)
        slots = StreamSlots(MAX_STREAMS)
        typed = TypedServices(host, self._gate, documented)
        self._system_service = BehaviorSystemService(host, self._gate, slots, typed.names)
        self._health = health_module.HealthService(slots)
        # The C++ order: BehaviorSystem, the typed services by behavior name, health.
        self._served = ([_SYSTEM_SERVICE] + [typed.names[name] for name in sorted(typed.names)]
                        + [health_module.SERVICE])
        reflection = ReflectionService(self._served, slots, {**documented, **typed.files})
        # The guard first: a call it refuses is neither run nor counted in grpc_server_*.
        interceptors = [CallGuard(policy, self._audit)]
        if o.grpc_metrics:
            interceptors.append(self.metrics.interceptor())
        self._server = grpc.server(
            concurrent.futures.ThreadPoolExecutor(max_workers=MAX_WORKERS,
                                                  thread_name_prefix="grpc"),
            interceptors=interceptors, options=SERVER_OPTIONS)
        self._server.add_generic_rpc_handlers([self._system_service.handler(),
                                               *typed.handlers(), self._health.handler(),
                                               *reflection.handlers()])
        try:
            if security.tls:
                self.grpc_port = self._server.add_secure_port(o.listen,
                                                              security.server_credentials())
            else:
                self.grpc_port = self._server.add_insecure_port(o.listen)
        except RuntimeError as error:
            raise StatusError(grpc.StatusCode.UNAVAILABLE,
                              f"cannot listen on {o.listen} (address in use or invalid); choose "
                              "another with --listen, e.g. 127.0.0.1:0") from error
        self._server.start()
        for name in [""] + self._served:
            self._health.set_serving(name, True)
        if o.coordinator:
            self._registration = CoordinatorRegistration(
                o.coordinator, robot_id=o.robot_id, system=o.system,
                address=o.advertise or advertised_address(o.listen, self.grpc_port),
                incarnation=host.events.incarnation, final_seq=host.events.latest_seq,
                log_prefix=o.system, channel_credentials=credentials)
            self._registration.start()
        if self._follower is not None:
            engines = host.engines
            clock = self._clock
            # Caught up: every behavior ran what was due, and so did the work on the clock
            # outside the ticks (ClockListener.caught_up: lease renewals).
            self._follower.start(
                lambda t: all(e.caught_up(t) for e in engines) and clock.listeners_caught_up(t),
                lambda: all(e.idle() for e in engines))

    @property
    def incarnation(self):
        return self._host.events.incarnation

    def behavior_names(self):
        return self._host.names()

    def write_port_file(self, path):
        """Writes "grpc_port=N\\nmetrics_port=M\\n" to `path` atomically (a temporary file
        renamed), as the C++ runtime does."""
        temporary = f"{path}.tmp.{os.getpid()}"
        with open(temporary, "w") as f:
            f.write(f"grpc_port={self.grpc_port}\nmetrics_port={self.metrics_port}\n")
        os.replace(temporary, path)

    def shutdown(self):
        """In order: leaves the simulator's time grants (--follow-time: commands then run at
        the last granted time), refuses new lifecycle calls, ends active behaviors with
        INTERRUPTED (their events reach the subscribers and the coordinator), unregisters naming
        the last event, ends the event streams once drained, reports every service NOT_SERVING,
        stops serving. Idempotent."""
        if self._stopped:
            return
        self._stopped = True
        if self._follower is not None:
            self._follower.stop()  # leaves the simulator's barrier first
        if self._server is not None:
            self._gate.close()
        if self._host is not None:
            self._host.stop()
        if self._registration is not None:
            self._registration.stop()
        if self._server is not None:
            self._system_service.shutdown_streams()
            for name in [""] + self._served:
                self._health.set_serving(name, False)
            self._health.close()
            self._server.stop(SHUTDOWN_GRACE_S).wait()
        if isinstance(self._clock, SimClock):
            self._clock.close()
        if self._channel is not None:
            self._channel.close()
        if self._audit is not None:
            self._audit.close()


def _fatal(program, error):
    print(f"{program}: {error.message}", file=sys.stderr, flush=True)
    return 2 if error.code == grpc.StatusCode.INVALID_ARGUMENT else 1


def run_system(behaviors, argv=None, *, system=None):
    """Parses the flags (`argv`, default sys.argv[1:]), starts a BehaviorSystemProcess hosting
    `behaviors` (a list of Behavior objects, or a callable making it from a SystemContext),
    writes the port file, serves until SIGTERM or SIGINT, then shuts it down. `system` is the
    system's name (default: the program's file name without .py). Returns the exit code: 0
    after a shutdown signal, 2 for a refused command line or behaviors that do not start, 1
    when it cannot serve."""
    argv = sys.argv[1:] if argv is None else list(argv)
    system = system or os.path.splitext(os.path.basename(sys.argv[0]))[0] or "python_behaviors"
    # Before any thread starts, so that every thread inherits the mask and only sigwait below
    # takes the signals.
    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGTERM, signal.SIGINT})
    try:
        options, port_file = parse_flags(argv, system)
        process = BehaviorSystemProcess(options, behaviors)
    except StatusError as error:
        return _fatal(system, error)
    try:
        if port_file:
            process.write_port_file(port_file)
    except OSError as error:
        process.shutdown()
        return _fatal(system, StatusError(grpc.StatusCode.UNKNOWN,
                                          f"cannot write port file {port_file}: {error}"))
    print(f"{system}: robot {options.robot_id}, behaviors [{', '.join(process.behavior_names())}"
          f"], gRPC on port {process.grpc_port}, metrics on port {process.metrics_port}, clock "
          f"{options.clock}, incarnation {process.incarnation}", file=sys.stderr, flush=True)
    received = signal.sigwait({signal.SIGTERM, signal.SIGINT})
    print(f"{system}: signal {received.value}, interrupting active behaviors and shutting down",
          file=sys.stderr, flush=True)
    process.shutdown()
    return 0

