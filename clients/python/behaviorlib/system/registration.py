"""Registration of a Python behavior system with the coordinator: a port of
services/behaviorlib/server/coordinator_registration.cc, with the behaviorlib.v1.Coordinator
messages.

RegisterSystem at start, retried with backoff (100 ms doubling to 2 s) while the coordinator is
not up (it reads the system's ListBehaviors before it answers, hence a 5 s deadline); Heartbeat
at the interval the coordinator asks for (clamped to [50 ms, 1 min], 1 s when it asks none);
registering again when the coordinator restarted (Heartbeat answers another incarnation, or
NOT_FOUND) or was unreachable; a FAILED_PRECONDITION (another live incarnation serves this robot
and system) is said once and heartbeats go on; UnregisterSystem on a clean shutdown, naming the
last event's seq so that the coordinator reads the stream up to it. It runs on a thread of its
own and never blocks the behaviors; each line it logs goes to stderr, once per kind of failure.

    registration = CoordinatorRegistration("127.0.0.1:50060", robot_id="drone1",
                                           system="my_behaviors", address="127.0.0.1:50061",
                                           incarnation=events.incarnation,
                                           final_seq=events.latest_seq)
    registration.start()
    ...                      # at shutdown, after the behaviors stopped:
    registration.stop()      # UnregisterSystem with the last event's seq
"""

import socket
import sys
import threading

import grpc

from behaviorlib.v1 import coordinator_pb2, coordinator_pb2_grpc

from .security import open_channel

INITIAL_BACKOFF_S = 0.1
MAX_BACKOFF_S = 2.0
DEFAULT_HEARTBEAT_S = 1.0
REGISTER_DEADLINE_S = 5.0

# gRPC's default reconnect backoff grows to 120 s; a restarted coordinator (or simulator, for
# time_follower.py) must be found again within our own 2 s retry period. Each connection attempt gets at least 5 s (gRPC's "minimum
# connect timeout"): at 100 ms, a server slow to send its HTTP/2 settings on a loaded machine
# failed the call.
RECONNECTING_CHANNEL_OPTIONS = (
    ("grpc.initial_reconnect_backoff_ms", int(INITIAL_BACKOFF_S * 1000)),
    ("grpc.min_reconnect_backoff_ms", 5000),
    ("grpc.max_reconnect_backoff_ms", int(MAX_BACKOFF_S * 1000)),
)


def advertised_address(listen, port):
    """The "host:port" under which a server started with `--listen listen` and bound to `port`
    is reachable: the listen host with the bound port, or this machine's host name when it
    listens on every interface (0.0.0.0, [::])."""
    host = listen.rpartition(":")[0] if ":" in listen else listen
    if host in ("", "0.0.0.0", "[::]", "::", "*"):
        host = socket.gethostname() or "localhost"
    return f"{host}:{port}"


def _describe(error):
    return f"{error.details()} (code {error.code().value[0]})"


class CoordinatorRegistration:
    """Registers one system with the coordinator at `coordinator` and keeps it registered.
    `final_seq()` gives the seq of the last event emitted, read when unregistering;
    `channel_credentials` (the process's TLS, security.TransportSecurity) makes the channel
    TLS."""

    def __init__(self, coordinator, *, robot_id, system, address, incarnation, final_seq,
                 log_prefix="behavior system", channel_credentials=None):
        self._coordinator = coordinator
        self._robot_id = robot_id
        self._system = system
        self._address = address
        self._incarnation = incarnation
        self._final_seq = final_seq
        self._log_prefix = log_prefix
        self._channel = open_channel(coordinator, channel_credentials, RECONNECTING_CHANNEL_OPTIONS)
        self._stub = coordinator_pb2_grpc.CoordinatorStub(self._channel)
        self._thread = threading.Thread(target=self._run, daemon=True,
                                        name="coordinator-registration")
        self._lock = threading.Condition()
        self._stopping = False
        self._stopped = False
        self._in_flight = None
        self._registered = False
        self._registrations = 0

    def start(self):
        self._thread.start()

    def registered(self):
        """True while the coordinator has accepted the registration."""
        with self._lock:
            return self._registered

    def registration_count(self):
        """Successful RegisterSystem calls so far."""
        with self._lock:
            return self._registrations

    def _log(self, line):
        print(f"{self._log_prefix}: {line}", file=sys.stderr, flush=True)

    def _wait(self, seconds):
        """Waits `seconds` unless stopped meanwhile."""
        with self._lock:
            self._lock.wait_for(lambda: self._stopping, seconds)

    def _call(self, method, request, deadline):
        """One unary call with `deadline` seconds, cancellable by stop(): its response, or the
        grpc.RpcError it failed with (CANCELLED once stopping)."""
        with self._lock:
            if self._stopping:
                return None, None
            future = method.future(request, timeout=deadline)
            self._in_flight = future
        try:
            return future.result(), None
        except grpc.RpcError as error:
            return None, error
        except grpc.FutureCancelledError:
            return None, None
        finally:
            with self._lock:
                self._in_flight = None

    def _run(self):
        backoff = INITIAL_BACKOFF_S
        interval = DEFAULT_HEARTBEAT_S
        coordinator_incarnation = ""
        last_complaint = ""
        where = f"the coordinator at {self._coordinator}"
        while True:
            with self._lock:
                if self._stopping:
                    return
                registered = self._registered
            if not registered:
                response, error = self._call(self._stub.RegisterSystem,
                                             coordinator_pb2.RegisterSystemRequest(
                                                 robot_id=self._robot_id, system=self._system,
                                                 address=self._address,
                                                 incarnation=self._incarnation),
                                             REGISTER_DEADLINE_S)
                if response is not None:
                    with self._lock:
                        self._registered = True
                        self._registrations += 1
                    coordinator_incarnation = response.coordinator_incarnation
                    asked = response.heartbeat_interval.ToMilliseconds() / 1000
                    interval = min(max(asked, 0.05), 60.0) if asked > 0 else DEFAULT_HEARTBEAT_S
                    backoff = INITIAL_BACKOFF_S
                    last_complaint = ""
                    self._log(f"registered with {where} as {self._address} "
                              f"({len(response.behaviors)} behaviors)")
                    continue
                if error is None or error.code() == grpc.StatusCode.CANCELLED:
                    continue  # stopping
                # Said once per kind of failure, not at every retry.
                complaint = f"cannot register with {where}: {_describe(error)}"
                if complaint != last_complaint:
                    self._log(complaint + "; retrying")
                last_complaint = complaint
                self._wait(backoff)
                backoff = min(backoff * 2, MAX_BACKOFF_S)
                continue

            self._wait(interval)
            response, error = self._call(self._stub.Heartbeat, coordinator_pb2.HeartbeatRequest(
                robot_id=self._robot_id, system=self._system, incarnation=self._incarnation),
                max(interval, 1.0))
            if response is None and (error is None or error.code() == grpc.StatusCode.CANCELLED):
                continue  # stopping
            again = ""
            if response is not None:
                if response.coordinator_incarnation != coordinator_incarnation:
                    again = f"{where} restarted"
            elif error.code() == grpc.StatusCode.FAILED_PRECONDITION:
                complaint = f"{where} refuses this process: {_describe(error)}"
                if complaint != last_complaint:
                    self._log(complaint)
                last_complaint = complaint
            elif error.code() == grpc.StatusCode.NOT_FOUND:
                again = f"{where} no longer knows this process ({error.details()})"
            else:
                again = f"lost {where} ({_describe(error)})"
            if again:
                self._log(again + "; registering again")
                with self._lock:
                    self._registered = False
                backoff = INITIAL_BACKOFF_S

    def stop(self, timeout=1.0):
        """Stops heartbeating and, if registered, calls UnregisterSystem (waiting at most
        `timeout` seconds). Idempotent."""
        with self._lock:
            if self._stopped:
                return
            self._stopped = True
            self._stopping = True
            self._lock.notify_all()
            if self._in_flight is not None:
                self._in_flight.cancel()
        if self._thread.is_alive():
            self._thread.join()
        with self._lock:
            registered = self._registered
            self._registered = False
        try:
            if not registered:
                return
            request = coordinator_pb2.UnregisterSystemRequest(
                robot_id=self._robot_id, system=self._system, incarnation=self._incarnation,
                final_seq=self._final_seq())
            try:
                self._stub.UnregisterSystem(request, timeout=timeout)
            except grpc.RpcError as error:
                self._log(f"could not unregister from the coordinator at {self._coordinator}: "
                          f"{_describe(error)}")
                return
            self._log(f"unregistered from the coordinator at {self._coordinator} (last event "
                      f"seq {request.final_seq})")
        finally:
            self._channel.close()
