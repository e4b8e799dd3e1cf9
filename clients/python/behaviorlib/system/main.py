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
topic is not read), --flight-controller (given to behaviors), --insecure, --grpc-metrics; and
--descriptor-set, a FileDescriptorSet with source info (protoc --include_imports
--include_source_info) whose comments describe the behaviors of protos compiled outside this
package, in ListBehaviors and reflection (the package's own behaviorlib/v1/descriptors.binpb is
read first). Not built yet, and refused with a message saying so rather than ignored: --config
(the YAML of decision 45), --link-loss-timeout-s and --link-loss-action, and TLS (--tls-cert,
--tls-key, --tls-ca, --access-policy): without TLS the process listens only on loopback unless
--insecure, as the C++ servers do.

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
from .channel import DataChannel
from .clock import SteadyClock
from .metrics import SystemMetrics
from .parameters import StatusError
from .reflection import ReflectionService
from .registration import CoordinatorRegistration, advertised_address
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
    "tls_cert": "TLS (--tls-cert)",
    "tls_key": "TLS (--tls-key)",
    "tls_ca": "TLS (--tls-ca)",
    "access_policy": "--access-policy (roles need TLS)",
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
         help="allow plaintext gRPC on an address other than loopback")
    flag("grpc-metrics", type=_flag_bool, nargs="?", const=True, default=True,
         help="count and time every call by service, method and status code (grpc_server_*)")
    flag("descriptor-set", action="append", default=[],
         help="a FileDescriptorSet with source info (protoc --include_imports "
              "--include_source_info) describing behaviors compiled outside this package; "
              "may be repeated")
    for name in ("config", "link-loss-timeout-s", "link-loss-action", "tls-cert",
                 "tls-key", "tls-ca", "access-policy"):
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
        grpc_metrics=args.grpc_metrics, descriptor_sets=tuple(args.descriptor_set))
    return options, args.port_file


def _is_loopback(address):
    if address.startswith(("unix:", "unix-abstract:")):
        return True
    host = address.rpartition(":")[0].strip("[]")
    return host in ("localhost", "::1") or host.startswith("127.")


def _check_listen(options):
    """Plaintext only on loopback, unless --insecure (transport_security.cc)."""
    if _is_loopback(options.listen):
        return
    if options.insecure:
        print(f"warning: --listen {options.listen} without TLS (--insecure): anyone who can "
              "reach this port can command, land or kill the vehicles", file=sys.stderr)
        return
    raise StatusError(grpc.StatusCode.INVALID_ARGUMENT,
                      f"--listen {options.listen} is not a loopback address and there is no TLS: "
                      "anyone who could reach it could command, land or kill the vehicles. Python "
                      "behavior systems serve no TLS yet: give --insecure to accept that risk on "
                      "a private network")


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
        try:
            self._start(options, behaviors)
        except BaseException:
            self.shutdown()
            raise

    def _start(self, o, behaviors):
        _check_listen(o)
        documented = _documented_files(o.descriptor_sets)
        if o.channel:
            self._channel = DataChannel(o.channel)
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
                flight_controller=o.flight_controller))
        self.metrics = SystemMetrics(o.robot_id, o.system)
        if o.follow_time:
            self._follower = TimeFollower(o.follow_time, f"{o.system}/{o.robot_id}", self._clock,
                                          self._channel, o.robot_id)
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

        self._gate = AcceptGate()
        slots = StreamSlots(MAX_STREAMS)
        typed = TypedServices(host, self._gate, documented)
        self._system_service = BehaviorSystemService(host, self._gate, slots, typed.names)
        self._health = health_module.HealthService(slots)
        # The C++ order: BehaviorSystem, the typed services by behavior name, health.
        self._served = ([_SYSTEM_SERVICE] + [typed.names[name] for name in sorted(typed.names)]
                        + [health_module.SERVICE])
        reflection = ReflectionService(self._served, slots, {**documented, **typed.files})
        self._server = grpc.server(
            concurrent.futures.ThreadPoolExecutor(max_workers=MAX_WORKERS,
                                                  thread_name_prefix="grpc"),
            interceptors=[self.metrics.interceptor()] if o.grpc_metrics else None,
            options=SERVER_OPTIONS)
        self._server.add_generic_rpc_handlers([self._system_service.handler(),
                                               *typed.handlers(), self._health.handler(),
                                               *reflection.handlers()])
        try:
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
                log_prefix=o.system)
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

