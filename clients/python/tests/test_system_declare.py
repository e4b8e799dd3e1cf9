"""Parameters declared in Python (behaviorlib.system.declare): the message they make carries
the options a .proto would, and is validated and described as a compiled one is."""

import grpc
import pytest
from google.protobuf import struct_pb2

from behaviorlib.system import declare, parameters
from behaviorlib.v1 import behavior_pb2, options_pb2

Declared = declare.declare_parameters(
    "DeclaredTestParameters", package="behaviorlib.tests.declared.v1",
    behavior="DECLARED_TEST", kind="GOAL_BASED", doc="Flies a test.",
    activate_doc="Activates DECLARED_TEST.",
    fields=[
        declare.Field("center_m", "Vector3", required=True, doc="Centre in metres."),
        declare.Field("radius_m", "double", range=(0.3, 50), default=2.0, doc="Radius in m."),
        declare.Field("names", "string", repeated=True, doc="Some names."),
    ])


def test_the_message_carries_the_declaration_and_the_rules():
    descriptor = Declared.DESCRIPTOR
    assert descriptor.full_name == "behaviorlib.tests.declared.v1.DeclaredTestParameters"
    declaration = descriptor.GetOptions().Extensions[options_pb2.declare]
    assert (declaration.name, declaration.kind) == ("DECLARED_TEST",
                                                   options_pb2.BEHAVIOR_KIND_GOAL_BASED)
    assert declaration.activate_doc == "Activates DECLARED_TEST."
    radius = descriptor.fields_by_name["radius_m"]
    rule = radius.GetOptions().Extensions[options_pb2.param]
    assert (rule.range.min, rule.range.max, rule.default_json) == (0.3, 50.0, "2.0")
    assert radius.has_presence  # `optional`, as the shipped protos declare such a field
    assert descriptor.fields_by_name["center_m"].message_type.full_name == "behaviorlib.v1.Vector3"
    assert parameters.leading_comment(descriptor.full_name) == "Flies a test."
    assert parameters.leading_comment(descriptor.full_name + ".radius_m") == "Radius in m."


def test_it_is_validated_as_a_compiled_message_is():
    values = struct_pb2.Struct()
    values.update({"center_m": {"x": 1, "y": 2, "z": 3}})
    message = parameters.from_struct(values, Declared)
    parameters.apply_defaults_and_validate(message)
    assert message.radius_m == 2.0 and message.center_m.z == 3.0
    values.update({"radius_m": 100})
    with pytest.raises(parameters.StatusError) as out_of_range:
        message = parameters.from_struct(values, Declared)
        parameters.apply_defaults_and_validate(message)
    error = out_of_range.value
    assert error.code == grpc.StatusCode.INVALID_ARGUMENT
    assert error.reason == "PARAMETER_OUT_OF_RANGE"
    assert [field for field, _ in error.field_violations] == ["radius_m"]
    with pytest.raises(parameters.StatusError) as missing:
        message = Declared()
        parameters.apply_defaults_and_validate(message)
    assert [field for field, _ in missing.value.field_violations] == ["center_m"]


def test_it_is_described_for_list_behaviors():
    description = behavior_pb2.BehaviorDescription()
    parameters.describe(Declared.DESCRIPTOR, description.parameters)
    by_name = {p.name: p for p in description.parameters}
    assert set(by_name) >= {"center_m", "radius_m", "names"}
    assert by_name["radius_m"].description.startswith("Radius in m.")


def test_bad_declarations_are_refused():
    with pytest.raises(ValueError, match="neither a scalar"):
        declare.declare_parameters("Bad1", package="behaviorlib.tests.bad.v1", behavior="BAD",
                                   fields=[declare.Field("x", "Quux")])
    with pytest.raises(ValueError, match="twice"):
        declare.declare_parameters("Bad2", package="behaviorlib.tests.bad.v1", behavior="BAD",
                                   fields=[declare.Field("x", "double"),
                                           declare.Field("x", "double")])
    with pytest.raises(TypeError, match="unknown declaration"):
        declare.declare_parameters("Bad3", package="behaviorlib.tests.bad.v1", behavior="BAD",
                                   launch_doc="no")
