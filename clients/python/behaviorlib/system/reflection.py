"""gRPC server reflection (grpc.reflection.v1 and grpc.reflection.v1alpha) for a Python behavior
system, as services/server_kit/reflection serves it for the C++ ones: grpcurl, the console and
scripts learn the services, their methods and their messages from the running process, the
typed behavior services built at run time included, and call them without any .proto file.

Debian packages neither grpcio-reflection nor a Python module of reflection.proto, so the
protocol is implemented here on its messages. The .proto files are packaged (grpc-proto:
/usr/share/grpc-proto/grpc/reflection/v1{,alpha}/reflection.proto), but this package's build
compiles only the repository's protos, so the messages are described at run time with
descriptor_pb2 as files of the same names, packages, messages, fields and service: the wire
format is fixed by the reflection protocol (v1 and v1alpha are the same messages in two
packages), and a test compares this description with protoc's compilation of the packaged files.

What it answers, on one bidirectional stream, a response per request:
  - list_services: the names the process serves (given at construction), then
    grpc.reflection.v1alpha.ServerReflection and grpc.reflection.v1.ServerReflection;
  - file_by_filename and file_containing_symbol (a service, method, message, field, enum, enum
    value or extension by full name): the serialized FileDescriptorProto of the file, then
    those of its dependencies, transitively, breadth first, each once;
  - file_containing_extension and all_extension_numbers_of_type;
  - anything unknown: an error_response NOT_FOUND (or INVALID_ARGUMENT for an empty request).
Descriptors come from the default descriptor pool (every generated module imported, and the
files built at run time). A file also given as `documented` (a FileDescriptorProto with source
info: a descriptor set's, or a typed service file built with its comments) is served in that
form, so that `grpcurl describe` shows the comments, as the C++ servers serve their embedded
descriptor set.
"""

import collections
import threading

import grpc
from google.protobuf import descriptor_pb2, descriptor_pool

from . import _protocol

VERSIONS = ("v1alpha", "v1")


def file_descriptor_proto(version):
    """reflection.proto of `version` ("v1" or "v1alpha") as a FileDescriptorProto (without its
    comments and language options)."""
    package = f"grpc.reflection.{version}"
    file = descriptor_pb2.FileDescriptorProto(
        name=f"grpc/reflection/{version}/reflection.proto", package=package, syntax="proto3")

    def message(name, fields, oneof=None):
        out = file.message_type.add(name=name)
        if oneof:
            out.oneof_decl.add(name=oneof)
        for field_name, number, kind, options in fields:
            type_name = f".{package}.{options['type']}" if "type" in options else ""
            _protocol.add_field(out, field_name, number, kind, type_name,
                                repeated=options.get("repeated", False),
                                oneof_index=0 if options.get("oneof") else None)

    member = {"oneof": True}
    message("ServerReflectionRequest", [
        ("host", 1, "string", {}),
        ("file_by_filename", 3, "string", member),
        ("file_containing_symbol", 4, "string", member),
        ("file_containing_extension", 5, "message", {"oneof": True, "type": "ExtensionRequest"}),
        ("all_extension_numbers_of_type", 6, "string", member),
        ("list_services", 7, "string", member),
    ], oneof="message_request")
    message("ExtensionRequest", [
        ("containing_type", 1, "string", {}),
        ("extension_number", 2, "int32", {}),
    ])
    message("ServerReflectionResponse", [
        ("valid_host", 1, "string", {}),
        ("original_request", 2, "message", {"type": "ServerReflectionRequest"}),
        ("file_descriptor_response", 4, "message",
         {"oneof": True, "type": "FileDescriptorResponse"}),
        ("all_extension_numbers_response", 5, "message",
         {"oneof": True, "type": "ExtensionNumberResponse"}),
        ("list_services_response", 6, "message", {"oneof": True, "type": "ListServiceResponse"}),
        ("error_response", 7, "message", {"oneof": True, "type": "ErrorResponse"}),
    ], oneof="message_response")
    message("FileDescriptorResponse", [("file_descriptor_proto", 1, "bytes", {"repeated": True})])
    message("ExtensionNumberResponse", [
        ("base_type_name", 1, "string", {}),
        ("extension_number", 2, "int32", {"repeated": True}),
    ])
    message("ListServiceResponse", [
        ("service", 1, "message", {"repeated": True, "type": "ServiceResponse"}),
    ])
    message("ServiceResponse", [("name", 1, "string", {})])
    message("ErrorResponse", [
        ("error_code", 1, "int32", {}),
        ("error_message", 2, "string", {}),
    ])
    service = file.service.add(name="ServerReflection")
    service.method.add(name="ServerReflectionInfo",
                       input_type=f".{package}.ServerReflectionRequest",
                       output_type=f".{package}.ServerReflectionResponse",
                       client_streaming=True, server_streaming=True)
    return file


class DescriptorCatalog:
    """What reflection describes: the default pool's files, `documented` ones (file name ->
    FileDescriptorProto with source info) served in their documented form. Thread-safe."""

    def __init__(self, service_names, documented=None):
        self.service_names = list(dict.fromkeys(name for name in service_names if name))
        self._pool = descriptor_pool.Default()
        self._documented = dict(documented or {})
        self._lock = threading.Lock()
        self._serialized = {}

    def file_by_name(self, name):
        try:
            return self._pool.FindFileByName(name)
        except KeyError:
            return None

    def file_containing_symbol(self, symbol):
        if not symbol:
            return None
        try:
            return self._pool.FindFileContainingSymbol(symbol)
        except KeyError:
            return None

    def message(self, full_name):
        try:
            return self._pool.FindMessageTypeByName(full_name)
        except KeyError:
            return None

    def extension(self, extendee, number):
        try:
            return self._pool.FindExtensionByNumber(extendee, number)
        except KeyError:
            return None

    def extension_numbers(self, extendee):
        return sorted({x.number for x in self._pool.FindAllExtensions(extendee)})

    def serialized_with_dependencies(self, file):
        """The serialized file, then its transitive dependencies (breadth first, each once)."""
        out = []
        seen = {file.name}
        queue = collections.deque([file])
        while queue:
            current = queue.popleft()
            out.append(self._serialize(current))
            for dependency in current.dependencies:
                if dependency.name not in seen:
                    seen.add(dependency.name)
                    queue.append(dependency)
        return out

    def _serialize(self, file):
        with self._lock:
            data = self._serialized.get(file.name)
            if data is None:
                documented = self._documented.get(file.name)
                if documented is not None:
                    data = documented.SerializeToString()
                else:
                    proto = descriptor_pb2.FileDescriptorProto()
                    file.CopyToProto(proto)
                    data = proto.SerializeToString()
                self._serialized[file.name] = data
            return data


class ReflectionService:
    """Both reflection services (v1alpha and v1) over one DescriptorCatalog. `service_names`
    are what list_services reports before the reflection services themselves; `documented`
    as for DescriptorCatalog; `stream_slots` (a _protocol.StreamSlots) bounds the reflection
    streams with the process's other streams."""

    def __init__(self, service_names, stream_slots, documented=None):
        self._versions = {}
        for version in VERSIONS:
            file = _protocol.add_file(file_descriptor_proto(version))
            response = _protocol.message_class(
                file.message_types_by_name["ServerReflectionResponse"])
            self._versions[version] = (file.services_by_name["ServerReflection"], response)
        self._catalog = DescriptorCatalog(
            list(service_names) + [f"grpc.reflection.{version}.ServerReflection"
                                   for version in VERSIONS], documented)
        self._slots = stream_slots

    def handlers(self):
        """The grpc.GenericRpcHandlers to add to the server (v1alpha and v1)."""
        return [_protocol.serve_service(service, {"ServerReflectionInfo": self._info(response)})
                for service, response in self._versions.values()]

    def _info(self, response_class):
        def info(requests, context):
            if not self._slots.take():
                context.abort(grpc.StatusCode.RESOURCE_EXHAUSTED,
                              f"too many streams open on this behavior system (at most "
                              f"{self._slots.limit}); close one and ask again")
            try:
                for request in requests:
                    yield self.answer(request, response_class())
            finally:
                self._slots.give_back()
        return info

    def answer(self, request, response):
        """Fills `response` (a ServerReflectionResponse of the request's version) for
        `request`; returns it."""
        catalog = self._catalog
        response.valid_host = request.host
        response.original_request.CopyFrom(request)
        kind = request.WhichOneof("message_request")

        def error(code, message):
            response.error_response.error_code = code.value[0]
            response.error_response.error_message = message
            return response

        def files(file):
            response.file_descriptor_response.file_descriptor_proto.extend(
                catalog.serialized_with_dependencies(file))
            return response

        if kind == "file_by_filename":
            file = catalog.file_by_name(request.file_by_filename)
            if file is None:
                return error(grpc.StatusCode.NOT_FOUND,
                             f"file not found: {request.file_by_filename}")
            return files(file)
        if kind == "file_containing_symbol":
            file = catalog.file_containing_symbol(request.file_containing_symbol)
            if file is None:
                return error(grpc.StatusCode.NOT_FOUND,
                             f"symbol not found: {request.file_containing_symbol}")
            return files(file)
        if kind == "file_containing_extension":
            wanted = request.file_containing_extension
            extendee = catalog.message(wanted.containing_type)
            if extendee is None:
                return error(grpc.StatusCode.NOT_FOUND,
                             f"type not found: {wanted.containing_type}")
            field = catalog.extension(extendee, wanted.extension_number)
            if field is None:
                return error(grpc.StatusCode.NOT_FOUND,
                             f"extension not found: {wanted.containing_type} field "
                             f"{wanted.extension_number}")
            return files(field.file)
        if kind == "all_extension_numbers_of_type":
            extendee = catalog.message(request.all_extension_numbers_of_type)
            if extendee is None:
                return error(grpc.StatusCode.NOT_FOUND,
                             f"type not found: {request.all_extension_numbers_of_type}")
            out = response.all_extension_numbers_response
            out.base_type_name = extendee.full_name
            out.extension_number.extend(catalog.extension_numbers(extendee))
            return response
        if kind == "list_services":
            for name in catalog.service_names:
                response.list_services_response.service.add(name=name)
            return response
        return error(grpc.StatusCode.INVALID_ARGUMENT,
                     "no or unknown message_request in the request")
