"""Prometheus /metrics of a Python behavior system, with Debian's python3-prometheus-client and
the C++ systems' metric names, labels and buckets, so that one dashboard and one set of alerts
serve both:

  - per behavior (services/behaviorlib/server/behavior_metrics.cc), labelled robot, system,
    behavior: behaviorlib_activations_total, behaviorlib_terminations_total (and cause),
    behaviorlib_active_behaviors, behaviorlib_monitoring_seconds,
    behaviorlib_monitoring_cpu_seconds, behaviorlib_activation_seconds (the paper's t3),
    behaviorlib_activate_call_seconds and behaviorlib_situation_performance_ratio;
  - per gRPC method (server_kit/server_metrics.cc), labelled grpc_type, grpc_service,
    grpc_method (and grpc_code): grpc_server_started_total, grpc_server_handled_total and
    grpc_server_handling_seconds, counted by a server interceptor (--grpc-metrics). A call of a
    method the server does not serve never reaches an interceptor in grpcio, so it is not
    counted (the C++ servers count it under "unknown");
  - the audit (audit.py, in this registry): behaviorlib_audited_calls_total{identity, method,
    outcome}, every control call and every call the access policy refused;
  - the process: process_cpu_seconds_total, process_resident_memory_bytes,
    process_virtual_memory_bytes, process_start_time_seconds, process_open_fds,
    process_max_fds (the client's ProcessCollector, the same names as the C++ collector),
    behaviorlib_process_heap_in_use_bytes and behaviorlib_process_heap_free_bytes (glibc's
    mallinfo2, as in C++; absent without it), and behaviorlib_build_info (the package's
    version, grpcio's and protobuf's, the Python that runs it as "compiler", build_type
    "python").

The Python client adds a `_created` series to each counter and histogram (set
PROMETHEUS_DISABLE_CREATED_SERIES=true to leave them out). The behavior observer's on_blocked
changes nothing here: the C++ system reports a behavior blocked by the watchdog NOT_SERVING,
but a Python engine abandons the stuck thread and serves its behavior again at once.

/metrics is served over plain HTTP, as by the C++ servers (decision 23): off loopback it belongs
on a private network. Its server threads are daemons left to the process's exit.
"""

import ctypes
import ctypes.util
import importlib.metadata
import platform
import socket
import sys
import threading
import time
from socketserver import ThreadingMixIn
from wsgiref.simple_server import WSGIRequestHandler, WSGIServer, make_server

import grpc
import google.protobuf
from prometheus_client import (CollectorRegistry, Counter, Gauge, Histogram, ProcessCollector,
                               make_wsgi_app)
from prometheus_client.core import GaugeMetricFamily

from behaviorlib.v1 import behavior_pb2

from .engine import BehaviorObserver, cause_name

# The paper's t1 is 0.1-3.9 us; cover 100 ns .. 10 ms.
MONITORING_BUCKETS = (1e-7, 2.5e-7, 5e-7, 1e-6, 2.5e-6, 5e-6, 1e-5, 2.5e-5, 5e-5, 1e-4, 1e-3,
                      1e-2)
# The paper's t3 is 0.6-51.5 ms. Cover 10 us .. 1 s.
ACTIVATION_BUCKETS = (1e-5, 2.5e-5, 5e-5, 1e-4, 2.5e-4, 5e-4, 1e-3, 2.5e-3, 1e-2, 5e-2, 0.25,
                      1.0)
# 100 us (a loopback call) to 10 s; longer streams fall in +Inf.
GRPC_BUCKETS = (0.0001, 0.00025, 0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25,
                0.5, 1, 2.5, 5, 10)

_CAUSES = (behavior_pb2.TERMINATION_CAUSE_GOAL_ACHIEVED, behavior_pb2.TERMINATION_CAUSE_TIME_OUT,
           behavior_pb2.TERMINATION_CAUSE_WRONG_PROGRESS,
           behavior_pb2.TERMINATION_CAUSE_SITUATION_CHANGE,
           behavior_pb2.TERMINATION_CAUSE_PROCESS_FAILURE,
           behavior_pb2.TERMINATION_CAUSE_INTERRUPTED)
_BEHAVIOR_LABELS = ("robot", "system", "behavior")
_METHOD_LABELS = ("grpc_type", "grpc_service", "grpc_method")


class _MallInfo2(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in (
        "arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks",
        "fordblks", "keepcost")]


class _HeapCollector:
    """behaviorlib_process_heap_*: glibc's allocator statistics (server_metrics.cc heapStat)."""

    def __init__(self, mallinfo2):
        self._mallinfo2 = mallinfo2

    def collect(self):
        info = self._mallinfo2()
        yield GaugeMetricFamily(
            "behaviorlib_process_heap_in_use_bytes",
            "Bytes the allocator has handed out and not had back (malloc arenas and mmap'd "
            "blocks).", value=info.uordblks + info.hblkhd)
        yield GaugeMetricFamily(
            "behaviorlib_process_heap_free_bytes",
            "Bytes the allocator holds from the system but has not handed out (freed, not yet "
            "returned).", value=info.fordblks)


def _mallinfo2():
    """glibc's mallinfo2, or None where the C library has none."""
    library = ctypes.util.find_library("c")
    function = getattr(ctypes.CDLL(library), "mallinfo2", None) if library else None
    if function is None:
        return None
    function.restype = _MallInfo2
    function.argtypes = []
    return function


def _package_version():
    try:
        return importlib.metadata.version("behaviorlib")
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


class _Observer(BehaviorObserver):
    """One behavior's series, resolved once at start, never per tick."""

    def __init__(self, metrics, behavior):
        labels = (metrics.robot_id, metrics.system, behavior)
        self._activations = metrics.activations.labels(*labels)
        self._terminations = {cause: metrics.terminations.labels(*labels, cause_name(cause))
                              for cause in _CAUSES}
        self._active = metrics.active.labels(*labels)
        self._active.set(0)
        self._monitoring = metrics.monitoring.labels(*labels)
        self._monitoring_cpu = metrics.monitoring_cpu.labels(*labels)
        self._activation = metrics.activation.labels(*labels)
        self._activate_call = metrics.activate_call.labels(*labels)
        self._performance = metrics.performance.labels(*labels)
        self._performance.set(1.0)

    def on_activated(self, activate_call):
        self._activate_call.observe(activate_call / 1e9)
        self._activations.inc()
        self._active.set(1)

    def on_first_execute(self, activation_latency):
        self._activation.observe(activation_latency / 1e9)

    def on_finished(self, cause):
        counter = self._terminations.get(cause)
        if counter is not None:
            counter.inc()
        self._active.set(0)

    def on_monitoring(self, wall, cpu):
        self._monitoring.observe(wall / 1e9)
        self._monitoring_cpu.observe(cpu / 1e9)

    def on_situation(self, performance_ratio):
        self._performance.set(performance_ratio)


def _code_of(context):
    """The status a call ended with, as its handler left it."""
    code = context.code()
    if code is not None:
        return code
    return grpc.StatusCode.OK if context.is_active() else grpc.StatusCode.CANCELLED


class _Interceptor(grpc.ServerInterceptor):
    """Counts and times every call of a served method (server_metrics.cc)."""

    def __init__(self, metrics):
        self._metrics = metrics
        self._series_lock = threading.Lock()
        self._series = {}

    def _method_series(self, kind, method):
        key = (kind, method)
        with self._series_lock:
            series = self._series.get(key)
            if series is None:
                service, _, name = method.lstrip("/").rpartition("/")
                labels = (kind, service, name)
                series = (self._metrics.started.labels(*labels),
                          self._metrics.handling.labels(*labels), labels)
                self._series[key] = series
            return series

    def intercept_service(self, continuation, handler_call_details):
        handler = continuation(handler_call_details)
        if handler is None:
            return None
        streaming = (handler.request_streaming, handler.response_streaming)
        kind, make, behavior = {
            (False, False): ("unary", grpc.unary_unary_rpc_method_handler, handler.unary_unary),
            (False, True): ("server_stream", grpc.unary_stream_rpc_method_handler,
                            handler.unary_stream),
            (True, False): ("client_stream", grpc.stream_unary_rpc_method_handler,
                            handler.stream_unary),
            (True, True): ("bidi_stream", grpc.stream_stream_rpc_method_handler,
                           handler.stream_stream),
        }[streaming]
        started, handling, labels = self._method_series(kind, handler_call_details.method)
        handled = self._metrics.handled

        def finish(start, code):
            handling.observe(time.monotonic() - start)
            handled.labels(*labels, code.name).inc()

        if handler.response_streaming:
            def counted(request, context):
                started.inc()
                start = time.monotonic()
                try:
                    yield from behavior(request, context)
                except GeneratorExit:
                    finish(start, grpc.StatusCode.CANCELLED)
                    raise
                except BaseException:
                    finish(start, context.code() or grpc.StatusCode.UNKNOWN)
                    raise
                finish(start, _code_of(context))
        else:
            def counted(request, context):
                started.inc()
                start = time.monotonic()
                try:
                    response = behavior(request, context)
                except BaseException:
                    finish(start, context.code() or grpc.StatusCode.UNKNOWN)
                    raise
                finish(start, _code_of(context))
                return response
        return make(counted, request_deserializer=handler.request_deserializer,
                    response_serializer=handler.response_serializer)


class _Server(ThreadingMixIn, WSGIServer):
    daemon_threads = True


class _QuietHandler(WSGIRequestHandler):
    def log_message(self, format, *args):  # noqa: A002 - the base class's signature
        """Scrapes are not logged."""


def _host_port(address):
    """("host", port) of "host:port" or "[v6]:port"."""
    host, _, port = address.rpartition(":")
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    return host, int(port)


class SystemMetrics:
    """The metrics of one behavior-system process, in a registry of its own."""

    def __init__(self, robot_id, system):
        self.robot_id = robot_id
        self.system = system
        self.registry = registry = CollectorRegistry()
        self.activations = Counter("behaviorlib_activations_total", "Activations started",
                                   _BEHAVIOR_LABELS, registry=registry)
        self.terminations = Counter("behaviorlib_terminations_total",
                                    "Activations finished, by termination cause",
                                    _BEHAVIOR_LABELS + ("cause",), registry=registry)
        self.active = Gauge("behaviorlib_active_behaviors",
                            "1 while the behavior is active (or paused)", _BEHAVIOR_LABELS,
                            registry=registry)
        self.monitoring = Histogram(
            "behaviorlib_monitoring_seconds",
            "Wall time of the four monitoring functions of one tick (the paper's t1)",
            _BEHAVIOR_LABELS, registry=registry, buckets=MONITORING_BUCKETS)
        self.monitoring_cpu = Histogram(
            "behaviorlib_monitoring_cpu_seconds",
            "CPU time of the thread running the four monitoring functions of one tick (the "
            "paper's t1, without preemption)", _BEHAVIOR_LABELS, registry=registry,
            buckets=MONITORING_BUCKETS)
        self.activation = Histogram(
            "behaviorlib_activation_seconds",
            "Activate request received until the first on_execute (the paper's t3)",
            _BEHAVIOR_LABELS, registry=registry, buckets=ACTIVATION_BUCKETS)
        self.activate_call = Histogram(
            "behaviorlib_activate_call_seconds",
            "Activate request received until the activation was decided (check_situation and "
            "on_activate included): the part of t3 before the first tick", _BEHAVIOR_LABELS,
            registry=registry, buckets=ACTIVATION_BUCKETS)
        self.performance = Gauge("behaviorlib_situation_performance_ratio",
                                 "Latest performance estimate of check_situation, in [0, 1]",
                                 _BEHAVIOR_LABELS, registry=registry)
        self.started = Counter("grpc_server_started_total",
                               "Calls started on the server, by type, service and method.",
                               _METHOD_LABELS, registry=registry)
        self.handled = Counter(
            "grpc_server_handled_total",
            "Calls completed on the server, by type, service, method and status code (a stream "
            "ended by its client counts as CANCELLED).", _METHOD_LABELS + ("grpc_code",),
            registry=registry)
        self.handling = Histogram(
            "grpc_server_handling_seconds",
            "Time from a call's arrival to its status, by type, service and method (a stream's "
            "whole life).", _METHOD_LABELS, registry=registry, buckets=GRPC_BUCKETS)
        Gauge("behaviorlib_build_info",
              "1, labelled with the version of behaviorlib and of the libraries it was built "
              "with.", ("version", "grpc_version", "protobuf_version", "compiler", "build_type"),
              registry=registry).labels(
                  _package_version(), grpc.__version__, google.protobuf.__version__,
                  f"{platform.python_implementation()} {platform.python_version()}",
                  "python").set(1)
        ProcessCollector(registry=registry)
        mallinfo2 = _mallinfo2()
        if mallinfo2 is not None:
            registry.register(_HeapCollector(mallinfo2))

    def observer_factory(self, engine):
        """The BehaviorObserver of one behavior (BehaviorHost's observer_factory)."""
        return _Observer(self, engine.name)

    def interceptor(self):
        """The grpc.ServerInterceptor that counts the calls (grpc_server_*)."""
        return _Interceptor(self)

    def serve(self, address):
        """Serves /metrics on `address` ("host:port", port 0 picks one) on daemon threads;
        returns the bound port. Raises OSError with an actionable message when it cannot
        bind."""
        host, port = _host_port(address)
        if not (host in ("localhost", "::1") or host.startswith("127.")):
            print(f"note: --metrics-listen {address} serves plain HTTP: keep it on a private "
                  "network", file=sys.stderr)
        server_class = type("_MetricsServer", (_Server,), {})
        if ":" in host:
            server_class.address_family = socket.AF_INET6
        try:
            httpd = make_server(host, port, make_wsgi_app(self.registry), server_class,
                                handler_class=_QuietHandler)
        except OSError as error:
            raise OSError(f"cannot serve metrics on {address} ({error}); is the port in use? "
                          "choose another with --metrics-listen") from error
        threading.Thread(target=httpd.serve_forever, daemon=True, name="metrics").start()
        return httpd.server_address[1]
