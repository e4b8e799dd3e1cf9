"""The flight recorder (clients/recorder, decision 36) end to end:

    build/venv/bin/python tests/e2e/flight_recorder_test.py --build-dir build

1. The local launcher flies the demo (--demo, the deterministic mode), which
   records by default into <run-dir>/recordings/flight.mcap; the report names the file.
2. Foxglove's MCAP library (npm @mcap/core, pinned by tests/e2e/mcap's
   lockfile, installed by npm ci into the build tree) reads the file: CRCs,
   summary, statistics, and per topic the messages, which must be the ones
   the recorder said it wrote and the flight's: TAKE_OFF to LAND with
   GOAL_ACHIEVED, poses, the mission's status.
3. `behaviorctl replay --speed 0` publishes the recording into a new broker;
   what a subscriber receives on the events, missions and ground-truth pose
   topics equals, message by message, what @mcap/core read from the file.
4. `replay --speed 4` of the events takes at least a quarter of their
   recorded span (pacing never runs ahead of the recording).

Exits 77 (skipped) when npm is not installed or its registry cannot be
reached (scripts/install-deps.sh installs npm).
"""

import argparse
import hashlib
import json
import os
import shutil
import struct
import subprocess
import sys
import tempfile
import threading
import time
import unittest

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.abspath(os.path.join(HERE, "..", ".."))
sys.path.insert(0, os.path.join(REPO, "tests", "deploy"))
import deploy_support as ds  # noqa: E402

import grpc  # noqa: E402
from behaviorlib.v1 import (channel_pb2, channel_pb2_grpc, coordinator_pb2,  # noqa: E402
                            mission_pb2)

LAUNCHER = os.path.join(REPO, "deploy", "local", "launch.py")
ROBOT = "drone1"
# Waits for what must happen; never a measure of speed.
WAIT_S = 120
ARGS = None


def digest(messages):
    """What read_mcap.js computes: SHA-256 over each message's data in
    order, each prefixed by its length (uint32, little-endian)."""
    hash_ = hashlib.sha256()
    for data in messages:
        hash_.update(struct.pack("<I", len(data)))
        hash_.update(data)
    return hash_.hexdigest()


class Subscriber:
    """Every sample of one topic of a broker, in order, on a thread."""

    def __init__(self, stub, topic):
        self.topic = topic
        self.samples = []
        self.dropped = 0
        request = channel_pb2.SubscribeRequest(topic=topic, mode=channel_pb2.DELIVERY_MODE_QUEUE,
                                               queue_size=10000)
        self.call = stub.Subscribe(request)
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self):
        try:
            for response in self.call:
                self.samples.append(response.sample)
                self.dropped = response.dropped_count
        except grpc.RpcError:
            pass

    def close(self):
        self.call.cancel()
        self.thread.join(timeout=10)


class FlightRecorderTest(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        cls.tmp = tempfile.mkdtemp(prefix="flight-recorder-e2e-")
        cls.run_dir = os.path.join(cls.tmp, "run")
        result = subprocess.run(
            [sys.executable, LAUNCHER, "--build-dir", ARGS.build_dir, "--run-dir", cls.run_dir,
             "--time-scale", "max", "--demo", "--no-console"],
            capture_output=True, text=True, timeout=WAIT_S)
        cls.launcher_output = result.stdout + result.stderr
        assert result.returncode == 0, f"the demo failed:\n{cls.launcher_output[-4000:]}"
        cls.recording = os.path.join(cls.run_dir, "recordings", "flight.mcap")
        read = subprocess.run(["node", os.path.join(HERE, "mcap", "read_mcap.js"), cls.recording],
                              env=dict(os.environ, NODE_PATH=os.path.join(ARGS.work_dir,
                                                                          "node_modules")),
                              capture_output=True, text=True, timeout=WAIT_S)
        assert read.returncode == 0, f"@mcap/core cannot read the recording:\n{read.stderr}"
        cls.read = json.loads(read.stdout)

    @classmethod
    def tearDownClass(cls):
        shutil.rmtree(cls.tmp, ignore_errors=True)

    def test_1_the_demo_is_recorded_and_the_report_names_the_file(self):
        self.assertTrue(os.path.getsize(self.recording) > 10000)
        self.assertIn(f"recording: {self.recording}", self.launcher_output)
        # The recorder caught up with the coordinator before it closed the
        # file, so the mission's end is in it (test 2).
        self.assertNotIn("did not catch up", self.launcher_output)
        with open(os.path.join(self.run_dir, "report.json")) as f:
            settings = json.load(f)["settings"]
        with open(os.path.join(self.run_dir, "report.md")) as f:
            markdown = f.read()
        self.assertEqual(settings["recording"], self.recording)
        self.assertIn(f"The flight recording is `{self.recording}`", markdown)
        # What the recorder said it wrote is what Foxglove's reader finds.
        recorded = {topic: int(n) for topic, n in settings["recording_messages"].items()}
        self.assertEqual(recorded, {t: v["count"] for t, v in self.read["topics"].items()})

    def test_2_foxglove_reads_the_file_and_it_holds_the_flight(self):
        read = self.read
        self.assertEqual(read["header"]["profile"], "behaviorlib")
        self.assertTrue(read["footer"])
        total = sum(v["count"] for v in read["topics"].values())
        self.assertEqual(read["statistics"]["message_count"], total)
        self.assertEqual(sorted(read["channels"]), sorted(read["topics"]))
        for topic, schema in (("coordinator/events", "behaviorlib.v1.FleetEvent"),
                              ("coordinator/missions", "behaviorlib.v1.MissionStatus"),
                              (f"robots/{ROBOT}/ground_truth/pose", "behaviorlib.v1.PoseStamped"),
                              (f"robots/{ROBOT}/flight_state", "behaviorlib.v1.FlightStatus")):
            self.assertIn(topic, read["topics"])
            self.assertEqual(read["topics"][topic]["schema"], schema)
            self.assertEqual(read["topics"][topic]["encoding"], "protobuf")
        for schema in read["schemas"]:
            self.assertEqual(schema["encoding"], "protobuf")
            self.assertGreater(schema["bytes"], 100, schema)  # a FileDescriptorSet
        # Poses at the recorder's rate (ground_truth/pose@30: at most 30 a second of wall
        # time, where the simulator publishes 100 a simulated second times the speed-up,
        # about 800 a second) through a flight of several seconds. The broker spaces its
        # writes; the log times are when the recorder took them, which on a busy machine
        # may lag a write by tens of milliseconds, so the span gets 0.25 s of slack (a
        # run beside a CPU hog logged 127 poses in 4.14 s).
        poses = read["topics"][f"robots/{ROBOT}/ground_truth/pose"]
        span_s = (int(poses["last_log_time_ns"]) - int(poses["first_log_time_ns"])) / 1e9
        self.assertGreater(poses["count"], 20)
        self.assertLessEqual(poses["count"], (span_s + 0.25) * 30 + 2, (poses["count"], span_s))
        # A topic recorded at every sample is not thinned: the flight state changes (landed,
        # taking off, flying, landing, landed) are all there.
        self.assertGreaterEqual(read["topics"][f"robots/{ROBOT}/flight_state"]["count"], 5)

    def _replay(self, broker_address, topics, *extra):
        stub = channel_pb2_grpc.DataChannelStub(grpc.insecure_channel(broker_address))
        subscribers = {topic: Subscriber(stub, topic) for topic in topics}
        # Published only once every subscription is taken: the broker says
        # which topics are wanted.
        interest = stub.WatchInterest(channel_pb2.WatchInterestRequest(prefix="robots/"),
                                      timeout=WAIT_S)
        for response in interest:
            if set(topics) <= set(response.wanted_topics):
                break
        interest.cancel()
        started = time.monotonic()
        result = subprocess.run(
            [os.path.join(ARGS.build_dir, "bin", "behaviorctl"), "--channel", broker_address,
             "replay", self.recording, *extra], capture_output=True, text=True, timeout=WAIT_S)
        wall_s = time.monotonic() - started
        self.assertEqual(result.returncode, 0, result.stderr)
        summary = json.loads(result.stdout)
        for topic, subscriber in subscribers.items():
            expected = int(summary["topics"].get(topic, 0))
            ds.wait_for(lambda s=subscriber, n=expected: len(s.samples) >= n, WAIT_S,
                        f"{expected} samples on {topic}")
            subscriber.close()
        return summary, subscribers, wall_s

    def test_3_a_replay_publishes_what_was_recorded(self):
        with tempfile.TemporaryDirectory(dir=self.tmp) as run_dir:
            broker_process, broker_address = start_broker(ARGS.build_dir, run_dir)
            try:
                pairs = {f"robots/{ROBOT}/recording/events": "coordinator/events",
                         f"robots/{ROBOT}/recording/missions": "coordinator/missions",
                         f"robots/{ROBOT}/ground_truth/pose": f"robots/{ROBOT}/ground_truth/pose"}
                summary, subscribers, _ = self._replay(broker_address, list(pairs), "--speed", "0")
                self.assertTrue(summary["complete"])
                self.assertEqual(int(summary["skipped"]), 0)
                for topic, recorded in pairs.items():
                    samples = subscribers[topic].samples
                    self.assertEqual(subscribers[topic].dropped, 0, topic)
                    self.assertEqual(len(samples), self.read["topics"][recorded]["count"], topic)
                    self.assertEqual(digest(s.value for s in samples),
                                     self.read["topics"][recorded]["sha256"], topic)
                # And they are the flight: each behavior from TAKE_OFF to
                # LAND ended GOAL_ACHIEVED, the mission SUCCEEDED.
                events = []
                for sample in subscribers[f"robots/{ROBOT}/recording/events"].samples:
                    event = coordinator_pb2.FleetEvent()
                    self.assertTrue(sample.Unpack(event))
                    events.append(event)
                seqs = [e.seq for e in events]
                self.assertEqual(seqs, sorted(set(seqs)))
                finished = {e.behavior_event.behavior: e.behavior_event.finished.cause
                            for e in events if e.behavior_event.HasField("finished")}
                for behavior in ("TAKE_OFF", "FOLLOW_PATH", "LAND"):
                    self.assertIn(behavior, finished)
                self.assertEqual(finished["LAND"], 1)  # TERMINATION_CAUSE_GOAL_ACHIEVED
                status = mission_pb2.MissionStatus()
                self.assertTrue(
                    subscribers[f"robots/{ROBOT}/recording/missions"].samples[-1].Unpack(status))
                self.assertEqual(status.state, mission_pb2.MISSION_STATE_SUCCEEDED)
            finally:
                broker_process.terminate()
                broker_process.wait(timeout=30)

    def test_4_a_paced_replay_never_runs_ahead_of_the_recording(self):
        events = self.read["topics"]["coordinator/events"]
        span_s = (int(events["last_log_time_ns"]) - int(events["first_log_time_ns"])) / 1e9
        self.assertGreater(span_s, 1.0)
        with tempfile.TemporaryDirectory(dir=self.tmp) as run_dir:
            broker_process, broker_address = start_broker(ARGS.build_dir, run_dir)
            try:
                topic = f"robots/{ROBOT}/recording/events"
                summary, subscribers, wall_s = self._replay(
                    broker_address, [topic], "--speed", "4", "--topic-prefix", "coordinator/events")
                self.assertEqual(int(summary["published"]), events["count"])
                self.assertEqual(digest(s.value for s in subscribers[topic].samples),
                                 events["sha256"])
                # A lower bound only: a busy machine makes a replay slower,
                # never faster.
                self.assertGreaterEqual(wall_s, span_s / 4)
            finally:
                broker_process.terminate()
                broker_process.wait(timeout=30)


def start_broker(build_dir, run_dir):
    """A channel_broker on a free loopback port: (process, address)."""
    port_file = os.path.join(run_dir, "broker.ports")
    log = open(os.path.join(run_dir, "broker.log"), "w")
    process = subprocess.Popen(
        [os.path.join(build_dir, "bin", "channel_broker"), "--listen", "127.0.0.1:0",
         "--metrics-listen", "127.0.0.1:0", "--port-file", port_file],
        stdout=log, stderr=subprocess.STDOUT)
    log.close()

    def ports():
        if process.poll() is not None:
            raise AssertionError(f"the broker exited: {ds.log_tail(log.name)}")
        if not os.path.exists(port_file):
            return None
        with open(port_file) as f:
            found = dict(line.strip().split("=", 1) for line in f if "=" in line)
        return found.get("grpc_port")

    port = ds.wait_for(ports, WAIT_S, "the broker's port")
    return process, f"127.0.0.1:{port}"


def main():
    global ARGS
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--build-dir", default=ds.DEFAULT_BUILD_DIR)
    parser.add_argument("--work-dir", required=True,
                        help="where npm installs @mcap/core (a build directory)")
    ARGS, rest = parser.parse_known_args()
    ARGS.build_dir = os.path.abspath(ARGS.build_dir)
    if not shutil.which("npm") or not shutil.which("node"):
        print("SKIPPED: npm is not installed (scripts/install-deps.sh)")
        return ds.SKIP
    try:
        ds.npm_ci(os.path.join(HERE, "mcap"), ARGS.work_dir)
    except ds.RegistryUnreachable as error:
        print(f"SKIPPED: {error}")
        return ds.SKIP
    program = unittest.main(argv=[sys.argv[0], *rest], exit=False)
    return 0 if program.result.wasSuccessful() else 1


if __name__ == "__main__":
    sys.exit(main())
