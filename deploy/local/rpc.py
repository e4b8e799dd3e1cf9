"""gRPC calls to the stack's servers through server reflection only.

No generated Python code: message classes are built from the descriptors each
server sends (reflection_client.py), requests and replies
are dicts in proto JSON form. Needs Debian's python3-grpcio and
python3-protobuf.

    client = Client("127.0.0.1:50060", ["behaviorlib.v1.Coordinator"])
    client.call("behaviorlib.v1.Coordinator", "ListSystems", {})
    for reply in client.stream("behaviorlib.v1.Coordinator", "WatchEvents", {}):
        ...
    health_status("127.0.0.1:50060")   # "SERVING", or raises grpc.RpcError
"""

import grpc
from google.protobuf import json_format

import reflection_client as rc

DEFAULT_TIMEOUT_S = 10.0

# grpc.health.v1 by hand: HealthCheckRequest{service = 1}, HealthCheckResponse
# {status = 1 (enum)}; the servers' reflection does not describe it.
_HEALTH_STATUS = {0: "UNKNOWN", 1: "SERVING", 2: "NOT_SERVING", 3: "SERVICE_UNKNOWN"}


def _encode_health_request(service):
    data = service.encode()
    if not data:
        return b""
    assert len(data) < 128, "service name too long for this encoder"
    return b"\x0a" + bytes([len(data)]) + data


def _decode_health_response(data):
    # Field 1, varint: 0x08 then the value (0..3 fits one byte); absent = 0.
    if len(data) >= 2 and data[0] == 0x08:
        return _HEALTH_STATUS.get(data[1], f"status {data[1]}")
    return _HEALTH_STATUS[0]


def health_status(address, service="", timeout=2.0):
    """grpc.health.v1.Health/Check of `service` ("" = the whole server):
    "SERVING", "NOT_SERVING", ...; raises grpc.RpcError when unreachable."""
    with rc.open_channel(address) as channel:
        check = channel.unary_unary("/grpc.health.v1.Health/Check",
                                    request_serializer=_encode_health_request,
                                    response_deserializer=_decode_health_response)
        return check(service, timeout=timeout)


def to_dict(message):
    """A message as a dict in proto JSON form (field names as in the .proto)."""
    return json_format.MessageToDict(message, preserving_proto_field_name=True)


class Client:
    """One server: a channel, and a descriptor pool fetched by reflection for
    the services named."""

    def __init__(self, address, services):
        self.address = address
        self.channel = rc.open_channel(address)
        self.pool = rc.pool_for_symbols(address, services)

    def close(self):
        self.channel.close()

    def has_method(self, service, method):
        return method in self.pool.FindServiceByName(service).methods_by_name

    def _method(self, service, method):
        desc = self.pool.FindServiceByName(service).methods_by_name[method]
        request_class = rc.message_class(self.pool, desc.input_type.full_name)
        response_class = rc.message_class(self.pool, desc.output_type.full_name)
        return request_class, response_class

    def _request(self, request_class, request):
        return json_format.ParseDict(request or {}, request_class(), descriptor_pool=self.pool)

    def call(self, service, method, request=None, timeout=DEFAULT_TIMEOUT_S):
        """Unary call; the reply as a dict."""
        request_class, response_class = self._method(service, method)
        call = self.channel.unary_unary(f"/{service}/{method}",
                                        request_serializer=request_class.SerializeToString,
                                        response_deserializer=response_class.FromString)
        return to_dict(call(self._request(request_class, request), timeout=timeout))

    def stream(self, service, method, request=None, timeout=None):
        """Server-streaming call: the call object, iterable (each reply as a
        message; use to_dict) and cancellable with .cancel()."""
        request_class, response_class = self._method(service, method)
        call = self.channel.unary_stream(f"/{service}/{method}",
                                         request_serializer=request_class.SerializeToString,
                                         response_deserializer=response_class.FromString)
        return call(self._request(request_class, request), timeout=timeout)

    def bidi(self, service, method, requests, timeout=None):
        """Bidirectional streaming call: `requests` yields dicts in proto JSON
        form (the stream half-closes when it ends); the call object, iterable
        (each reply as a message) and cancellable with .cancel()."""
        request_class, response_class = self._method(service, method)
        call = self.channel.stream_stream(f"/{service}/{method}",
                                          request_serializer=request_class.SerializeToString,
                                          response_deserializer=response_class.FromString)
        return call((self._request(request_class, r) for r in requests), timeout=timeout)
