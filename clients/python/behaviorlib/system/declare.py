"""A behavior's parameter message declared in Python, for a behavior that has no .proto file:
the same message, with the same options (behaviorlib.v1.declare, behaviorlib.v1.param), that
a .proto would give, built as a FileDescriptorProto and added to the default descriptor pool.
It is validated, described (ListBehaviors), served (the typed service, reflection) and shown
exactly as a compiled one is, and needs no protoc at run time.

    from behaviorlib.system.declare import Field, declare_parameters

    CircleAroundParameters = declare_parameters(
        "CircleAroundParameters", package="examples.circle_around.v1",
        behavior="CIRCLE_AROUND", kind="GOAL_BASED",
        doc="Flies circles around a point at its altitude.",
        activate_doc="Activates CIRCLE_AROUND. INVALID_ARGUMENT for bad parameters ...",
        fields=[
            Field("center_m", "Vector3", required=True,
                  doc="Centre of the circle in metres, world frame (ENU); z is the altitude."),
            Field("radius_m", "double", range=(0.3, 50), default=2.0, doc="Radius in metres."),
            Field("turns", "double", range=(0.1, 20), default=1.0, doc="Turns to fly."),
        ])

A field's type is a scalar name ("double", "float", "int32", "int64", "uint32", "uint64",
"bool", "string", "bytes") or a message of behaviorlib.v1 (its short name, "Vector3", or a full
name). A scalar field with a default or a range is `optional` (proto3 presence), as the shipped
protos declare them, so that an unset value takes the default. `repeated=True` makes a list.
Why not protoc at run time: a user's Python package would then need protoc and the behaviorlib
.proto sources installed beside it; the descriptor the declaration builds is the same message.
"""

import dataclasses
import json

from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

from behaviorlib.system import parameters
from behaviorlib.v1 import options_pb2, types_pb2

_SCALARS = {
    "double": descriptor_pb2.FieldDescriptorProto.TYPE_DOUBLE,
    "float": descriptor_pb2.FieldDescriptorProto.TYPE_FLOAT,
    "int32": descriptor_pb2.FieldDescriptorProto.TYPE_INT32,
    "int64": descriptor_pb2.FieldDescriptorProto.TYPE_INT64,
    "uint32": descriptor_pb2.FieldDescriptorProto.TYPE_UINT32,
    "uint64": descriptor_pb2.FieldDescriptorProto.TYPE_UINT64,
    "bool": descriptor_pb2.FieldDescriptorProto.TYPE_BOOL,
    "string": descriptor_pb2.FieldDescriptorProto.TYPE_STRING,
    "bytes": descriptor_pb2.FieldDescriptorProto.TYPE_BYTES,
}
_KINDS = {"GOAL_BASED": options_pb2.BEHAVIOR_KIND_GOAL_BASED,
          "RECURRENT": options_pb2.BEHAVIOR_KIND_RECURRENT}
_DOCS = ("activate_doc", "deactivate_doc", "check_activation_doc", "check_situation_doc",
         "pause_doc", "resume_doc", "modify_doc", "modify_parameters_doc")
# Where the messages a field may name come from.
_IMPORTS = {types_pb2.DESCRIPTOR.name: types_pb2.DESCRIPTOR}


@dataclasses.dataclass(frozen=True)
class Field:
    """One parameter: its name (snake_case, with its SI unit as a suffix: `_m`, `_s`, `_m_s`,
    `_rad`), type, rule and description."""

    name: str
    type: str
    doc: str = ""
    required: bool = False
    range: tuple = None   # (min, max); either may be None
    default: object = None  # a JSON-able value
    repeated: bool = False


def _message_type(name):
    """The full name of a behaviorlib.v1 message named `name` (short or full)."""
    pool = descriptor_pool.Default()
    for full in (name, f"behaviorlib.v1.{name}"):
        try:
            return pool.FindMessageTypeByName(full)
        except KeyError:
            continue
    raise ValueError(f"field type {name!r} is neither a scalar ({', '.join(_SCALARS)}) nor a "
                     "message of behaviorlib.v1")


def _add_field(message, number, field, file):
    proto = message.field.add(name=field.name, number=number, json_name=_json_name(field.name))
    proto.label = (descriptor_pb2.FieldDescriptorProto.LABEL_REPEATED if field.repeated else
                   descriptor_pb2.FieldDescriptorProto.LABEL_OPTIONAL)
    if field.type in _SCALARS:
        proto.type = _SCALARS[field.type]
    else:
        descriptor = _message_type(field.type)
        proto.type = descriptor_pb2.FieldDescriptorProto.TYPE_MESSAGE
        proto.type_name = "." + descriptor.full_name
        if descriptor.file.name not in file.dependency:
            file.dependency.append(descriptor.file.name)
    rule = proto.options.Extensions[options_pb2.param]
    if field.required:
        rule.required = True
    if field.range is not None:
        low, high = field.range
        if low is not None:
            rule.range.min = float(low)
        if high is not None:
            rule.range.max = float(high)
    if field.default is not None:
        rule.default_json = json.dumps(field.default)
    if field.doc:
        rule.description = field.doc
    if not proto.options.ListFields():
        proto.ClearField("options")
    # A scalar with a default or a range has presence, as `optional double x = 1;` in a .proto.
    scalar = field.type in _SCALARS and not field.repeated
    if scalar and (field.default is not None or field.range is not None):
        proto.proto3_optional = True
        proto.oneof_index = len(message.oneof_decl)
        message.oneof_decl.add(name=f"_{field.name}")


def _json_name(name):
    head, *rest = name.split("_")
    return head + "".join(part[:1].upper() + part[1:] for part in rest)


def declare_parameters(name, *, package, behavior, kind="GOAL_BASED", doc="", fields=(), **docs):
    """The message class of a behavior's parameters, declared as above. `name` is the message's
    name, `package` its proto package (the typed service is named after the message without
    "Parameters", `<package>.CircleAround` for CircleAroundParameters, as for a .proto), `behavior` the behavior's name (UPPER_SNAKE), `kind` GOAL_BASED or RECURRENT,
    `doc` the behavior's description, and the keyword arguments `activate_doc`,
    `deactivate_doc`, ... the typed methods' descriptions (behaviorlib.v1.BehaviorDeclaration).
    Declaring the same message twice is an error (its name is taken in the pool)."""
    unknown = set(docs) - set(_DOCS)
    if unknown:
        raise TypeError(f"unknown declaration fields {sorted(unknown)}: use {', '.join(_DOCS)}")
    if kind not in _KINDS:
        raise ValueError(f"kind {kind!r}: use GOAL_BASED or RECURRENT")
    names = [f.name for f in fields]
    if len(set(names)) != len(names):
        raise ValueError(f"{name}: a field is declared twice in {names}")
    file = descriptor_pb2.FileDescriptorProto(
        name=f"{package.replace('.', '/')}/{name}.declared.proto", package=package,
        syntax="proto3")
    file.dependency.append(options_pb2.DESCRIPTOR.name)
    message = file.message_type.add(name=name)
    declaration = message.options.Extensions[options_pb2.declare]
    declaration.name = behavior
    declaration.kind = _KINDS[kind]
    for key, value in docs.items():
        setattr(declaration, key, value)
    # Fields first (scalars with presence take their synthetic oneofs after every real one:
    # there are none here).
    for number, field in enumerate(fields, start=1):
        _add_field(message, number, field, file)
    # The comments a .proto would have: the message's is the behavior's description
    # (ListBehaviors), each field's its parameter's (also its rule's description).
    comments = [([4, 0], doc)] + [([4, 0, 2, i], f.doc) for i, f in enumerate(fields)]
    for path, text in comments:
        if text:
            location = file.source_code_info.location.add(path=path, span=[0, 0, 0])
            location.leading_comments = " " + text.replace("\n", "\n ") + "\n"
    pool = descriptor_pool.Default()
    pool.Add(file)
    parameters.load_descriptor_set(
        descriptor_pb2.FileDescriptorSet(file=[file]).SerializeToString())
    descriptor = pool.FindMessageTypeByName(f"{package}.{name}")
    return message_factory.MessageFactory(pool).GetPrototype(descriptor)
