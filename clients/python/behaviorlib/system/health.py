"""The standard gRPC health service, grpc.health.v1.Health (Check and Watch), for a Python
behavior system: what the coordinator probes to tell a silent system from a dead one, and what
the local launcher waits for before it calls a process started.

Debian packages neither grpcio-health-checking nor a Python module of health.proto, so the
protocol is implemented here on its messages. The .proto is packaged (grpc-proto:
/usr/share/grpc-proto/grpc/health/v1/health.proto), but this package's build compiles only the
repository's protos, so the messages are described at run time with descriptor_pb2 as a file
of the same name, package, messages, fields and service: the wire format is fixed by the gRPC
health-checking protocol, and a test compares this description with protoc's compilation of the
packaged file. The file goes into the default descriptor pool, where reflection finds it (a
grpc_health module imported first keeps its own, identical on the wire).

Statuses are kept per service name, "" standing for the whole server, as the C++ servers'
default health service keeps them: Check answers the status, NOT_FOUND for a service never set;
Watch sends the status at once and again at each change (SERVICE_UNKNOWN for a service never
set, until it is), and ends when the server shuts down.
"""

import threading

import grpc
from google.protobuf import descriptor_pb2

from . import _protocol

FILE_NAME = "grpc/health/v1/health.proto"
PACKAGE = "grpc.health.v1"
SERVICE = f"{PACKAGE}.Health"

# HealthCheckResponse.ServingStatus
UNKNOWN = 0
SERVING = 1
NOT_SERVING = 2
SERVICE_UNKNOWN = 3


def file_descriptor_proto():
    """health.proto as a FileDescriptorProto (without its comments and language options)."""
    file = descriptor_pb2.FileDescriptorProto(name=FILE_NAME, package=PACKAGE, syntax="proto3")
    request = file.message_type.add(name="HealthCheckRequest")
    _protocol.add_field(request, "service", 1, "string")
    response = file.message_type.add(name="HealthCheckResponse")
    status = response.enum_type.add(name="ServingStatus")
    for name, number in (("UNKNOWN", UNKNOWN), ("SERVING", SERVING),
                         ("NOT_SERVING", NOT_SERVING), ("SERVICE_UNKNOWN", SERVICE_UNKNOWN)):
        status.value.add(name=name, number=number)
    _protocol.add_field(response, "status", 1, "enum",
                        f".{PACKAGE}.HealthCheckResponse.ServingStatus")
    service = file.service.add(name="Health")
    service.method.add(name="Check", input_type=f".{PACKAGE}.HealthCheckRequest",
                       output_type=f".{PACKAGE}.HealthCheckResponse")
    service.method.add(name="Watch", input_type=f".{PACKAGE}.HealthCheckRequest",
                       output_type=f".{PACKAGE}.HealthCheckResponse", server_streaming=True)
    return file


class HealthService:
    """The statuses and the grpc.health.v1.Health service that reports them. Thread-safe.
    `stream_slots` (a _protocol.StreamSlots) bounds the Watch streams with the process's other
    streams; a Watch beyond it is refused RESOURCE_EXHAUSTED."""

    def __init__(self, stream_slots):
        file = _protocol.add_file(file_descriptor_proto())
        self._service = file.services_by_name["Health"]
        self._response = _protocol.message_class(
            file.message_types_by_name["HealthCheckResponse"])
        self._slots = stream_slots
        self._changed = threading.Condition()
        self._statuses = {}
        self._closed = False

    def handler(self):
        """The grpc.GenericRpcHandler to add to the server."""
        return _protocol.serve_service(self._service, {"Check": self.check, "Watch": self.watch})

    def set_serving(self, service, serving):
        """Sets the status of `service` ("" for the whole server) to SERVING or NOT_SERVING."""
        with self._changed:
            self._statuses[service] = SERVING if serving else NOT_SERVING
            self._changed.notify_all()

    def status(self, service):
        """The status of `service`, or None when it was never set."""
        with self._changed:
            return self._statuses.get(service)

    def close(self):
        """Ends every Watch stream once it has sent the current status (at shutdown, after the
        services were set NOT_SERVING)."""
        with self._changed:
            self._closed = True
            self._changed.notify_all()

    def check(self, request, context):
        status = self.status(request.service)
        if status is None:
            context.abort(grpc.StatusCode.NOT_FOUND, "service name unknown")
        return self._response(status=status)

    def watch(self, request, context):
        if not self._slots.take():
            context.abort(grpc.StatusCode.RESOURCE_EXHAUSTED,
                          f"too many streams open on this behavior system (at most "
                          f"{self._slots.limit}); close one and watch again")
        try:
            yield from self._watch(request.service, context)
        finally:
            self._slots.give_back()

    def _watch(self, service, context):
        def wake():
            with self._changed:
                self._changed.notify_all()

        if not context.add_callback(wake):
            return
        sent = None
        while True:
            with self._changed:
                self._changed.wait_for(lambda: self._closed or not context.is_active()
                                       or self._statuses.get(service, SERVICE_UNKNOWN) != sent)
                status = self._statuses.get(service, SERVICE_UNKNOWN)
                closed = self._closed
            if not context.is_active():
                return
            if status != sent:
                sent = status
                yield self._response(status=status)
            if closed:
                return
