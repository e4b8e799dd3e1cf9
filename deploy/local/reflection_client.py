"""Minimal gRPC server reflection client (grpc.reflection.v1 / v1alpha).

Needs only Debian's python3-grpcio and python3-protobuf (no grpc_reflection
package, no generated stubs): the reflection messages are described at import
time with descriptor_pb2 in a private descriptor pool.

    import reflection_client as rc
    rc.list_services("127.0.0.1:50051")
    files = rc.file_containing_symbol(addr, "behaviorlib.v1.BehaviorSystem")
    pool = rc.pool_for_symbol(addr, "behaviorlib.v1.BehaviorSystem")
    Request = rc.message_class(pool, "behaviorlib.v1.ListBehaviorsRequest")
    Response = rc.message_class(pool, "behaviorlib.v1.ListBehaviorsResponse")
    call = channel.unary_unary("/behaviorlib.v1.BehaviorSystem/ListBehaviors",
                               request_serializer=Request.SerializeToString,
                               response_deserializer=Response.FromString)
    # or simply: rc.unary_call(channel, pool, "behaviorlib.v1.BehaviorSystem",
    #                          "ListBehaviors", {})

Every function opens one reflection stream per call. `version` selects the
reflection service: None tries grpc.reflection.v1 first and falls back to
v1alpha when the server does not implement v1.

Command line (a tiny grpcurl stand-in):
    /usr/bin/python3 reflection_client.py ADDRESS list
    /usr/bin/python3 reflection_client.py ADDRESS describe SYMBOL
"""

import sys

import grpc
from google.protobuf import descriptor_pb2
from google.protobuf import descriptor_pool
from google.protobuf import json_format
from google.protobuf import message_factory

__all__ = [
    "ReflectionError",
    "list_services",
    "file_by_filename",
    "file_containing_symbol",
    "file_containing_extension",
    "all_extension_numbers_of_type",
    "pool_for_symbol",
    "pool_for_symbols",
    "pool_from_files",
    "message_class",
    "leading_comments",
    "unary_call",
    "use_tls",
    "open_channel",
]

DEFAULT_TIMEOUT = 10.0
VERSIONS = ("v1", "v1alpha")

# Channel credentials of this process (use_tls); None: plaintext.
_CREDENTIALS = None


def use_tls(cert_file, key_file, ca_file):
    """Every channel this process opens from now on uses mutual TLS with
    this certificate, key and CA (PEM files), as the servers' --tls-cert,
    --tls-key and --tls-ca."""
    global _CREDENTIALS
    with open(ca_file, "rb") as ca, open(key_file, "rb") as key, open(cert_file, "rb") as cert:
        _CREDENTIALS = grpc.ssl_channel_credentials(root_certificates=ca.read(),
                                                    private_key=key.read(),
                                                    certificate_chain=cert.read())


def open_channel(address):
    """A channel to `address`: TLS after use_tls(), plaintext otherwise."""
    if _CREDENTIALS is not None:
        return grpc.secure_channel(address, _CREDENTIALS)
    return grpc.insecure_channel(address)


class ReflectionError(Exception):
    """The server answered with an error_response."""

    def __init__(self, code, message):
        super().__init__(f"{code.name}: {message}")
        self.code = code  # grpc.StatusCode
        self.message = message


def message_class(pool, full_name):
    """The Python class of message `full_name` in `pool`."""
    descriptor = pool.FindMessageTypeByName(full_name)
    get_class = getattr(message_factory, "GetMessageClass", None)  # protobuf >= 4.22
    if get_class is not None:
        return get_class(descriptor)
    return message_factory.MessageFactory(pool).GetPrototype(descriptor)


# --- the reflection protocol, described by hand -----------------------------

_F = descriptor_pb2.FieldDescriptorProto


def _reflection_file(package):
    """FileDescriptorProto equivalent (on the wire) to reflection.proto."""
    file = descriptor_pb2.FileDescriptorProto(
        name=f"reflection_client/{package}.proto", package=package, syntax="proto3")

    def message(name, fields, oneof=None):
        msg = file.message_type.add(name=name)
        if oneof:
            msg.oneof_decl.add(name=oneof)
        for field_name, number, field_type, extra in fields:
            field = msg.field.add(name=field_name, number=number, type=field_type,
                                  label=_F.LABEL_OPTIONAL, json_name=field_name)
            if "type_name" in extra:
                field.type_name = f".{package}.{extra['type_name']}"
            if extra.get("repeated"):
                field.label = _F.LABEL_REPEATED
            if extra.get("oneof"):
                field.oneof_index = 0

    one = {"oneof": True}
    message("ServerReflectionRequest", [
        ("host", 1, _F.TYPE_STRING, {}),
        ("file_by_filename", 3, _F.TYPE_STRING, one),
        ("file_containing_symbol", 4, _F.TYPE_STRING, one),
        ("file_containing_extension", 5, _F.TYPE_MESSAGE,
         {"oneof": True, "type_name": "ExtensionRequest"}),
        ("all_extension_numbers_of_type", 6, _F.TYPE_STRING, one),
        ("list_services", 7, _F.TYPE_STRING, one),
    ], oneof="message_request")
    message("ExtensionRequest", [
        ("containing_type", 1, _F.TYPE_STRING, {}),
        ("extension_number", 2, _F.TYPE_INT32, {}),
    ])
    message("ServerReflectionResponse", [
        ("valid_host", 1, _F.TYPE_STRING, {}),
        ("original_request", 2, _F.TYPE_MESSAGE, {"type_name": "ServerReflectionRequest"}),
        ("file_descriptor_response", 4, _F.TYPE_MESSAGE,
         {"oneof": True, "type_name": "FileDescriptorResponse"}),
        ("all_extension_numbers_response", 5, _F.TYPE_MESSAGE,
         {"oneof": True, "type_name": "ExtensionNumberResponse"}),
        ("list_services_response", 6, _F.TYPE_MESSAGE,
         {"oneof": True, "type_name": "ListServiceResponse"}),
        ("error_response", 7, _F.TYPE_MESSAGE, {"oneof": True, "type_name": "ErrorResponse"}),
    ], oneof="message_response")
    message("FileDescriptorResponse", [
        ("file_descriptor_proto", 1, _F.TYPE_BYTES, {"repeated": True}),
    ])
    message("ExtensionNumberResponse", [
        ("base_type_name", 1, _F.TYPE_STRING, {}),
        ("extension_number", 2, _F.TYPE_INT32, {"repeated": True}),
    ])
    message("ListServiceResponse", [
        ("service", 1, _F.TYPE_MESSAGE, {"repeated": True, "type_name": "ServiceResponse"}),
    ])
    message("ServiceResponse", [("name", 1, _F.TYPE_STRING, {})])
    message("ErrorResponse", [
        ("error_code", 1, _F.TYPE_INT32, {}),
        ("error_message", 2, _F.TYPE_STRING, {}),
    ])
    return file


_PROTOCOL_POOL = descriptor_pool.DescriptorPool()
_MESSAGES = {}
for _version in VERSIONS:
    _package = f"grpc.reflection.{_version}"
    _PROTOCOL_POOL.AddSerializedFile(_reflection_file(_package).SerializeToString())
    _MESSAGES[_version] = (
        message_class(_PROTOCOL_POOL, f"{_package}.ServerReflectionRequest"),
        message_class(_PROTOCOL_POOL, f"{_package}.ServerReflectionResponse"),
    )

_STATUS_BY_CODE = {status.value[0]: status for status in grpc.StatusCode}


def _exchange_once(channel, version, request_fields, timeout):
    request_class, response_class = _MESSAGES[version]
    request = request_class()
    for name, value in request_fields.items():
        if isinstance(value, dict):  # file_containing_extension
            sub = getattr(request, name)
            for sub_name, sub_value in value.items():
                setattr(sub, sub_name, sub_value)
        else:
            setattr(request, name, value)
    call = channel.stream_stream(
        f"/grpc.reflection.{version}.ServerReflection/ServerReflectionInfo",
        request_serializer=request_class.SerializeToString,
        response_deserializer=response_class.FromString)
    responses = list(call(iter([request]), timeout=timeout))
    if len(responses) != 1:
        raise RuntimeError(f"expected one reflection response, got {len(responses)}")
    response = responses[0]
    if response.WhichOneof("message_response") == "error_response":
        error = response.error_response
        code = _STATUS_BY_CODE.get(error.error_code, grpc.StatusCode.UNKNOWN)
        raise ReflectionError(code, error.error_message)
    return response


def _ask(address, request_fields, version, timeout):
    """One request on a fresh stream; returns the ServerReflectionResponse."""
    versions = (version,) if version else VERSIONS
    with open_channel(address) as channel:
        for i, v in enumerate(versions):
            try:
                return _exchange_once(channel, v, request_fields, timeout)
            except grpc.RpcError as error:
                last = i == len(versions) - 1
                if last or error.code() != grpc.StatusCode.UNIMPLEMENTED:
                    raise
    raise AssertionError("unreachable")


def _files(response):
    files = []
    for blob in response.file_descriptor_response.file_descriptor_proto:
        file = descriptor_pb2.FileDescriptorProto()
        file.ParseFromString(blob)
        files.append(file)
    return files


# --- public API --------------------------------------------------------------

def list_services(address, *, version=None, timeout=DEFAULT_TIMEOUT):
    """Fully-qualified names of the services the server reports."""
    response = _ask(address, {"list_services": "*"}, version, timeout)
    return [s.name for s in response.list_services_response.service]


def file_by_filename(address, filename, *, version=None, timeout=DEFAULT_TIMEOUT):
    """The file and its transitive dependencies (list of FileDescriptorProto,
    requested file first)."""
    return _files(_ask(address, {"file_by_filename": filename}, version, timeout))


def file_containing_symbol(address, symbol, *, version=None, timeout=DEFAULT_TIMEOUT):
    """The file defining `symbol` (service, method, message, field, enum, ...)
    and its transitive dependencies (list of FileDescriptorProto, defining
    file first). Raises ReflectionError (code NOT_FOUND) for unknown symbols."""
    return _files(_ask(address, {"file_containing_symbol": symbol}, version, timeout))


def file_containing_extension(address, containing_type, number, *, version=None,
                              timeout=DEFAULT_TIMEOUT):
    """The file defining extension `number` of `containing_type`, plus deps."""
    fields = {"file_containing_extension": {"containing_type": containing_type,
                                            "extension_number": number}}
    return _files(_ask(address, fields, version, timeout))


def all_extension_numbers_of_type(address, full_name, *, version=None, timeout=DEFAULT_TIMEOUT):
    """Sorted extension field numbers of message type `full_name`."""
    response = _ask(address, {"all_extension_numbers_of_type": full_name}, version, timeout)
    return sorted(response.all_extension_numbers_response.extension_number)


def pool_from_files(files):
    """A new DescriptorPool holding `files` (FileDescriptorProtos, any order,
    duplicates by name ignored). Dependencies must be among `files`."""
    by_name = {}
    for file in files:
        by_name.setdefault(file.name, file)
    pool = descriptor_pool.DescriptorPool()
    added = set()

    def add(name, stack=()):
        if name in added:
            return
        if name in stack:
            raise ValueError(f"import cycle through {name}")
        if name not in by_name:
            raise ValueError(f"dependency {name} was not sent by the server")
        file = by_name[name]
        for dep in file.dependency:
            add(dep, stack + (name,))
        pool.AddSerializedFile(file.SerializeToString())
        added.add(name)

    for name in by_name:
        add(name)
    return pool


def pool_for_symbols(address, symbols, *, version=None, timeout=DEFAULT_TIMEOUT):
    """A new DescriptorPool with the files defining every symbol in `symbols`."""
    files = []
    for symbol in symbols:
        files.extend(file_containing_symbol(address, symbol, version=version, timeout=timeout))
    return pool_from_files(files)


def pool_for_symbol(address, symbol, *, version=None, timeout=DEFAULT_TIMEOUT):
    """A new DescriptorPool with the file defining `symbol` and its deps, e.g.
    to build request messages with message_class()."""
    return pool_for_symbols(address, [symbol], version=version, timeout=timeout)


def unary_call(channel, pool, service, method, request=None, *, timeout=DEFAULT_TIMEOUT,
               metadata=None):
    """Calls unary `service`/`method` with `request` (a dict in proto JSON
    form, or a message) and returns the response message."""
    method_desc = pool.FindServiceByName(service).methods_by_name[method]
    request_class = message_class(pool, method_desc.input_type.full_name)
    response_class = message_class(pool, method_desc.output_type.full_name)
    if request is None or isinstance(request, dict):
        request = json_format.ParseDict(request or {}, request_class(), descriptor_pool=pool)
    call = channel.unary_unary(f"/{service}/{method}",
                               request_serializer=request_class.SerializeToString,
                               response_deserializer=response_class.FromString)
    return call(request, timeout=timeout, metadata=metadata)


# --- comments ----------------------------------------------------------------

def _elements(file):
    """Yields (full_name, kind, source path, descriptor proto) of every element."""
    prefix = f"{file.package}." if file.package else ""

    def enum(e, scope, path):
        yield scope + e.name, "enum", path, e
        # Enum values are scoped next to their enum, not inside it.
        for i, value in enumerate(e.value):
            yield scope + value.name, "enum value", path + (2, i), value

    def message(m, scope, path):
        name = scope + m.name
        yield name, "message", path, m
        for i, field in enumerate(m.field):
            yield f"{name}.{field.name}", "field", path + (2, i), field
        for i, nested in enumerate(m.nested_type):
            yield from message(nested, name + ".", path + (3, i))
        for i, nested in enumerate(m.enum_type):
            yield from enum(nested, name + ".", path + (4, i))
        for i, ext in enumerate(m.extension):
            yield f"{name}.{ext.name}", "extension", path + (6, i), ext

    for i, m in enumerate(file.message_type):
        yield from message(m, prefix, (4, i))
    for i, e in enumerate(file.enum_type):
        yield from enum(e, prefix, (5, i))
    for i, s in enumerate(file.service):
        yield prefix + s.name, "service", (6, i), s
        for j, method in enumerate(s.method):
            yield f"{prefix}{s.name}.{method.name}", "method", (6, i, 2, j), method
    for i, ext in enumerate(file.extension):
        yield prefix + ext.name, "extension", (7, i), ext


def leading_comments(files, full_name):
    """Leading comments of element `full_name` (service, method, message,
    field, enum, enum value, extension) found in `files`, or None when the
    element is absent. "" when it has no comment or no source info was sent."""
    for file in files:
        for name, _, path, _ in _elements(file):
            if name == full_name:
                for location in file.source_code_info.location:
                    if tuple(location.path) == path:
                        return location.leading_comments
                return ""
    return None


def _describe(address, symbol):
    files = file_containing_symbol(address, symbol)
    elements = {name: (kind, path, proto) for name, kind, path, proto in _elements(files[0])}
    if symbol not in elements:
        print(f"{symbol} is defined in {files[0].name}")
        return
    kind, path, _ = elements[symbol]

    def comment(name, indent=""):
        text = leading_comments(files, name) or ""
        return "".join(f"{indent}//{line}\n" for line in text.rstrip("\n").split("\n") if text)

    article = "an" if kind[0] in "aeiou" else "a"
    print(f"{symbol} is {article} {kind} in {files[0].name}:")
    sys.stdout.write(comment(symbol))
    children = [(n, k) for n, (k, p, _) in elements.items()
                if len(p) == len(path) + 2 and p[:len(path)] == path]
    for name, child_kind in children:
        sys.stdout.write(comment(name, "  "))
        print(f"  {child_kind} {name.rsplit('.', 1)[-1]}")


def main(argv):
    if len(argv) < 3 or argv[2] not in ("list", "describe") or (
            argv[2] == "describe" and len(argv) != 4):
        print(__doc__.split("Command line")[1], file=sys.stderr)
        return 2
    address = argv[1]
    try:
        if argv[2] == "list":
            for name in list_services(address):
                print(name)
        else:
            _describe(address, argv[3])
    except ReflectionError as error:
        print(error, file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
