#!/usr/bin/python3
"""Writes the binary and generated seeds of tests/fuzz/corpus (docs/fuzzing.md).

The YAML seeds are hand-written or copied from shipped files; the seeds of
fuzz_parameters_struct, fuzz_parameters_json, fuzz_journal and
fuzz_channel_sample are made here, from messages written in Python.

    /usr/bin/python3 tests/fuzz/make_seeds.py     # Debian's python3-protobuf, protoc

Each seed's first byte selects what the target does with the rest (see the
comment at the top of each target); the indices below must match the
targets' tables.
"""

import json
import os
import struct
import subprocess
import sys
import tempfile
import zlib

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
CORPUS = os.path.join(ROOT, "tests", "fuzz", "corpus")
PROTOS = ["options", "errors", "types", "behavior", "mission", "channel", "motion", "platform",
          "simulator", "coordinator"]

_gen_dir = tempfile.TemporaryDirectory(prefix="behaviorlib_pb2_")  # removed at exit
gen = _gen_dir.name
subprocess.run(["protoc", "--proto_path=" + os.path.join(ROOT, "proto"), "--python_out=" + gen]
               + [os.path.join(ROOT, "proto", "behaviorlib", "v1", p + ".proto") for p in PROTOS]
               + [os.path.join(ROOT, "proto", "behaviorlib", "durable", "v1", "journal.proto")],
               check=True)
sys.path.insert(0, gen)

from google.protobuf import any_pb2, json_format, struct_pb2  # noqa: E402
from behaviorlib.v1 import (channel_pb2, coordinator_pb2, mission_pb2, motion_pb2,  # noqa: E402
                            platform_pb2, types_pb2)
from behaviorlib.durable.v1 import journal_pb2  # noqa: E402


def encode(message):
    """Map fields in a fixed order, so that the seeds are the same at every run."""
    return message.SerializeToString(deterministic=True)


def write(target, name, data):
    os.makedirs(os.path.join(CORPUS, target), exist_ok=True)
    with open(os.path.join(CORPUS, target, name), "wb") as f:
        f.write(data if isinstance(data, bytes) else data.encode())


# --- parameters ---------------------------------------------------------------
# Index in kTypes of fuzz_parameters_{struct,json}.cc.
FOLLOW_PATH, QR_CODES, GENERATE_PATH, INFORM_ROBOTS, ESTIMATE, TAKE_OFF = range(6)
ALL_KINDS, CHOICE, TREE, STRICT = range(6, 10)

PARAMETERS = {
    "follow_path": (FOLLOW_PATH, {"path_m": [{"x": 4, "y": 0, "z": 1.5}, {"x": 4, "y": 4, "z": 1.5},
                                             {"x": 0, "y": 0, "z": 1.5}],
                                  "speed_m_s": 1.0, "tolerance_m": 0.1}),
    "follow_path_camel": (FOLLOW_PATH, {"pathM": [{"x": 1, "y": 2, "z": 3}], "speedMS": 0.5,
                                        "accelerationM_s2": 2}),
    "follow_path_bad": (FOLLOW_PATH, {"path_m": [{"x": "1"}, None, [1, 2]], "speed_m_s": 99}),
    "qr_codes": (QR_CODES, {"marker_size_m": 0.5, "marker_sizes_m": {"ROOM-A": 0.3, "": 10},
                            "min_sightings": 3, "max_range_m": 8}),
    "generate_path": (GENERATE_PATH, {"goal_m": {"x": 3, "y": 4, "z": 1.5}, "max_replans": 4,
                                      "bounds_min_m": {"x": -10, "y": -10, "z": 0},
                                      "bounds_max_m": {"x": 10, "y": 10, "z": 5},
                                      "belief_key": "drone1/path"}),
    "generate_path_missing": (GENERATE_PATH, {"max_replans": -1, "vehicle_radius_m": 1e308}),
    "inform_robots": (INFORM_ROBOTS, {"robot_ids": ["drone1", "drone2"], "text": "hello",
                                      "payload_json": "{\"k\": [1, 2]}"}),
    "estimate": (ESTIMATE, {"max_innovation_m": 2.0, "max_rejected_samples": 4294967295,
                            "use_barometer": False}),
    "take_off": (TAKE_OFF, {"altitude_m": 1.5}),
    "all_kinds": (ALL_KINDS, {
        "count": 3, "big": -9007199254740993, "small_u": 7, "big_u": 1.8e19, "s32": -5,
        "f64": 123, "ratio": 0.1, "duration_s": 2.5, "enabled": True, "name": "n",
        "blob": "aGVsbG8=", "mode": "MEDIUM", "target": {"x_m": 1, "y_m": 2, "speed_m_s": 3},
        "path": {"waypoints": [{"x_m": 1}, {"y_m": -2}], "frame": "odom"}, "ids": [1, 2, 99],
        "gains": [0.5, 10], "tags": ["a", ""], "modes": ["SLOW", 1], "flags": [True, False],
        "chunks": ["AA==", "_-8="], "altitude_m": 120, "retries": 0,
        "tree": {"label": "root", "children": [{"label": "a", "children": [{"label": "b"}]}]},
        "goal_yaw_rad": 1.57, "limits": {"x": 1, "y": 0}, "stops": {"1": {"x_m": 1}, "-2": {}},
        "camelCaseName": "c"}),
    "all_kinds_bad": (ALL_KINDS, {"count": 1.5, "mode": "FAST", "goal_yaw_rad": 1, "goal_name": "x",
                                  "stops": {"x": {}}, "blob": "!!", "ratio": 3.5e38,
                                  "big": 9.3e18, "camel_case_name": "a", "camelCaseName": "b"}),
    "choice": (CHOICE, {"b": "picked"}),
    "tree_deep": (TREE, json.loads("{\"children\": [" * 30 + "{}" + "]}" * 30)),
    "strict": (STRICT, {"level": 0}),
}

for name, (index, value) in PARAMETERS.items():
    s = struct_pb2.Struct()
    s.update(value)
    write("fuzz_parameters_struct", name, bytes([index]) + encode(s))
    text = json.dumps(value)
    write("fuzz_parameters_json", name + ".json", bytes([index]) + text.encode())
# Values a Struct built in code can carry but JSON cannot.
for name, number in [("nan", float("nan")), ("inf", float("inf")), ("huge", 1e300)]:
    s = struct_pb2.Struct()
    s.update({"altitude_m": number, "duration_s": number, "count": number})
    write("fuzz_parameters_struct", "take_off_" + name, bytes([TAKE_OFF]) + encode(s))
    write("fuzz_parameters_struct", "all_kinds_" + name, bytes([ALL_KINDS]) + encode(s))
write("fuzz_parameters_struct", "empty", bytes([ALL_KINDS]))
# YAML (source 1: high nibble 1), as a mission step's parameters.
YAML = {
    "follow_path.yaml": (FOLLOW_PATH, "path_m:\n  - {x: 4.0, y: 0.0, z: 1.5}\n"
                                      "  - {x: 4, y: 4, z: 1.5}\nspeed_m_s: 1.0\n"),
    "qr_codes.yaml": (QR_CODES, "marker_sizes_m: {ROOM-A: 0.5, '1': .inf}\nmin_sightings: 0x10\n"),
    "all_kinds.yaml": (ALL_KINDS, "count: 3\nmode: MEDIUM\nname: !!str 12\nenabled: yes\n"
                                  "duration_s: 1e1\ntags: [a, 'b', ~]\nstops: {1: {x_m: 1}}\n"
                                  "tree: &t {label: x}\nblob: !binary aGk=\n"),
    "anchors.yaml": (TREE, "children: &c [{label: a}, {label: b}]\nlabel: &l root\n"),
    "not_a_mapping.yaml": (TAKE_OFF, "- altitude_m: 1\n"),
    "complex_key.yaml": (TAKE_OFF, "? [a, b]\n: 1\n"),
}
for name, (index, text) in YAML.items():
    write("fuzz_parameters_json", name, bytes([0x10 | index]) + text.encode())
# A belief value (source 2: high nibble 2), bound into every parameter.
BELIEFS = {
    "belief_path.json": (FOLLOW_PATH, [{"x": 1, "y": 2, "z": 3}]),
    "belief_number.json": (TAKE_OFF, 1.5),
    "belief_object.json": (GENERATE_PATH, {"x": 1, "y": 2, "z": 3}),
    "belief_text.json": (INFORM_ROBOTS, "drone${belief.fuzz/value}"),
    "belief_list.json": (ALL_KINDS, [1, "two", None, True, {"a": []}]),
}
for name, (index, value) in BELIEFS.items():
    write("fuzz_parameters_json", name, bytes([0x20 | index]) + json.dumps(value).encode())

# --- journal ------------------------------------------------------------------
def frame(payload):
    return struct.pack("<II", len(payload), zlib.crc32(payload)) + payload


def record(**kwargs):
    r = journal_pb2.JournalRecord()
    for field, value in kwargs.items():
        getattr(r, field).CopyFrom(value)
    return encode(r)


def belief(key, value, version, deleted=False, type_name=""):
    b = mission_pb2.Belief(key=key, version=version, deleted=deleted, writer="operator",
                           type=type_name)
    if value is not None:
        json_format.Parse(json.dumps(value), b.value)
    return b


with open(os.path.join(ROOT, "deploy", "missions", "demo.yaml")) as f:
    demo = f.read()
running = mission_pb2.MissionStatus(mission_id="m1", name="demo_square", robot_id="drone1",
                                    file="demo.yaml", state=mission_pb2.MISSION_STATE_RUNNING,
                                    source=demo)
running.steps.add(path=[1], name="take_off", behavior="TAKE_OFF", attempt=1)
ended = mission_pb2.MissionStatus(mission_id="m0", state=mission_pb2.MISSION_STATE_FAILED,
                                  source="steps: [{behavior: WAIT}]", message="aborted")
ended.end_time.seconds = 1700000000
records = [
    record(belief=belief("drone1/path", [{"x": 1, "y": 2, "z": 3}], 1,
                         type_name="behaviorlib.v1.Path")),
    record(belief=belief("operator_answer", "yes", 2)),
    record(belief=belief("drone1/path", None, 3, deleted=True)),
    record(belief=belief("bad key!", {"a": None}, 2**64 - 1)),
    record(mission=running),
    record(mission=ended),
    record(system=journal_pb2.SystemRecord(robot_id="drone1", system="basic",
                                           address="127.0.0.1:50061")),
    record(system=journal_pb2.SystemRecord(robot_id="drone1", system="basic", unregistered=True)),
]
journal = b"".join(frame(r) for r in records)
write("fuzz_journal", "mode0_records", b"\x00" + journal)
write("fuzz_journal", "mode0_torn_tail",
      b"\x00" + journal + bytes([40, 0, 0, 0, 1, 2, 3, 4]) + b"xy")
corrupt = bytearray(frame(records[0]))
corrupt[-1] ^= 0x7F
write("fuzz_journal", "mode0_corrupt_crc", b"\x00" + frame(records[1]) + bytes(corrupt))
write("fuzz_journal", "mode0_too_long", b"\x00" + struct.pack("<II", 64 << 20 | 1, 0))
write("fuzz_journal", "mode0_empty_records", b"\x00" + frame(b"") * 3)
for i, r in enumerate(records):
    write("fuzz_journal", "mode1_record%d" % i, b"\x01" + r)


def lengths_at_end(payloads):
    """Mode 2 (FuzzedDataProvider): payloads from the front, each length (0..4096, two bytes)
    taken from the end of the data."""
    tail = b""
    for p in payloads:
        tail = bytes([len(p) & 0xFF, len(p) >> 8]) + tail
    return b"".join(payloads) + tail


write("fuzz_journal", "mode2_records", b"\x02" + lengths_at_end(records))

# --- channel samples ----------------------------------------------------------
def stamped(message):
    message.header.stamp.seconds = 12
    message.header.frame_id = "world"
    message.header.robot_id = "drone1"
    message.header.seq = 3
    return message


pose = stamped(types_pb2.PoseStamped())
pose.pose.position_m.x, pose.pose.orientation.w = 1.0, 1.0
scan = stamped(types_pb2.LaserScan(angle_min_rad=-3.14, angle_max_rad=3.14,
                                   ranges_m=[1.0, 2.0, 30.0]))
image = stamped(types_pb2.Image(width_px=2, height_px=2, encoding="png", data=b"\x89PNG\r\n\x1a\n"))
clock = types_pb2.Clock()
clock.time.seconds = 5
samples = [
    ("robots/drone1/ground_truth/pose", pose),
    ("robots/drone1/lidar/scan", scan),
    ("robots/drone1/camera/image", image),
    ("clock", clock),
    ("robots/drone1/flight_status", platform_pb2.FlightStatus()),
    ("robots/drone1/motion_reference",
     motion_pb2.MotionReference(source="FOLLOW_PATH-1",
                                mode=motion_pb2.MOTION_REFERENCE_MODE_TRAJECTORY)),
    ("robots/swarm/messages", types_pb2.SwarmMessage(text="hi", payload_json="{}")),
]


def packed(message, prefix="type.googleapis.com/"):
    a = any_pb2.Any()
    a.type_url = prefix + message.DESCRIPTOR.full_name
    a.value = encode(message)
    return a


# Mode 0 (FuzzedDataProvider): the value from the front; from the end, in
# order: a bool (topic from the list), the topic's index, the type_url case
# (0: with the usual prefix), the type's index in kSampleTypes.
POSE_STAMPED, LASER_SCAN, IMAGE = 1, 8, 10
for name, value, type_index, topic_index in [
        ("mode0_pose", pose, POSE_STAMPED, 1), ("mode0_scan", scan, LASER_SCAN, 3),
        ("mode0_image", image, IMAGE, 4)]:
    write("fuzz_channel_sample", name,
          b"\x00" + encode(value) + bytes([type_index, 0, topic_index, 1]))
write("fuzz_channel_sample", "mode0_no_prefix",
      b"\x00" + encode(pose) + bytes([POSE_STAMPED, 1, 1, 1]))
for i, (topic, message) in enumerate(samples):
    request = channel_pb2.PublishRequest(topic=topic, sample=packed(message))
    if i == 0:
        request.more.add(topic=topic, sample=packed(message, "x/"))
        request.more.add(topic="robots//bad", sample=packed(message, ""))
        request.more.add(topic=topic, sample=any_pb2.Any(type_url="type.googleapis.com/no.Such"))
    write("fuzz_channel_sample", "mode1_publish%d" % i, b"\x01" + encode(request))
    response = channel_pb2.SubscribeResponse(topic=topic, sample=packed(message), topic_seq=i,
                                             dropped_count=1)
    response.receive_time.seconds = 1700000000
    write("fuzz_channel_sample", "mode2_subscribe%d" % i, b"\x02" + encode(response))


# --- flight recordings (MCAP, formats/mcap/mcap.cc) -----------------------
# Built here record by record (https://mcap.dev/spec), small: schemas carry a
# placeholder instead of a FileDescriptorSet, which the reader does not parse.
MCAP_MAGIC = b"\x89MCAP0\r\n"


def mcap_record(opcode, content):
    return struct.pack("<BQ", opcode, len(content)) + content


def mcap_string(text):
    data = text.encode()
    return struct.pack("<I", len(data)) + data


def mcap_file(messages, chunked=False, whole=True):
    """messages: (topic, type, bytes) in order."""
    header = mcap_record(0x01, mcap_string("behaviorlib") + mcap_string("make_seeds"))
    records = b""
    schemas, channels = {}, {}
    for i, (topic, type_name, data) in enumerate(messages):
        if type_name not in schemas:
            schemas[type_name] = len(schemas) + 1
            records += mcap_record(0x03, struct.pack("<H", schemas[type_name])
                                   + mcap_string(type_name) + mcap_string("protobuf")
                                   + struct.pack("<I", 4) + b"FDS\0")
        if topic not in channels:
            channels[topic] = len(channels) + 1
            records += mcap_record(0x04, struct.pack("<HH", channels[topic], schemas[type_name])
                                   + mcap_string(topic) + mcap_string("protobuf")
                                   + struct.pack("<I", 0))
        records += mcap_record(0x05, struct.pack("<HIQQ", channels[topic], i,
                                                 1700000000000000000 + i * 1000000,
                                                 1700000000000000000 + i * 1000000) + data)
    if chunked:
        records = mcap_record(0x06, struct.pack("<QQQI", 0, 0, len(records), zlib.crc32(records))
                              + mcap_string("") + struct.pack("<Q", len(records)) + records)
    body = MCAP_MAGIC + header + records
    if not whole:
        return body[:-3]
    body += mcap_record(0x0F, struct.pack("<I", 0))
    return body + mcap_record(0x02, struct.pack("<QQI", 0, 0, 0)) + MCAP_MAGIC


flight = []
activated = coordinator_pb2.FleetEvent(seq=1, incarnation="c1")
activated.behavior_event.robot_id = "drone1"
activated.behavior_event.behavior = "TAKE_OFF"
flight.append(("coordinator/events", "behaviorlib.v1.FleetEvent", encode(activated)))
system = coordinator_pb2.FleetEvent(seq=2)
system.system_state_changed.system.robot_id = "drone1"
flight.append(("coordinator/events", "behaviorlib.v1.FleetEvent", encode(system)))
status = mission_pb2.MissionStatus(mission_id="m1", robot_id="drone1")
flight.append(("coordinator/missions", "behaviorlib.v1.MissionStatus", encode(status)))
found = mission_pb2.Belief(key="drone1/markers/QR-1", version=3)
flight.append(("coordinator/beliefs", "behaviorlib.v1.Belief", encode(found)))
flight.append(("robots/drone1/ground_truth/pose", "behaviorlib.v1.PoseStamped", encode(pose)))
flight.append(("robots/drone1/ground_truth/pose", "behaviorlib.v1.PoseStamped", encode(pose)))
write("fuzz_mcap", "flight.mcap", mcap_file(flight))
write("fuzz_mcap", "flight_chunked.mcap", mcap_file(flight, chunked=True))
write("fuzz_mcap", "flight_cut.mcap", mcap_file(flight, whole=False))
