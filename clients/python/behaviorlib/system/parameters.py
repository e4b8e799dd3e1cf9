"""Behavior parameters: a port of services/behaviorlib/core/parameters.{h,cc}, with the error
details of services/errors/status_details.{h,cc} and the comments of documentation.cc.

A behavior's parameters are a protobuf message whose fields carry the (behaviorlib.v1.param)
options of proto/behaviorlib/v1/options.proto: ranges, defaults, `required` and descriptions.
Everything here is derived from the message's descriptor, so that the rules are written once,
in the .proto file, and the C++ and the Python systems refuse the same requests with the same
errors: the same gRPC code, the same message text, the same ErrorInfo reason and the same
BadRequest field violation.

    message = from_struct(request.parameters, WaitParameters)   # shape, types, names
    apply_defaults_and_validate(message)                         # defaults, required, ranges

Both raise StatusError. As in the C++ system, from_struct's field violations name the parameter
("duration_s"), while the engine prefixes those of validation with "parameters."
(engine.parameter_error), because that is where the C++ service and engine report them.

Descriptions: a rule without `description` takes the field's leading comment from its .proto
file. Generated Python modules carry no comments, so they come from a descriptor set built with
`protoc --include_imports --include_source_info`: load_descriptor_set() reads one, and the
package's own behaviorlib/v1/descriptors.binpb is read when it exists. Without comments a
refusal of a missing required parameter ends after its name.
"""

import base64
import binascii
import decimal
import math
import os
import re
import struct

import grpc
from google.protobuf import descriptor_pb2, json_format, struct_pb2
from google.protobuf.descriptor import FieldDescriptor as FD
from google.rpc import error_details_pb2, status_pb2

import behaviorlib.v1
from behaviorlib.v1 import behavior_pb2, errors_pb2, options_pb2

# ErrorInfo.domain of every behaviorlib error (status_details.h kDomain).
DOMAIN = "behaviorlib.v1"
# The trailing metadata key that carries a serialized google.rpc.Status.
STATUS_DETAILS_KEY = "grpc-status-details-bin"
_TYPE_URL_PREFIX = "type.googleapis.com/"

# describe(): past this depth a schema is unreadable anyway.
_MAX_DESCRIBE_DEPTH = 8
# Long strings are cut in messages so that one bad parameter cannot blow up a log line.
_MAX_QUOTED_LENGTH = 60
_FLOAT_MAX = 3.4028234663852886e38


def _reason_name(reason):
    """An ErrorReason given as a value or a name, as its name."""
    return reason if isinstance(reason, str) else errors_pb2.ErrorReason.Name(reason)


class StatusError(Exception):
    """A refused call: a gRPC status code, its message, and the machine-readable details that
    the C++ code attaches (status_details.h): the ErrorInfo `reason` (an ErrorReason name, ""
    for none) with its `metadata`, and the BadRequest `field_violations` as (field,
    description) pairs.

    Behavior code raises it to refuse on purpose (on_activate, on_modify, on_configure) with a
    code of its choice; the library raises it for every refusal. The with_* methods return a
    new error, as the C++ helpers return a new absl::Status.
    """

    def __init__(self, code, message, *, reason="", metadata=None, field_violations=()):
        super().__init__(f"{code.name}: {message}")
        self.code = code
        self.message = message
        self.reason = _reason_name(reason) if reason else ""
        self.metadata = dict(metadata or {})
        self.field_violations = list(field_violations)

    def _copy(self, **changes):
        values = {"code": self.code, "message": self.message, "reason": self.reason,
                  "metadata": self.metadata, "field_violations": self.field_violations}
        values.update(changes)
        code = values.pop("code")
        message = values.pop("message")
        return StatusError(code, message, **values)

    def _add_metadata(self, metadata):
        merged = dict(self.metadata)
        for key, value in (metadata or {}).items():
            merged.setdefault(key, value)  # an existing key keeps its value
        return merged

    def with_reason(self, reason, metadata=None):
        """This error with its reason set to `reason` and `metadata` added (errors::withReason)."""
        return self._copy(reason=_reason_name(reason), metadata=self._add_metadata(metadata))

    def with_default_reason(self, reason, metadata=None):
        """Like with_reason, but keeps an earlier reason (errors::withDefaultReason)."""
        keep = self.reason and self.reason != "ERROR_REASON_UNSPECIFIED"
        return self._copy(reason=self.reason if keep else _reason_name(reason),
                          metadata=self._add_metadata(metadata))

    def with_field_violation(self, field, description):
        """This error with one more BadRequest field violation."""
        return self._copy(field_violations=self.field_violations + [(field, description)])

    def prefix_field_violations(self, prefix, description_prefix=""):
        """Every violation's field path prefixed by `prefix` ("parameters.") and its description
        by `description_prefix` (errors::prefixFieldViolations)."""
        violations = []
        for field, description in self.field_violations:
            path = prefix + field
            if not field and path.endswith("."):
                path = path[:-1]
            violations.append((path, description_prefix + description))
        return self._copy(field_violations=violations)

    def rewrap(self, message, code=None):
        """A new message (and code) that keeps the details (errors::rewrap)."""
        return self._copy(message=message, code=code or self.code)

    def error_info(self):
        """The google.rpc.ErrorInfo as a server sends it (errors::toGrpc): an error without a
        reason gets INVALID_REQUEST if INVALID_ARGUMENT, else ERROR_REASON_UNSPECIFIED."""
        reason = self.reason
        if not reason or reason == "ERROR_REASON_UNSPECIFIED":
            reason = ("INVALID_REQUEST" if self.code == grpc.StatusCode.INVALID_ARGUMENT
                      else "ERROR_REASON_UNSPECIFIED")
        return error_details_pb2.ErrorInfo(reason=reason, domain=DOMAIN, metadata=self.metadata)

    def bad_request(self):
        """The google.rpc.BadRequest, or None without field violations."""
        if not self.field_violations:
            return None
        bad = error_details_pb2.BadRequest()
        for field, description in self.field_violations:
            bad.field_violations.add(field=field, description=description)
        return bad

    def to_rpc_status(self):
        """The google.rpc.Status of the grpc-status-details-bin trailer: the ErrorInfo first,
        then the BadRequest, as errors::toGrpc writes them."""
        status = status_pb2.Status(code=self.code.value[0], message=self.message)
        status.details.add().Pack(self.error_info())
        bad = self.bad_request()
        if bad is not None:
            status.details.add().Pack(bad)
        return status

    def trailing_metadata(self):
        """The trailing metadata that carries the details, for a grpcio servicer:
        context.set_trailing_metadata(e.trailing_metadata()); context.abort(e.code, e.message)."""
        return ((STATUS_DETAILS_KEY, self.to_rpc_status().SerializeToString()),)


def _field_error(path, message, reason=errors_pb2.PARAMETER_INVALID):
    """INVALID_ARGUMENT with a reason and the parameter's path as a field violation."""
    return StatusError(grpc.StatusCode.INVALID_ARGUMENT, message, reason=reason,
                       field_violations=[(path, message)])


def _param_error(path, what, reason=errors_pb2.PARAMETER_INVALID):
    return _field_error(path, f"parameter '{path}': {what}", reason)


# ---- Comments (documentation.cc) -------------------------------------------------------------

_comments = {}
_default_set_loaded = False
_DEFAULT_DESCRIPTOR_SET = "descriptors.binpb"


def _one_paragraph(comment):
    """The comment's lines trimmed and joined by single spaces, blank lines dropped."""
    return " ".join(line.strip(" \t") for line in comment.split("\n") if line.strip(" \t"))


def _element_names(file):
    """Source-info path -> full name for the elements of one FileDescriptorProto."""
    prefix = f"{file.package}." if file.package else ""
    names = {}

    def enum(path, e, scope):
        names[path] = scope + e.name
        for i, value in enumerate(e.value):
            names[path + (2, i)] = scope + value.name  # enum values are the enum's siblings

    def message(path, m, scope):
        full = scope + m.name
        names[path] = full
        for i, f in enumerate(m.field):
            names[path + (2, i)] = f"{full}.{f.name}"
        for i, nested in enumerate(m.nested_type):
            message(path + (3, i), nested, full + ".")
        for i, e in enumerate(m.enum_type):
            enum(path + (4, i), e, full + ".")
        for i, x in enumerate(m.extension):
            names[path + (6, i)] = f"{full}.{x.name}"

    for i, m in enumerate(file.message_type):
        message((4, i), m, prefix)
    for i, e in enumerate(file.enum_type):
        enum((5, i), e, prefix)
    for i, service in enumerate(file.service):
        names[(6, i)] = prefix + service.name
        for j, method in enumerate(service.method):
            names[(6, i, 2, j)] = f"{prefix}{service.name}.{method.name}"
    for i, x in enumerate(file.extension):
        names[(7, i)] = prefix + x.name
    return names


def load_descriptor_set(data):
    """Reads the leading comments of a serialized FileDescriptorSet made with
    --include_source_info (its files' comments replace those already known)."""
    files = descriptor_pb2.FileDescriptorSet.FromString(data)
    for file in files.file:
        names = _element_names(file)
        for location in file.source_code_info.location:
            name = names.get(tuple(location.path))
            if name is not None and location.leading_comments:
                _comments[name] = _one_paragraph(location.leading_comments)


def leading_comment(full_name):
    """The leading comment of a message, field, enum, service or method by full name
    ("behaviorlib.v1.WaitParameters.duration_s"), in one paragraph; "" when unknown."""
    global _default_set_loaded
    if not _default_set_loaded:
        _default_set_loaded = True
        path = os.path.join(os.path.dirname(behaviorlib.v1.__file__), _DEFAULT_DESCRIPTOR_SET)
        if os.path.exists(path):
            with open(path, "rb") as f:
                load_descriptor_set(f.read())
    return _comments.get(full_name, "")


# ---- Text of numbers and values ----------------------------------------------------------------

def _shortest_digits(v):
    """(negative, digits, exponent) of the shortest decimal that reads back as `v`:
    v = digits * 10**exponent, without trailing zeros."""
    sign, digits, exponent = decimal.Decimal(repr(v)).as_tuple()
    text = "".join(map(str, digits)).lstrip("0")
    if not text:
        return bool(sign), "0", 0
    stripped = text.rstrip("0")
    return bool(sign), stripped, exponent + len(text) - len(stripped)


def _fixed(digits, exponent):
    if exponent >= 0:
        return digits + "0" * exponent
    point = len(digits) + exponent
    if point > 0:
        return f"{digits[:point]}.{digits[point:]}"
    return "0." + "0" * -point + digits


def _scientific(digits, exponent):
    e = exponent + len(digits) - 1
    mantissa = digits[0] + (f".{digits[1:]}" if len(digits) > 1 else "")
    return f"{mantissa}e{'-' if e < 0 else '+'}{abs(e):02d}"


def number_text(value):
    """A number as the parameter errors print it: the shortest text that reads back to the same
    double ("0.2", "30", "1e-06"), as C++ std::to_chars writes it; integral values below 1e21
    print like integers ("3000000000")."""
    if math.isnan(value):
        return "NaN"
    if math.isinf(value):
        return "Infinity" if value > 0 else "-Infinity"
    negative, digits, exponent = _shortest_digits(float(value))
    sign = "-" if negative else ""
    fixed = _fixed(digits, exponent)
    if math.trunc(value) == value and abs(value) < 1e21:
        return sign + fixed
    scientific = _scientific(digits, exponent)
    return sign + (scientific if len(scientific) < len(fixed) else fixed)


def _float_to_double(v):
    """A float32 value through its shortest decimal text: 0.1f becomes 0.1, what the caller
    wrote, not 0.10000000149011612."""
    if not math.isfinite(v):
        return v
    for precision in range(1, 10):
        candidate = float(f"{v:.{precision}g}")
        if struct.unpack("f", struct.pack("f", candidate))[0] == v:
            return candidate
    return v


def _format_float(v):
    return number_text(_float_to_double(v))


def range_text(rule_range):
    """A range as the parameter errors print it: "[0.2, 30]", "(-inf, 3]"."""
    low = f"[{number_text(rule_range.min)}" if rule_range.HasField("min") else "(-inf"
    high = f"{number_text(rule_range.max)}]" if rule_range.HasField("max") else "+inf)"
    return f"{low}, {high}"


def _quoted(text):
    """A string as C++ absl::CHexEscape quotes it, cut after 60 bytes."""
    data = text.encode("utf-8") if isinstance(text, str) else text
    cut = len(data) > _MAX_QUOTED_LENGTH
    out = []
    last_hex = False
    for byte in data[:_MAX_QUOTED_LENGTH]:
        is_hex = False
        char = chr(byte)
        if char in "\n\r\t\"'\\":
            out.append({"\n": "\\n", "\r": "\\r", "\t": "\\t", '"': '\\"', "'": "\\'",
                        "\\": "\\\\"}[char])
        elif not 0x20 <= byte <= 0x7E or (last_hex and char in "0123456789abcdefABCDEF"):
            out.append(f"\\x{byte:02x}")
            is_hex = True
        else:
            out.append(char)
        last_hex = is_hex
    return '"' + "".join(out) + ('"...' if cut else '"')


def _describe_value(v):
    """What the caller actually sent, for "got ..." messages: 'a string ("five")'."""
    kind = v.WhichOneof("kind")
    if kind == "null_value":
        return "null"
    if kind == "number_value":
        return f"a number ({number_text(v.number_value)})"
    if kind == "string_value":
        return f"a string ({_quoted(v.string_value)})"
    if kind == "bool_value":
        return f"a boolean ({'true' if v.bool_value else 'false'})"
    if kind == "struct_value":
        return "an object"
    if kind == "list_value":
        return "a list"
    return "no value"


def _child_path(parent, name):
    return f"{parent}.{name}" if parent else name


def _element_path(parent, index):
    return f"{parent}[{index}]"


def _map_key_path(parent, key_field, key):
    """Map keys as JSON writes them: strings quoted, numbers and booleans bare."""
    if key_field.cpp_type == FD.CPPTYPE_STRING:
        return f"{parent}[{_quoted(key)}]"
    return f"{parent}[{key}]"


# ---- Descriptors -------------------------------------------------------------------------------

_TYPE_NAMES = {
    FD.TYPE_DOUBLE: "double", FD.TYPE_FLOAT: "float", FD.TYPE_INT64: "int64",
    FD.TYPE_UINT64: "uint64", FD.TYPE_INT32: "int32", FD.TYPE_FIXED64: "fixed64",
    FD.TYPE_FIXED32: "fixed32", FD.TYPE_BOOL: "bool", FD.TYPE_STRING: "string",
    FD.TYPE_GROUP: "group", FD.TYPE_MESSAGE: "message", FD.TYPE_BYTES: "bytes",
    FD.TYPE_UINT32: "uint32", FD.TYPE_ENUM: "enum", FD.TYPE_SFIXED32: "sfixed32",
    FD.TYPE_SFIXED64: "sfixed64", FD.TYPE_SINT32: "sint32", FD.TYPE_SINT64: "sint64",
}
_INTEGERS = (FD.CPPTYPE_INT32, FD.CPPTYPE_INT64, FD.CPPTYPE_UINT32, FD.CPPTYPE_UINT64)
_FLOATING = (FD.CPPTYPE_DOUBLE, FD.CPPTYPE_FLOAT)
_proto3_optional = {}


def _type_name(field):
    return _TYPE_NAMES[field.type]


def _rule(field):
    return field.GetOptions().Extensions[options_pb2.param]


def _description(field, rule):
    """The rule's description, else the field's comment in its .proto file."""
    return rule.description or leading_comment(field.full_name)


def _is_map(field):
    return (field.type == FD.TYPE_MESSAGE and field.label == FD.LABEL_REPEATED
            and field.message_type.GetOptions().map_entry)


def _optional_fields(file):
    """Full names of the proto3 `optional` fields of a file (their oneof is synthetic)."""
    names = _proto3_optional.get(file.name)
    if names is None:
        proto = descriptor_pb2.FileDescriptorProto.FromString(file.serialized_pb)
        names = set()

        def walk(messages, scope):
            for m in messages:
                full = scope + m.name
                names.update(f"{full}.{f.name}" for f in m.field if f.proto3_optional)
                walk(m.nested_type, full + ".")

        walk(proto.message_type, f"{proto.package}." if proto.package else "")
        _proto3_optional[file.name] = names
    return names


def _real_oneof(field):
    """The field's oneof, unless it is the synthetic one of a proto3 `optional` field."""
    oneof = field.containing_oneof
    if oneof is None or field.full_name in _optional_fields(field.file):
        return None
    return oneof


def _enum_names(enum_type):
    return ", ".join(v.name for v in enum_type.values)


def _expected_kind(field):
    """What a field (or one element of a repeated field) accepts, for "expected ..."."""
    cpp = field.cpp_type
    if cpp in _INTEGERS:
        return "an integer"
    if cpp in _FLOATING:
        return "a number"
    if cpp == FD.CPPTYPE_BOOL:
        return "a boolean"
    if cpp == FD.CPPTYPE_STRING:
        return "a base64 string" if field.type == FD.TYPE_BYTES else "a string"
    if cpp == FD.CPPTYPE_ENUM:
        return f"one of {_enum_names(field.enum_type)}"
    return "an object"


def _expected_error(path, expected, got):
    return _param_error(path, f"expected {expected}, got {_describe_value(got)}")


# ---- from_struct -------------------------------------------------------------------------------

_INTEGER_BOUNDS = {
    FD.CPPTYPE_INT32: (-2**31, 2**31 - 1, "[-2147483648, 2147483647]"),
    FD.CPPTYPE_UINT32: (0, 2**32 - 1, "[0, 4294967295]"),
    # 2^63 and 2^64 are exact doubles; the largest doubles below them are in range.
    FD.CPPTYPE_INT64: (-2.0**63, math.nextafter(2.0**63, 0.0),
                       "[-9223372036854775808, 9223372036854775807]"),
    FD.CPPTYPE_UINT64: (0, math.nextafter(2.0**64, 0.0), "[0, 18446744073709551615]"),
}


def _check_integer(d, field, path):
    """A JSON number that is an integer fitting the field's type, as an int."""
    if not math.isfinite(d) or math.trunc(d) != d:
        raise _param_error(path, f"{number_text(d)} is not an integer")
    unsigned = field.cpp_type in (FD.CPPTYPE_UINT32, FD.CPPTYPE_UINT64)
    if unsigned and d < 0:
        raise _param_error(path, f"{number_text(d)} is negative, but the parameter is "
                                 f"{_type_name(field)} (unsigned)")
    low, high, bounds = _INTEGER_BOUNDS[field.cpp_type]
    if d < low or d > high:
        raise _param_error(
            path, f"{number_text(d)} is out of range for {_type_name(field)} {bounds}",
            errors_pb2.PARAMETER_OUT_OF_RANGE)
    return int(d)


_BASE64_STANDARD = set("ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/")
_BASE64_WEB_SAFE = set("ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789-_")


def _base64_decode(text, alphabet):
    """Base64 as absl::Base64Unescape reads it (whitespace skipped, padding '=' or '.', none
    accepted); None when invalid."""
    text = "".join(c for c in text if c not in " \t\n\v\f\r")
    pad_at = min([i for i in (text.find("="), text.find(".")) if i >= 0], default=len(text))
    data, padding = text[:pad_at], text[pad_at:]
    if any(c not in alphabet for c in data) or any(c not in "=." for c in padding):
        return None
    if len(data) % 4 == 1:
        return None
    expected = (4 - len(data) % 4) % 4
    if padding and len(padding) != expected:
        return None
    if alphabet is _BASE64_WEB_SAFE:
        data = data.replace("-", "+").replace("_", "/")
    try:
        return base64.b64decode(data + "=" * expected, validate=True)
    except binascii.Error:
        return None


class _Slot:
    """Where one converted value goes: the singular field, a new element of a repeated
    field, or the value of a map entry (`set` a scalar, `message()` the message to fill)."""

    def __init__(self, set_value, message):
        self.set = set_value
        self.message = message


def _singular_slot(message, field):
    def mutable():
        sub = getattr(message, field.name)
        sub.SetInParent()
        return sub

    return _Slot(lambda value: setattr(message, field.name, value), mutable)


def _parse_single(v, field, slot, path):
    """Converts one JSON value (a single value or a list element) into the slot's type."""
    kind = v.WhichOneof("kind")
    cpp = field.cpp_type
    if cpp in _INTEGERS:
        if kind != "number_value":
            raise _expected_error(path, _expected_kind(field), v)
        slot.set(_check_integer(v.number_value, field, path))
    elif cpp in _FLOATING:
        if kind != "number_value":
            raise _expected_error(path, _expected_kind(field), v)
        d = v.number_value
        # JSON cannot carry NaN or infinities; a Struct built in code can.
        if not math.isfinite(d):
            raise _param_error(path, f"{number_text(d)} is not a finite number")
        if cpp == FD.CPPTYPE_FLOAT and abs(d) > _FLOAT_MAX:
            raise _param_error(path, f"{number_text(d)} is out of range for float")
        slot.set(d)
    elif cpp == FD.CPPTYPE_BOOL:
        if kind != "bool_value":
            raise _expected_error(path, _expected_kind(field), v)
        slot.set(v.bool_value)
    elif cpp == FD.CPPTYPE_STRING:
        if kind != "string_value":
            raise _expected_error(path, _expected_kind(field), v)
        if field.type != FD.TYPE_BYTES:
            slot.set(v.string_value)
            return
        # Proto3 JSON writes standard base64 but accepts the URL-safe alphabet too.
        decoded = _base64_decode(v.string_value, _BASE64_STANDARD)
        if decoded is None:
            decoded = _base64_decode(v.string_value, _BASE64_WEB_SAFE)
        if decoded is None:
            raise _param_error(path, f"{_quoted(v.string_value)} is not valid base64")
        slot.set(decoded)
    elif cpp == FD.CPPTYPE_ENUM:
        _parse_enum(v, kind, field, slot, path)
    else:
        if kind != "struct_value":
            raise _expected_error(path, _expected_kind(field), v)
        _parse_message(v.struct_value, slot.message(), path)


def _parse_enum(v, kind, field, slot, path):
    enum_type = field.enum_type
    if kind == "string_value":
        value = enum_type.values_by_name.get(v.string_value)
        if value is None:
            raise _param_error(path, f"unknown value {_quoted(v.string_value)}; accepted: "
                                     f"{_enum_names(enum_type)}")
        slot.set(value.number)
    elif kind == "number_value":
        d = v.number_value
        if not math.isfinite(d) or math.trunc(d) != d:
            raise _param_error(path, f"{number_text(d)} is not an integer")
        value = enum_type.values_by_number.get(int(d)) if -2**31 <= d <= 2**31 - 1 else None
        if value is None:
            # Numbers are the less common spelling, so show the mapping.
            accepted = ", ".join(f"{e.name} ({e.number})" for e in enum_type.values)
            raise _param_error(path, f"unknown value {number_text(d)}; accepted: {accepted}")
        slot.set(value.number)
    else:
        raise _expected_error(path, _expected_kind(field), v)


_INTEGER_KEY = re.compile(r"[ \t\n\v\f\r]*([+-]?)([0-9]+)[ \t\n\v\f\r]*")


def _parse_map_key(key, key_field, path):
    """A JSON object key (always a string) as the map's key type (absl::SimpleAtoi rules)."""
    cpp = key_field.cpp_type
    if cpp == FD.CPPTYPE_STRING:
        return key
    if cpp in _INTEGERS:
        match = _INTEGER_KEY.fullmatch(key)
        if match and not (match.group(1) == "-" and cpp in (FD.CPPTYPE_UINT32,
                                                             FD.CPPTYPE_UINT64)):
            value = int(match.group(1) + match.group(2))
            low, high, _ = _INTEGER_BOUNDS[cpp]
            if low <= value <= int(high):
                return value
    elif cpp == FD.CPPTYPE_BOOL and key in ("true", "false"):
        return key == "true"
    raise _param_error(path, f"key {_quoted(key)} is not a valid {_type_name(key_field)}")


def _parse_field(v, field, out, path):
    """Converts the JSON value of one field (a list for repeated fields, an object for maps)."""
    kind = v.WhichOneof("kind")
    if kind == "null_value":
        raise _param_error(path, "null is not accepted; omit the parameter to leave it unset")
    if _is_map(field):
        if kind != "struct_value":
            raise _expected_error(path, "an object", v)
        key_field = field.message_type.fields_by_name["key"]
        value_field = field.message_type.fields_by_name["value"]
        container = getattr(out, field.name)
        # Struct fields are a hash map; sorting makes the first error independent of hashing.
        for key in sorted(v.struct_value.fields):
            item_path = _map_key_path(path, key_field, key)
            map_key = _parse_map_key(key, key_field, path)
            slot = _Slot(lambda value, k=map_key: container.__setitem__(k, value),
                         lambda k=map_key: container[k])
            _parse_single(v.struct_value.fields[key], value_field, slot, item_path)
        return
    if field.label == FD.LABEL_REPEATED:
        if kind != "list_value":
            raise _expected_error(path, "a list", v)
        container = getattr(out, field.name)
        slot = _Slot(container.append, container.add if field.cpp_type == FD.CPPTYPE_MESSAGE
                     else None)
        for i, element in enumerate(v.list_value.values):
            _parse_single(element, field, slot, _element_path(path, i))
        return
    _parse_single(v, field, _singular_slot(out, field), path)


def _find_field(descriptor, key):
    """Field names as written in the .proto are canonical; JSON names ("durationS") are
    accepted because proto3 JSON tools produce them."""
    field = descriptor.fields_by_name.get(key)
    if field is not None:
        return field
    for field in descriptor.fields:
        if key in (field.json_name, field.camelcase_name):
            return field
    return None


def _parse_message(struct_value, out, path):
    descriptor = out.DESCRIPTOR
    given = []  # (field, the key it was given under)
    for key in sorted(struct_value.fields):
        field = _find_field(descriptor, key)
        child = _child_path(path, key)
        if field is None:
            known = ", ".join(f.name for f in descriptor.fields) or "(none)"
            raise _field_error(child, f"unknown parameter '{child}' for {descriptor.full_name}; "
                                      f"known parameters: {known}")
        for other, other_key in given:
            if other is field:
                raise _field_error(
                    _child_path(path, field.name),
                    f"parameter '{_child_path(path, field.name)}' is given twice, as "
                    f"'{other_key}' and as '{key}'")
            oneof = _real_oneof(field)
            if oneof is not None and _real_oneof(other) is oneof:
                raise _field_error(
                    _child_path(path, field.name),
                    f"parameters '{_child_path(path, other.name)}' and "
                    f"'{_child_path(path, field.name)}' are alternatives (oneof {oneof.name}); "
                    f"set only one")
        given.append((field, key))
        _parse_field(struct_value.fields[key], field, out, _child_path(path, field.name))


def _as_struct(values):
    """A google.protobuf.Struct, or a dict made into one."""
    if isinstance(values, struct_pb2.Struct):
        return values
    converted = struct_pb2.Struct()
    try:
        converted.update(values)
    except (TypeError, ValueError) as error:
        raise StatusError(grpc.StatusCode.INVALID_ARGUMENT,
                          f"parameters must be JSON-like values: {error}",
                          reason=errors_pb2.INVALID_REQUEST) from error
    return converted


def from_struct(values, message_class):
    """A new `message_class` filled from a Struct (or a dict of JSON-like values) whose keys are
    its field names (params::fromStruct). Raises StatusError INVALID_ARGUMENT naming the
    parameter by its path ("path.poses[2].position_m.x") for an unknown field, a wrong JSON
    type, a non-integral or out-of-type number for an integer field, an unknown enum value or a
    null. Keys may also be the JSON (lowerCamel) names; enums are accepted by name or number,
    bytes as base64, map fields as objects. Defaults and ranges are apply_defaults_and_validate's
    work."""
    message = message_class()
    _parse_message(_as_struct(values), message, "")
    return message


# ---- to_struct ---------------------------------------------------------------------------------

def _single_to_value(value, field):
    out = struct_pb2.Value()
    cpp = field.cpp_type
    if cpp in _INTEGERS or cpp == FD.CPPTYPE_DOUBLE:
        out.number_value = float(value)
    elif cpp == FD.CPPTYPE_FLOAT:
        out.number_value = _float_to_double(value)
    elif cpp == FD.CPPTYPE_BOOL:
        out.bool_value = value
    elif cpp == FD.CPPTYPE_STRING:
        out.string_value = (base64.b64encode(value).decode("ascii")
                            if field.type == FD.TYPE_BYTES else value)
    elif cpp == FD.CPPTYPE_ENUM:
        # An open enum can hold a number without a name; keep it rather than losing it.
        named = field.enum_type.values_by_number.get(value)
        if named is not None:
            out.string_value = named.name
        else:
            out.number_value = value
    else:
        out.struct_value.CopyFrom(to_struct(value))
    return out


def _map_key_text(key, key_field):
    if key_field.cpp_type == FD.CPPTYPE_BOOL:
        return "true" if key else "false"
    return str(key)


def to_struct(message):
    """The message as a Struct (params::toStruct): every field that is set (explicit presence)
    or not default (implicit presence); enums as names, 64-bit integers as numbers, bytes as
    base64, nested messages as objects."""
    out = struct_pb2.Struct()
    for field, value in message.ListFields():
        target = out.fields[field.name]
        if _is_map(field):
            key_field = field.message_type.fields_by_name["key"]
            value_field = field.message_type.fields_by_name["value"]
            target.struct_value.SetInParent()
            for key in value:
                target.struct_value.fields[_map_key_text(key, key_field)].CopyFrom(
                    _single_to_value(value[key], value_field))
        elif field.label == FD.LABEL_REPEATED:
            target.list_value.SetInParent()
            for element in value:
                target.list_value.values.add().CopyFrom(_single_to_value(element, field))
        else:
            target.CopyFrom(_single_to_value(value, field))
    return out


# ---- apply_defaults_and_validate ---------------------------------------------------------------

def _is_set(message, field):
    """Whether the caller (or a default) gave the field a value. For implicit-presence scalars
    this is "not zero" (a negative zero counts as set, as in C++), the best that can be known."""
    if field.label == FD.LABEL_REPEATED:
        return len(getattr(message, field.name)) > 0
    if field.has_presence:
        return message.HasField(field.name)
    value = getattr(message, field.name)
    if field.cpp_type in _FLOATING:
        return value != 0 or math.copysign(1.0, value) < 0
    return bool(value)


def _apply_default(rule, field, message, path):
    """A default_json that does not fit its field is a bug in the behavior's .proto, not in the
    request: INTERNAL, naming the schema."""
    try:
        value = json_format.Parse(rule.default_json, struct_pb2.Value())
    except json_format.ParseError as error:
        raise StatusError(grpc.StatusCode.INTERNAL,
                          f"schema error in {field.full_name}: default_json "
                          f"{_quoted(rule.default_json)} is not valid JSON: {error}") from error
    try:
        _parse_field(value, field, message, path)
    except StatusError as error:
        message.ClearField(field.name)
        raise StatusError(grpc.StatusCode.INTERNAL,
                          f"schema error in {field.full_name}: default_json "
                          f"{_quoted(rule.default_json)} does not fit the field: "
                          f"{error.message}") from error


def _numeric(value, field):
    """(value, exact text, floating) of a numeric field's value; None for other types."""
    cpp = field.cpp_type
    if cpp in _INTEGERS:
        return float(value), str(value), False
    if cpp == FD.CPPTYPE_DOUBLE:
        return value, number_text(value), True
    if cpp == FD.CPPTYPE_FLOAT:
        return value, _format_float(value), True
    return None


def _check_numeric(value, field, rule, path):
    numeric = _numeric(value, field)
    if numeric is None:
        return
    number, text, floating = numeric
    if floating and not math.isfinite(number):
        raise _field_error(path, f"parameter '{path}' = {text} is not a finite number")
    if not rule.HasField("range"):
        return
    limits = rule.range
    if ((limits.HasField("min") and number < limits.min)
            or (limits.HasField("max") and number > limits.max)):
        raise _field_error(path, f"parameter '{path}' = {text} is out of range "
                                 f"{range_text(limits)}", errors_pb2.PARAMETER_OUT_OF_RANGE)


def _validate_field(message, field, path):
    rule = _rule(field)
    # A default on a oneof member must not displace the member the caller chose.
    oneof = _real_oneof(field)
    oneof_taken = oneof is not None and message.WhichOneof(oneof.name) is not None
    if rule.default_json and not _is_set(message, field) and not oneof_taken:
        _apply_default(rule, field, message, path)
    if rule.required and not _is_set(message, field):
        description = _description(field, rule)
        raise _field_error(path, f"parameter '{path}' is required" +
                           (f": {description}" if description else ""))
    if _is_map(field):
        key_field = field.message_type.fields_by_name["key"]
        value_field = field.message_type.fields_by_name["value"]
        container = getattr(message, field.name)
        # Sorted, so that the first error reported does not depend on hashing.
        for key in sorted(container):
            entry_path = _map_key_path(path, key_field, _map_key_text(key, key_field))
            if value_field.cpp_type == FD.CPPTYPE_MESSAGE:
                _validate_message(container[key], entry_path)
            else:
                _check_numeric(container[key], value_field, rule, entry_path)
        return
    if field.label == FD.LABEL_REPEATED:
        for i, element in enumerate(getattr(message, field.name)):
            if field.cpp_type == FD.CPPTYPE_MESSAGE:
                _validate_message(element, _element_path(path, i))
            else:
                _check_numeric(element, field, rule, _element_path(path, i))
        return
    if field.cpp_type == FD.CPPTYPE_MESSAGE:
        if message.HasField(field.name):
            _validate_message(getattr(message, field.name), path)
        return
    # An implicit-presence scalar always has a value the behavior will use: checked even at 0.
    if field.has_presence and not message.HasField(field.name):
        return
    _check_numeric(getattr(message, field.name), field, rule, path)


def _validate_message(message, path):
    for field in message.DESCRIPTOR.fields:
        _validate_field(message, field, _child_path(path, field.name))


def apply_defaults_and_validate(message):
    """Sets each unset field that declares a default_json to that default, then checks every
    rule (params::applyDefaultsAndValidate), in place: required fields set (INVALID_ARGUMENT
    "parameter 'x' is required: <description>"), numbers within range (INVALID_ARGUMENT
    "parameter 'x' = 5 is out of range [0, 3]", reason PARAMETER_OUT_OF_RANGE), recursively into
    nested messages, NaN and infinities refused for floating fields. Without explicit presence a
    zero or empty value counts as unset. A default_json that does not fit is INTERNAL. Raises
    StatusError at the first problem, in field declaration order."""
    _validate_message(message, "")


# ---- merge_update ------------------------------------------------------------------------------

def merge_update(update, current):
    """Applies a partial update in place (params::mergeUpdate): every field set in `update`
    (present with explicit presence, non-empty if repeated, non-default otherwise) replaces the
    same field of `current`; lists and maps are replaced, not appended to; nested messages are
    merged recursively. Both must be of one type."""
    if update.DESCRIPTOR is not current.DESCRIPTOR:
        raise TypeError(f"merge_update of {update.DESCRIPTOR.full_name} into "
                        f"{current.DESCRIPTOR.full_name}")
    for field, value in update.ListFields():
        if _is_map(field):
            current.ClearField(field.name)
            target = getattr(current, field.name)
            for key in value:
                if field.message_type.fields_by_name["value"].cpp_type == FD.CPPTYPE_MESSAGE:
                    target[key].CopyFrom(value[key])
                else:
                    target[key] = value[key]
        elif field.label == FD.LABEL_REPEATED:
            current.ClearField(field.name)
            getattr(current, field.name).extend(value)
        elif field.cpp_type == FD.CPPTYPE_MESSAGE:
            if current.HasField(field.name):
                merge_update(value, getattr(current, field.name))
            else:
                getattr(current, field.name).CopyFrom(value)
        else:
            setattr(current, field.name, value)


# ---- describe ----------------------------------------------------------------------------------

_UNIT_SUFFIXES = (
    ("_s", "s"), ("_ms", "ms"), ("_m", "m"), ("_m_s", "m/s"), ("_m_s2", "m/s^2"),
    ("_rad", "rad"), ("_rad_s", "rad/s"), ("_deg", "deg"), ("_hz", "Hz"), ("_n", "N"),
    ("_kg", "kg"), ("_v", "V"), ("_a", "A"), ("_px", "px"), ("_pa", "Pa"), ("_ratio", "1"),
    ("_percent", "%"), ("_bytes", "bytes"), ("_m_s3", "m/s^3"), ("_n_s_m", "N s/m"),
    ("_n_s2_m2", "N s^2/m^2"),
)


def unit_of_field_name(name):
    """The unit carried by a field name's suffix ("duration_s" -> "s", "speed_m_s" -> "m/s",
    "rate_hz" -> "Hz"), or "" if none is recognised. The longest suffix wins."""
    best, unit = "", ""
    for suffix, suffix_unit in _UNIT_SUFFIXES:
        if len(name) > len(suffix) and name.endswith(suffix) and len(suffix) > len(best):
            best, unit = suffix, suffix_unit
    return unit


def _value_type(field):
    cpp = field.cpp_type
    if cpp in _FLOATING:
        return behavior_pb2.PARAMETER_TYPE_NUMBER
    if cpp in _INTEGERS:
        return behavior_pb2.PARAMETER_TYPE_INTEGER
    if cpp == FD.CPPTYPE_BOOL:
        return behavior_pb2.PARAMETER_TYPE_BOOLEAN
    if cpp == FD.CPPTYPE_STRING:
        return (behavior_pb2.PARAMETER_TYPE_BYTES if field.type == FD.TYPE_BYTES
                else behavior_pb2.PARAMETER_TYPE_STRING)
    if cpp == FD.CPPTYPE_ENUM:
        return behavior_pb2.PARAMETER_TYPE_ENUM
    return behavior_pb2.PARAMETER_TYPE_OBJECT


def _set_value_type(value_type, schema):
    """ParameterSchema.value_type and `type`, its text form ("number", ...)."""
    schema.value_type = value_type
    name = behavior_pb2.ParameterType.Name(value_type)
    schema.type = ("" if value_type == behavior_pb2.PARAMETER_TYPE_UNSPECIFIED
                   else name[len("PARAMETER_TYPE_"):].lower())


def _proto_type(field):
    if field.type == FD.TYPE_ENUM:
        return field.enum_type.full_name
    if field.type in (FD.TYPE_MESSAGE, FD.TYPE_GROUP):
        return field.message_type.full_name
    return _type_name(field)


def _describe_fields(descriptor, depth, stack, out):
    stack.append(descriptor)
    for field in descriptor.fields:
        rule = _rule(field)
        # For a map, what the schema describes per key is its value type.
        is_map = _is_map(field)
        value_field = field.message_type.fields_by_name["value"] if is_map else field
        schema = out.add(name=field.name)
        if is_map:
            _set_value_type(behavior_pb2.PARAMETER_TYPE_OBJECT, schema)
            key_field = field.message_type.fields_by_name["key"]
            schema.proto_type = f"map<{_proto_type(key_field)}, {_proto_type(value_field)}>"
        else:
            _set_value_type(_value_type(field), schema)
            schema.proto_type = _proto_type(field)
            schema.repeated = field.label == FD.LABEL_REPEATED
        schema.unit = unit_of_field_name(field.name)
        if rule.HasField("range"):
            schema.range.CopyFrom(rule.range)
        schema.default_json = rule.default_json
        schema.required = rule.required
        schema.description = _description(field, rule)
        if value_field.cpp_type == FD.CPPTYPE_ENUM:
            schema.enum_values.extend(v.name for v in value_field.enum_type.values)
        if value_field.cpp_type == FD.CPPTYPE_MESSAGE:
            nested = value_field.message_type
            if all(d is not nested for d in stack) and depth + 1 < _MAX_DESCRIBE_DEPTH:
                _describe_fields(nested, depth + 1, stack, schema.fields)
    stack.pop()


def describe(descriptor, out):
    """Adds to `out` (a repeated ParameterSchema field, e.g. BehaviorDescription.parameters) one
    schema per field of the message `descriptor` (params::describe), recursing into nested
    messages, guarding against recursive types and stopping at depth 8; for ListBehaviors."""
    _describe_fields(descriptor, 0, [], out)
