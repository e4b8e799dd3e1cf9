"""The console's gateway (console/gateway, decision 35) against the real
coordinator and a real behavior system on loopback:

    /usr/bin/python3 console_gateway_test.py --build-dir build

- the page and its scripts are served;
- POST /api/coordinator/ListSystems answers the coordinator's reply as JSON;
- the event feed (/api/events, Server-Sent Events) carries a behavior's
  activation and its termination with the cause, a mission started through
  the gateway up to its end, and resumes after Last-Event-ID without a gap;
- refusals answer their HTTP status with the google.rpc.Status as JSON (a
  call the console does not make, a body that is not the request, a refused
  mission with its field violation);
- the vehicle's pose and flight status arrive from the data channel, the
  map's world is the world file's, and beliefs come with their latest value;
- a flight recording (behaviorctl record, still being written, then whole)
  opens as the feed's messages with their times; bad names, missing files
  and files that are not MCAP are refused with their status;
- a coordinator that goes away is reported on the feed.
"""

import argparse
import http.client
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
import unittest

REPO = os.path.abspath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", ".."))
BUILD_DIR = os.path.join(REPO, "build")
# Waits for what must happen; never a measure of speed.
WAIT_S = 60


class Process:
    def __init__(self, name, argv, run_dir, tag=None):
        tag = tag or name
        self.port_file = os.path.join(run_dir, f"{tag}.ports")
        self.log_path = os.path.join(run_dir, f"{tag}.log")
        with open(self.log_path, "w") as log:
            self.process = subprocess.Popen(
                [os.path.join(BUILD_DIR, "bin", name), "--port-file", self.port_file, *argv],
                stdout=log, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + WAIT_S
        while not os.path.exists(self.port_file):
            if self.process.poll() is not None or time.monotonic() > deadline:
                raise AssertionError(f"{tag} did not start:\n{open(self.log_path).read()}")
            time.sleep(0.05)
        with open(self.port_file) as f:
            self.ports = dict(line.strip().split("=", 1) for line in f if "=" in line)

    def stop(self):
        if self.process.poll() is None:
            self.process.terminate()
            self.process.wait(timeout=30)
        return self.process.returncode


class EventFeed:
    """A reader of the gateway's Server-Sent Events."""

    def __init__(self, port, last_event_id=None):
        self.connection = http.client.HTTPConnection("127.0.0.1", port, timeout=WAIT_S)
        # What a browser sends: the feed comes uncompressed.
        headers = {"Accept": "text/event-stream", "Accept-Encoding": "gzip, deflate, br"}
        if last_event_id is not None:
            headers["Last-Event-ID"] = str(last_event_id)
        self.connection.request("GET", "/api/events", headers=headers)
        self.response = self.connection.getresponse()
        assert self.response.status == 200, self.response.status
        assert self.response.getheader("Content-Type").startswith("text/event-stream")
        encoding = self.response.getheader("Content-Encoding")
        assert encoding is None, f"the feed came encoded: {encoding}"

    def next(self):
        """(id, event, data as JSON) of the next message."""
        message = {}
        while True:
            line = self.response.fp.readline()
            if not line:
                raise EOFError("the feed ended")
            line = line.decode().rstrip("\n")
            if not line:
                if "data" in message:
                    return int(message["id"]), message["event"], json.loads(message["data"])
                message = {}
                continue
            if line.startswith(":"):
                continue  # keepalive
            field, _, value = line.partition(": ")
            message[field] = value

    def until(self, predicate):
        """Messages up to the first that satisfies predicate(event, data)."""
        seen = []
        deadline = time.monotonic() + WAIT_S
        while time.monotonic() < deadline:
            message = self.next()
            seen.append(message)
            if predicate(message[1], message[2]):
                return seen
        raise AssertionError(f"not seen within {WAIT_S} s: {seen[-5:]}")

    def close(self):
        self.connection.close()


def finished(behavior, duration_s, robot="robot-a"):
    """The finished event of the activation of `behavior` with this
    duration_s (each test activates its own, and a new feed replays the
    past)."""
    def test(event, data):
        e = data.get("behavior_event") or {}
        return (event == "fleet" and e.get("behavior") == behavior and
                e.get("robot_id") == robot and "finished" in e and
                e["finished"]["parameters"].get("duration_s") == duration_s)
    return test


class ConsoleGatewayTest(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        cls.dir = tempfile.mkdtemp(prefix="console-test-")
        listen = ["--listen", "127.0.0.1:0", "--metrics-listen", "127.0.0.1:0"]
        cls.broker = Process("channel_broker", listen, cls.dir)
        broker = f"127.0.0.1:{cls.broker.ports['grpc_port']}"
        # robot-a's vehicle, publishing its pose and flight status.
        cls.simulator = Process("simulator", listen + ["--channel", broker, "--vehicles",
                                                       "robot-a"], cls.dir)
        cls.coordinator = Process("coordinator", listen, cls.dir)
        cls.coordinator_address = f"127.0.0.1:{cls.coordinator.ports['grpc_port']}"
        cls.system = Process("basic_quadrotor_behaviors",
                             listen + ["--robot-id", "robot-a", "--coordinator",
                                       cls.coordinator_address], cls.dir)
        cls.broker_address = broker
        cls.recordings = os.path.join(cls.dir, "recordings")
        os.makedirs(cls.recordings)
        cls.console = Process("console", ["--listen", "127.0.0.1:0", "--coordinator",
                                          cls.coordinator_address, "--channel", broker,
                                          "--recordings-dir", cls.recordings,
                                          "--world", os.path.join(REPO, "simulator", "worlds",
                                                                  "rooms.yaml")], cls.dir)
        cls.port = int(cls.console.ports["http_port"])

    @classmethod
    def tearDownClass(cls):
        for process in (cls.console, cls.system, cls.coordinator, cls.simulator, cls.broker):
            process.stop()
        shutil.rmtree(cls.dir, ignore_errors=True)

    def request(self, method, path, body=None, headers=None):
        connection = http.client.HTTPConnection("127.0.0.1", self.port, timeout=WAIT_S)
        connection.request(method, path, body=body, headers=headers or {})
        response = connection.getresponse()
        data = response.read()
        connection.close()
        self.last_encoding = response.getheader("Content-Encoding")
        return response.status, response.getheader("Content-Type"), data

    def call(self, name, request):
        # As a browser asks: a reply comes uncompressed all the same (brotli
        # at the library's quality 11 cost the console tens of ms a reply).
        status, content_type, data = self.request(
            "POST", f"/api/coordinator/{name}", json.dumps(request),
            {"Content-Type": "application/json", "Accept-Encoding": "gzip, deflate, br"})
        self.assertEqual(content_type, "application/json; charset=utf-8")
        self.assertIsNone(self.last_encoding, f"{name}'s reply came encoded")
        return status, json.loads(data)

    def activate(self, behavior, parameters):
        ctl = os.path.join(BUILD_DIR, "bin", "behaviorctl")
        subprocess.run([ctl, "--coordinator", self.coordinator_address, "--robot", "robot-a",
                        "activate", behavior, json.dumps(parameters)], check=True,
                       stdout=subprocess.DEVNULL, timeout=WAIT_S)

    def wait_for_system(self):
        deadline = time.monotonic() + WAIT_S
        while time.monotonic() < deadline:
            status, reply = self.call("ListSystems", {})
            if status == 200 and any(s["state"] == "SYSTEM_STATE_UP"
                                     for s in reply["systems"]):
                return reply
            time.sleep(0.1)
        self.fail(f"the system never came up: {reply}")

    def test_1_the_page_and_its_scripts_are_served(self):
        status, content_type, page = self.request("GET", "/")
        self.assertEqual(status, 200)
        self.assertTrue(content_type.startswith("text/html"), content_type)
        self.assertIn(b"<title>behaviorlib console</title>", page)
        for script in (b"console.js", b"console.css"):
            self.assertIn(script, page)
            status, _, _ = self.request("GET", "/" + script.decode())
            self.assertEqual(status, 200, script)
        status, _, _ = self.request("GET", "/../CMakeLists.txt")
        self.assertNotEqual(status, 200)

    def test_2_list_systems_is_the_coordinators_reply(self):
        reply = self.wait_for_system()
        (system,) = reply["systems"]
        self.assertEqual(system["robot_id"], "robot-a")
        self.assertEqual(system["system"], "basic_quadrotor_behaviors")
        status, behaviors = self.call("ListBehaviors", {"robot_id": "robot-a"})
        self.assertEqual(status, 200)
        self.assertIn("WAIT", [b["description"]["name"] for b in behaviors["behaviors"]])

    def test_3_the_feed_carries_a_behaviors_life_with_its_cause(self):
        self.wait_for_system()
        feed = EventFeed(self.port)
        try:
            self.activate("WAIT", {"duration_s": 0.05})
            seen = feed.until(finished("WAIT", 0.05))
        finally:
            feed.close()
        events = [data["behavior_event"] for _, event, data in seen
                  if event == "fleet" and "behavior_event" in data]
        last = events[-1]
        self.assertEqual(last["finished"]["cause"], "TERMINATION_CAUSE_GOAL_ACHIEVED")
        activations = [e for e in events if "activated" in e and
                       e["activation_id"] == last["activation_id"]]
        self.assertEqual(len(activations), 1, events)
        # Ids increase. (Not one by one: a state, a vehicle's pose, keeps only
        # its latest message, so the replay skips the ids it replaced.)
        ids = [message[0] for message in seen]
        self.assertEqual(ids, sorted(set(ids)))

    def test_4_a_browser_that_reconnects_resumes_after_its_last_event(self):
        self.wait_for_system()
        feed = EventFeed(self.port)
        try:
            self.activate("WAIT", {"duration_s": 0.06})
            seen = feed.until(finished("WAIT", 0.06))
        finally:
            feed.close()
        middle = seen[len(seen) // 2][0]
        last = seen[-1][0]
        # Every event after `middle` comes again, in order; states (vehicle
        # samples) only with their latest message.
        missed = [m[0] for m in seen if m[0] > middle and m[1] in ("fleet", "mission")]
        again = EventFeed(self.port, last_event_id=middle)
        resumed = []
        try:
            while not resumed or resumed[-1][0] < last:
                resumed.append(again.next())
        finally:
            again.close()
        self.assertGreater(resumed[0][0], middle)
        self.assertEqual([m[0] for m in resumed if m[0] <= last and m[1] in ("fleet", "mission")],
                         missed)
        self.assertTrue(missed, seen)

    def test_5_a_mission_started_through_the_gateway_is_followed_to_its_end(self):
        self.wait_for_system()
        feed = EventFeed(self.port)
        try:
            status, reply = self.call("StartMission", {
                "text": "name: console-test\nrobot: robot-a\nsteps:\n"
                        "  - behavior: WAIT\n    parameters: {duration_s: 0.05}\n"
                        "  - behavior: WAIT\n    parameters: {duration_s: 0.05}\n",
                "mission_id": "console-mission"})
            self.assertEqual(status, 200, reply)
            seen = feed.until(lambda event, data: event == "mission" and
                              data["mission_id"] == "console-mission" and
                              data["state"] == "MISSION_STATE_SUCCEEDED")
        finally:
            feed.close()
        final = seen[-1][2]
        self.assertEqual(len(final["steps"]), 2, final)

    def test_6_refusals_are_their_http_status_with_the_rpc_status(self):
        status, body = self.call("Kill", {"robot_id": "robot-a", "confirm": True})
        self.assertEqual(status, 404)
        self.assertIn("Coordinator.Kill", body["message"])
        status, content_type, data = self.request(
            "POST", "/api/coordinator/ListSystems", "{not json",
            {"Content-Type": "application/json"})
        self.assertEqual(status, 400)
        body = json.loads(data)
        self.assertEqual(body["code"], 3)  # INVALID_ARGUMENT
        self.assertEqual(body["details"][0]["reason"], "INVALID_REQUEST")
        status, body = self.call("StartMission", {
            "text": "name: bad\nrobot: robot-a\nsteps:\n  - behavior: FLY_TO_THE_MOON\n"})
        self.assertEqual(status, 400, body)
        reasons = [d.get("reason") for d in body["details"]]
        self.assertIn("MISSION_INVALID", reasons, body)
        violations = [v for d in body["details"] for v in d.get("field_violations", [])]
        self.assertTrue(violations, body)
        # CheckMission: the same problem as data, with its line, in an OK reply.
        status, body = self.call("CheckMission", {
            "text": "name: bad\nrobot: robot-a\nsteps:\n  - behavior: FLY_TO_THE_MOON\n"})
        self.assertEqual(status, 200, body)
        self.assertEqual(len(body["problems"]), 1, body)
        self.assertEqual(body["problems"][0]["line"], 4, body)
        self.assertEqual(body["problems"][0]["field"], "steps[0].behavior", body)
        status, body = self.call("GetMission", {"mission_id": "no-such-mission"})
        self.assertEqual(status, 404)
        self.assertEqual(body["details"][0]["reason"], "MISSION_NOT_FOUND")

    def test_6b_the_vehicles_pose_and_flight_status_come_from_the_channel(self):
        self.wait_for_system()
        feed = EventFeed(self.port)
        seen = {}
        try:
            def vehicle(event, data):
                if event == "vehicle":
                    assert "sample" in data, data
                    seen[data["topic"]] = data["sample"]
                return {"robots/robot-a/ground_truth/pose",
                        "robots/robot-a/flight_state"} <= set(seen)
            feed.until(vehicle)
        finally:
            feed.close()
        status = seen["robots/robot-a/flight_state"]
        self.assertTrue(status["@type"].endswith("behaviorlib.v1.FlightStatus"), status)
        self.assertEqual(status["state"], "FLIGHT_STATE_LANDED")
        self.assertGreater(status["battery_ratio"], 0.5)
        pose = seen["robots/robot-a/ground_truth/pose"]
        self.assertEqual(pose["header"]["robot_id"], "robot-a")
        self.assertIn("position_m", pose["pose"])

    def test_6c_the_maps_world_is_the_world_files(self):
        status, content_type, data = self.request("GET", "/api/world")
        self.assertEqual(status, 200)
        self.assertEqual(content_type, "application/json; charset=utf-8")
        world = json.loads(data)
        # The rooms' walls stand on the floor (their lintels above the doors
        # do not).
        walls = [b for b in world["boxes"] if b["kind"] == "wall" and
                 b["center_m"]["z"] - b["size_m"]["z"] / 2 < 0.01]
        self.assertGreater(len(walls), 4, world)
        self.assertTrue(all(w["size_m"]["z"] > 1.0 for w in walls), walls)
        # A console without --world has an empty one.
        other = Process("console", ["--listen", "127.0.0.1:0", "--coordinator",
                                    self.coordinator_address], self.dir, tag="console-no-world")
        try:
            connection = http.client.HTTPConnection(
                "127.0.0.1", int(other.ports["http_port"]), timeout=WAIT_S)
            connection.request("GET", "/api/world")
            reply = connection.getresponse()
            body = json.loads(reply.read())
            connection.close()
        finally:
            self.assertEqual(other.stop(), 0)
        self.assertEqual(reply.status, 200)
        self.assertEqual(body, {"boxes": [], "markers": []})

    def test_6d_beliefs_come_with_their_latest_value(self):
        ctl = os.path.join(BUILD_DIR, "bin", "behaviorctl")
        marker = {"text": "AC-001", "position_m": {"x": 1.5, "y": -2.0, "z": 1.0}}
        subprocess.run([ctl, "--coordinator", self.coordinator_address, "belief", "set",
                        "robot-a/markers/AC-001", json.dumps(marker)], check=True,
                       stdout=subprocess.DEVNULL, timeout=WAIT_S)
        feed = EventFeed(self.port)
        try:
            seen = feed.until(lambda event, data: event == "belief" and
                              data["key"] == "robot-a/markers/AC-001")
        finally:
            feed.close()
        belief = seen[-1][2]
        self.assertEqual(belief["value"]["position_m"]["x"], 1.5)
        self.assertFalse(belief["deleted"])

    def test_6e_a_recording_opens_as_the_feeds_messages(self):
        self.wait_for_system()
        ctl = os.path.join(BUILD_DIR, "bin", "behaviorctl")
        path = os.path.join(self.recordings, "short.mcap")
        recorder = subprocess.Popen([ctl, "--coordinator", self.coordinator_address,
                                     "--channel", self.broker_address, "record", path],
                                    stdout=subprocess.PIPE, text=True)
        try:
            # The recorder creates its file before it follows the fleet
            # (slower to start in a sanitizer build than the console's first
            # read of it).
            deadline = time.monotonic() + WAIT_S
            while not os.path.exists(path):
                self.assertIsNone(recorder.poll(), "the recorder stopped")
                self.assertLess(time.monotonic(), deadline, "the recorder made no file")
                time.sleep(0.05)
            self.activate("WAIT", {"duration_s": 0.07})
            # Recorded once the recorder saw the activation's end: the
            # console reads a recording that is still being written.
            deadline = time.monotonic() + WAIT_S
            while True:
                status, _, body = self.request("GET", "/api/recordings/short.mcap")
                self.assertEqual(status, 200, body)
                recording = json.loads(body)
                if any(m["event"] == "fleet" and finished("WAIT", 0.07)("fleet", m["data"])
                       for m in recording["messages"]):
                    break
                self.assertLess(time.monotonic(), deadline, recording["messages"][-5:])
                time.sleep(0.2)
        finally:
            recorder.terminate()
            out, _ = recorder.communicate(timeout=WAIT_S)
        self.assertEqual(recorder.returncode, 0)
        self.assertGreater(json.loads(out)["messages"]["coordinator/events"], 0)
        status, _, body = self.request("GET", "/api/recordings")
        self.assertEqual(status, 200)
        self.assertIn({"name": "short.mcap", "bytes": os.path.getsize(path)},
                      json.loads(body)["recordings"])
        status, _, body = self.request("GET", "/api/recordings/short.mcap")
        recording = json.loads(body)
        self.assertTrue(recording["complete"])
        times = [m["t_ms"] for m in recording["messages"]]
        self.assertEqual(times[0], 0)
        kinds = {m["event"] for m in recording["messages"]}
        self.assertLessEqual({"fleet", "vehicle"}, kinds)
        # Samples in the live feed's shape, thinned to 10 per second.
        poses = [m for m in recording["messages"] if m["event"] == "vehicle" and
                 m["data"]["topic"] == "robots/robot-a/ground_truth/pose"]
        self.assertTrue(poses)
        self.assertIn("position_m", poses[0]["data"]["sample"]["pose"])
        gaps = [b["t_ms"] - a["t_ms"] for a, b in zip(poses, poses[1:])]
        self.assertTrue(all(gap >= 100 for gap in gaps), gaps)
        # Refused: a name that is not a recording's, a missing one, a file
        # that is not MCAP; the process keeps serving.
        status, _, _ = self.request("GET", "/api/recordings/..%2Fconsole.log")
        self.assertEqual(status, 404)  # No route: '/' is not in a name.
        for name, code in (("..console.mcap.log", 400), ("missing.mcap", 404),
                           ("notes.txt", 400)):
            status, content_type, body = self.request("GET", f"/api/recordings/{name}")
            self.assertEqual((status, content_type), (code, "application/json; charset=utf-8"),
                             (name, body))
            self.assertIn("message", json.loads(body))
        with open(os.path.join(self.recordings, "text.mcap"), "w") as f:
            f.write("not a recording")
        status, _, body = self.request("GET", "/api/recordings/text.mcap")
        self.assertEqual(status, 400, body)
        self.assertIn("not an MCAP file", json.loads(body)["message"])

    def test_7_a_coordinator_that_goes_away_is_reported(self):
        feed = EventFeed(self.port)
        try:
            self.assertEqual(self.coordinator.stop(), 0)
            seen = feed.until(lambda event, data: event == "gateway" and
                              not data["coordinator_up"])
        finally:
            feed.close()
        self.assertTrue(seen[-1][2]["message"], seen[-1])
        status, body = self.call("ListSystems", {})
        self.assertEqual(status, 503, body)


def main():
    global BUILD_DIR
    parser = argparse.ArgumentParser()
    parser.add_argument("--build-dir", default=BUILD_DIR)
    args, rest = parser.parse_known_args()
    BUILD_DIR = os.path.abspath(args.build_dir)
    unittest.main(argv=[sys.argv[0], *rest], verbosity=2)


if __name__ == "__main__":
    main()
