"""The CIRCLE_AROUND example's reference (examples/python_behavior/circle_around.py), without a
server: continuous from the vehicle to the circle and around it, at the asked speed, ending where
its turns end; and its parameters validated as declared."""

import math
import os
import sys

import pytest
from google.protobuf import struct_pb2

from behaviorlib.system import StatusError, apply_defaults_and_validate, from_struct
from behaviorlib.v1 import options_pb2

from conftest import REPO

sys.path.insert(0, os.path.join(REPO, "examples", "python_behavior"))
import circle_around  # noqa: E402


def test_the_reference_is_continuous_at_the_asked_speed_and_ends_after_its_turns():
    plan = circle_around.Plan(start=(0.0, 0.0, 1.5), center=(3.0, 0.0, 2.0), radius=1.0,
                              speed=1.0, turns=1.5)
    # The nearest point of the circle to the vehicle, at the centre's altitude.
    assert plan.entry == pytest.approx((2.0, 0.0, 2.0))
    assert plan.approach_s == pytest.approx(math.dist((0, 0, 1.5), (2, 0, 2)))
    assert plan.end_s == pytest.approx(plan.approach_s + 1.5 * 2 * math.pi)
    step = 0.01
    previous = plan.at(0.0)[0]
    t = step
    while t <= plan.end_s:
        position, velocity, _ = plan.at(t)
        assert math.dist(previous, position) <= 1.0 * step * 1.01 + 1e-9, t  # no jump
        assert math.hypot(*velocity) == pytest.approx(1.0, rel=1e-6), t
        previous = position
        t += step
    # After 1.5 turns from the entry (angle pi), the end is on the other side (angle 0).
    assert plan.end == pytest.approx((4.0, 0.0, 2.0), abs=1e-9)
    assert plan.at(plan.end_s + 5.0)[1] == (0.0, 0.0, 0.0)  # it stops there
    assert plan.yaw_at((4.0, 0.0, 2.0)) == pytest.approx(math.pi)  # facing the centre


def test_its_parameters_are_validated_with_their_ranges_and_defaults():
    values = struct_pb2.Struct()
    values.update({"center_m": {"x": 0, "y": 0, "z": 2}})
    parameters = from_struct(values, circle_around.CircleAroundParameters)
    apply_defaults_and_validate(parameters)
    assert (parameters.radius_m, parameters.speed_m_s, parameters.turns) == (2.0, 1.0, 1.0)
    values.update({"speed_m_s": 9})
    with pytest.raises(StatusError) as refused:
        apply_defaults_and_validate(from_struct(values, circle_around.CircleAroundParameters))
    assert refused.value.reason == "PARAMETER_OUT_OF_RANGE"
    assert [f for f, _ in refused.value.field_violations] == ["speed_m_s"]


def test_the_shipped_catalog_has_its_entry():
    import yaml
    with open(os.path.join(REPO, "deploy", "config", "catalog.yaml")) as f:
        catalog = yaml.safe_load(f)
    name = circle_around.CircleAroundParameters.DESCRIPTOR.GetOptions().Extensions[
        options_pb2.declare].name
    assert catalog["behaviors"][name] == {"requires": ["self_localization", "motion_control"],
                                          "holds": ["motion_reference"]}


def test_the_python_section_of_writing_a_behavior_is_the_example():
    import re
    with open(os.path.join(REPO, "docs", "writing-a-behavior.md")) as f:
        text = f.read()
    blocks = re.findall(r"<!-- python-file: (\S+) -->\n```\w*\n(.*?)```", text, re.S)
    assert [name for name, _ in blocks] == ["circle_around.py", "system.py",
                                            "circle_mission.yaml"]
    for name, code in blocks:
        with open(os.path.join(REPO, "examples", "python_behavior", name)) as f:
            assert code == f.read(), f"docs/writing-a-behavior.md's {name} is not the example's"
    entry = re.search(r"<!-- python-catalog -->\n```yaml\n(.*?)```", text, re.S).group(1)
    with open(os.path.join(REPO, "deploy", "config", "catalog.yaml")) as f:
        assert entry in f.read()
