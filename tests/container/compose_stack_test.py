"""The compose deployment in real containers, on a real engine: the stack of
deploy/compose/docker-compose.yml (with docker-compose.offline.yml, which
builds Prometheus's image from Debian's package where no registry answers),
started with docker-compose from the image behaviorlib:latest that
scripts/container-tests.sh built as the README says, then flown from the
host over mutual TLS. In order, each check able to fail:

1. every service becomes healthy within its start period, as `docker
   inspect` reports it (its first passing health probe);
2. the hardening holds while everything works: every behaviorlib container
   runs as uid 10001 with a read-only root and no capabilities, the image
   has no compiler, a plaintext client to a published port is refused;
3. the demo mission SUCCEEDS through the published coordinator port
   (behaviorctl on the host, the operator's certificate); the console
   answers over HTTPS, acts with an operator's token and refuses without;
   Prometheus has every target up and its rules evaluated;
4. kill -9 of a behavior system's process mid-mission (FOLLOW_PATH flying):
   Docker restarts it, the safety rule lands the vehicle, the system
   registers again with a new incarnation, and the fleet's event stream
   has no gap and no duplicate;
5. kill -9 of the coordinator mid-mission: Docker restarts it and the
   mission resumes from the journal on the volume and succeeds;
6. `docker-compose down`, then `up` with the volume kept: the finished
   missions are still listed; `down -v` drops them;
7. the two-vehicle file (docker-compose.drone2.yml) flies the swarm
   mission on both vehicles, and both missions succeed.

The stack runs in the deterministic mode (SIMULATOR_TIME_SCALE=max and the
behavior systems following the simulator's time grants), so that a busy
machine slows the flight instead of failing it. The project's name, the
published ports and the certificates are the test's own (a deployment of
the user's on the same engine is left alone).

Exits 77 (skipped) when no engine answers or behaviorlib:latest is absent:
scripts/container-tests.sh makes both.

    /usr/bin/python3 tests/container/compose_stack_test.py --build-dir build
"""

import argparse
import hashlib
import http.client
import json
import os
import secrets
import shutil
import socket
import ssl
import subprocess
import sys
import tempfile
import threading
import time
import unittest
from datetime import datetime

import grpc
import yaml

REPO = os.path.abspath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", ".."))
sys.path.insert(0, os.path.join(REPO, "deploy", "local"))
import demo  # noqa: E402
import reflection_client as rc  # noqa: E402
import rpc  # noqa: E402

COMPOSE_DIR = os.path.join(REPO, "deploy", "compose")
BASE_FILE = os.path.join(COMPOSE_DIR, "docker-compose.yml")
OFFLINE_FILE = os.path.join(COMPOSE_DIR, "docker-compose.offline.yml")
DRONE2_FILE = os.path.join(COMPOSE_DIR, "docker-compose.drone2.yml")
DEMO_MISSION = os.path.join(REPO, "deploy", "missions", "demo.yaml")
SWARM_MISSION = os.path.join(REPO, "deploy", "missions", "swarm_member.yaml")
BUILD_DIR = os.path.join(REPO, "build")
PROJECT = "behaviorlibtest"
IMAGE = "behaviorlib:latest"
SKIP = 77
UID = 10001
BEHAVIOR_SYSTEMS_PER_VEHICLE = 9
# The systems register with the coordinator from their own containers.
MOTION_SYSTEM = "quadrotor_motion_with_pid_control"
MOTION_SERVICE = "drone1-quadrotor-motion-with-pid-control"
# Upper bounds on waits for what must follow; none is a measurement.
HEALTHY_TIMEOUT_S = 240
MISSION_TIMEOUT_S = 300


def log(text):
    print(f"[{time.strftime('%H:%M:%S')}] {text}", flush=True)


def run(argv, timeout=300, check=True, env=None):
    result = subprocess.run(argv, capture_output=True, text=True, timeout=timeout, env=env)
    if check and result.returncode != 0:
        raise AssertionError(f"{' '.join(argv)} exited {result.returncode}:\n"
                             f"{result.stdout[-3000:]}\n{result.stderr[-3000:]}")
    return result


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def parse_time(text):
    """Docker's RFC 3339 time with nanoseconds, as seconds since the epoch."""
    text = text.rstrip("Z")
    whole, _, fraction = text.partition(".")
    seconds = datetime.fromisoformat(whole + "+00:00").timestamp()
    return seconds + (float("0." + fraction[:9]) if fraction else 0.0)


def wait_for(predicate, timeout_s, what, interval_s=0.5):
    deadline = time.monotonic() + timeout_s
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")
        time.sleep(interval_s)


def engine_answers():
    return shutil.which("docker") is not None and subprocess.run(
        ["docker", "version"], capture_output=True).returncode == 0


class Stack:
    """The test's compose project: its environment, files and containers."""

    def __init__(self, work_dir):
        self.certs = os.path.join(work_dir, "certs")
        run([os.path.join(REPO, "scripts", "make-dev-certs.sh"), "--readable-keys",
             "--out", self.certs])
        # An operator's token, added to the coordinator's policy by its hash
        # as the policy file's comment says.
        self.token = secrets.token_urlsafe(24)
        with open(os.path.join(REPO, "deploy", "config", "access_policy.yaml")) as f:
            policy = f.read()
        digest = hashlib.sha256(self.token.encode()).hexdigest()
        policy = policy.replace(
            "identities:\n",
            "identities:\n  - token_sha256: " + digest +
            "\n    name: operator-container-test\n    roles: [viewer, operator, safety]\n", 1)
        self.policy = os.path.join(work_dir, "access_policy.yaml")
        with open(self.policy, "w") as f:
            f.write(policy)
        os.chmod(self.policy, 0o644)
        self.ports = {name: free_port() for name in
                      ("COORDINATOR_HOST_PORT", "CONSOLE_HOST_PORT", "PROMETHEUS_HOST_PORT",
                       "GRAFANA_HOST_PORT")}
        self.env = dict(os.environ)
        self.env.update({
            "COMPOSE_PROJECT_NAME": PROJECT,
            "BEHAVIORLIB_CERTS_DIR": self.certs,
            "BEHAVIORLIB_ACCESS_POLICY": self.policy,
            "GRAFANA_ADMIN_PASSWORD": secrets.token_urlsafe(18),
            # The deterministic mode (decision 18).
            "SIMULATOR_TIME_SCALE": "max",
            "BEHAVIOR_SYSTEM_FOLLOW_TIME": "simulator:50070",
            "COORDINATOR_GRACE_PERIOD_S": "5",
            **{k: str(v) for k, v in self.ports.items()},
        })
        self.files = [BASE_FILE, OFFLINE_FILE]
        self.vehicles = 1

    def with_drone2(self, drone2=True):
        self.files = [BASE_FILE, OFFLINE_FILE] + ([DRONE2_FILE] if drone2 else [])
        self.vehicles = 2 if drone2 else 1

    def compose(self, *args, timeout=600, check=True):
        argv = ["docker-compose"]
        for path in self.files:
            argv += ["-f", path]
        return run(argv + list(args), timeout=timeout, check=check, env=self.env)

    def services(self):
        """The services to start: every one of the files but Grafana, unless
        its image is in the engine (one `config` call)."""
        config = yaml.safe_load(self.compose("config").stdout)
        names = list(config["services"])
        grafana = config["services"].get("grafana")
        self.grafana = grafana is not None and subprocess.run(
            ["docker", "image", "inspect", grafana["image"]], capture_output=True).returncode == 0
        if grafana is not None and not self.grafana:
            names.remove("grafana")
        return names

    def up(self):
        services = self.services()
        if not self.grafana:
            log("grafana left out: its image is not in the engine (no registry, and Debian "
                "does not package Grafana)")
        self.env["SIMULATOR_MIN_FOLLOWERS"] = str(BEHAVIOR_SYSTEMS_PER_VEHICLE * self.vehicles)
        started = time.monotonic()
        self.compose("up", "-d", *services)
        log(f"up -d returned after {time.monotonic() - started:.1f} s ({len(services)} services)")
        return services

    def down(self, volumes=False):
        self.compose("down", "--remove-orphans", *(["-v"] if volumes else []), timeout=300)

    def container(self, service):
        """The id of the service's one container (by Compose's labels: one
        docker call, where `docker-compose ps` starts a Python program)."""
        ids = run(["docker", "ps", "-a", "-q", "--no-trunc",
                   "--filter", f"label=com.docker.compose.project={PROJECT}",
                   "--filter", f"label=com.docker.compose.service={service}"]).stdout.split()
        assert len(ids) == 1, (service, ids)
        return ids[0]

    def inspect(self, container):
        return json.loads(run(["docker", "inspect", container]).stdout)[0]

    def behaviorlib_services(self, services):
        return [s for s in services if s not in ("prometheus", "grafana")]

    def address(self, name):
        return f"127.0.0.1:{self.ports[name]}"

    def behaviorctl(self, *args, timeout=MISSION_TIMEOUT_S):
        return run([os.path.join(BUILD_DIR, "bin", "behaviorctl"),
                    "--tls-cert", os.path.join(self.certs, "operator.pem"),
                    "--tls-key", os.path.join(self.certs, "operator.key"),
                    "--tls-ca", os.path.join(self.certs, "ca.pem"),
                    "--coordinator", self.address("COORDINATOR_HOST_PORT"), *args],
                   timeout=timeout, check=False)

    def coordinator(self):
        rc.use_tls(os.path.join(self.certs, "operator.pem"),
                   os.path.join(self.certs, "operator.key"), os.path.join(self.certs, "ca.pem"))
        return rpc.Client(self.address("COORDINATOR_HOST_PORT"), [demo.COORDINATOR])

    def console(self, method, path, body=None, token=None):
        context = ssl.create_default_context(cafile=os.path.join(self.certs, "ca.pem"))
        connection = http.client.HTTPSConnection("127.0.0.1", self.ports["CONSOLE_HOST_PORT"],
                                                 timeout=30, context=context)
        headers = {"Content-Type": "application/json"}
        if token is not None:
            headers["Authorization"] = "Bearer " + token
        try:
            connection.request(method, path, None if body is None else json.dumps(body), headers)
            reply = connection.getresponse()
            return reply.status, reply.read()
        finally:
            connection.close()

    def console_latest(self, wanted, timeout_s=10):
        """The console's /api/events from a new connection: the latest value
        of each state the hub keeps, then new ones; returns the first
        (event, data) for which wanted(event, data) holds."""
        context = ssl.create_default_context(cafile=os.path.join(self.certs, "ca.pem"))
        connection = http.client.HTTPSConnection("127.0.0.1", self.ports["CONSOLE_HOST_PORT"],
                                                 timeout=timeout_s, context=context)
        try:
            connection.request("GET", "/api/events")
            reply = connection.getresponse()
            event, deadline = None, time.monotonic() + timeout_s
            while time.monotonic() < deadline:
                line = reply.fp.readline().decode().rstrip("\n")
                if line.startswith("event: "):
                    event = line[len("event: "):]
                elif line.startswith("data: "):
                    data = json.loads(line[len("data: "):])
                    if wanted(event, data):
                        return event, data
            return None
        except (socket.timeout, TimeoutError):
            return None
        finally:
            connection.close()

    def prometheus(self, path):
        connection = http.client.HTTPConnection("127.0.0.1", self.ports["PROMETHEUS_HOST_PORT"],
                                                timeout=10)
        try:
            connection.request("GET", path)
            return json.loads(connection.getresponse().read())
        finally:
            connection.close()


class FleetEvents:
    """The coordinator's WatchEvents from seq 0, on a thread: every event
    kept, so that gaps and duplicates can be counted. A stream broken by a
    coordinator restart is resumed from the last seq seen."""

    def __init__(self, stack):
        self._stack = stack
        self._lock = threading.Lock()
        self.events = []
        self.starts = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._call = None

    def start(self):
        self._thread.start()

    def _run(self):
        since, incarnation = 0, ""
        while not self._stop.is_set():
            client = None
            try:
                client = self._stack.coordinator()
                self._call = client.stream(demo.COORDINATOR, "WatchEvents",
                                           {"since_seq": since, "incarnation": incarnation},
                                           timeout=3600)
                for reply in self._call:
                    kind = reply.WhichOneof("kind")
                    if kind == "start":
                        with self._lock:
                            self.starts.append(rpc.to_dict(reply.start))
                    elif kind == "event":
                        event = rpc.to_dict(reply.event)
                        with self._lock:
                            self.events.append(event)
                        since = int(event.get("seq", 0))
                        incarnation = event.get("incarnation", "")
            except grpc.RpcError:
                time.sleep(0.5)
            finally:
                if client is not None:
                    client.close()

    def stop(self):
        self._stop.set()
        if self._call is not None:
            self._call.cancel()
        self._thread.join(timeout=10)

    def snapshot(self):
        with self._lock:
            return list(self.events)


def check_no_gap_no_duplicate(test, events):
    """The coordinator's seq numbers of one incarnation increase by one; no
    behavior event (a system incarnation's seq) arrives twice, and each
    system incarnation's events are consecutive."""
    by_incarnation = {}
    for e in events:
        by_incarnation.setdefault(e["incarnation"], []).append(int(e["seq"]))
    for incarnation, seqs in by_incarnation.items():
        test.assertEqual(seqs, list(range(seqs[0], seqs[0] + len(seqs))),
                         f"coordinator incarnation {incarnation}: a gap or a duplicate")
    seen, per_system = set(), {}
    for e in events:
        b = e.get("behavior_event")
        if not b or e.get("synthesized"):
            continue
        key = (b["incarnation"], int(b["seq"]))
        test.assertNotIn(key, seen, f"behavior event {key} delivered twice")
        seen.add(key)
        per_system.setdefault(b["incarnation"], []).append(int(b["seq"]))
    for incarnation, seqs in per_system.items():
        ordered = sorted(seqs)
        test.assertEqual(ordered, list(range(ordered[0], ordered[0] + len(ordered))),
                         f"system incarnation {incarnation}: a gap in its events")
    return len(seen)


class ComposeStackTest(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        cls.work = tempfile.mkdtemp(prefix="compose-stack-test-")
        cls.stack = Stack(cls.work)
        # What a failed earlier run may have left.
        cls.stack.with_drone2()
        cls.stack.down(volumes=True)
        cls.stack.with_drone2(False)
        cls.failed_probes = {}  # service: {(seconds after start, exit code, output)}
        cls.up_wall = time.time()
        try:
            cls.services = cls.stack.up()
        except BaseException:
            # unittest runs no tearDownClass after a failed setUpClass.
            cls.tearDownClass()
            raise

    @classmethod
    def tearDownClass(cls):
        try:
            if os.environ.get("BEHAVIORLIB_KEEP_STACK") != "1":
                # Every file, so that drone2's containers go too.
                cls.stack.with_drone2()
                cls.stack.down(volumes=True)
        finally:
            shutil.rmtree(cls.work, ignore_errors=True)

    def wait_healthy(self, services, timeout_s=HEALTHY_TIMEOUT_S):
        """{service: seconds from its container's start to its first passing
        probe}, once every one is healthy; fails naming those that are not."""
        containers = {s: self.stack.container(s) for s in services}
        first_pass = {}

        def all_healthy():
            for service, container in containers.items():
                if service in first_pass:
                    continue
                state = self.stack.inspect(container)["State"]
                health = state.get("Health", {})
                for probe in health.get("Log", []):
                    if probe.get("ExitCode") != 0:
                        self.failed_probes.setdefault(service, set()).add(
                            (round(parse_time(probe["Start"]) - parse_time(state["StartedAt"]),
                              1), probe.get("ExitCode"), probe.get("Output", "")[:200]))
                if health.get("Status") == "healthy":
                    passed = [parse_time(p["Start"]) for p in health.get("Log", [])
                              if p.get("ExitCode") == 0]
                    first_pass[service] = min(passed) - parse_time(state["StartedAt"])
            return len(first_pass) == len(containers)

        try:
            wait_for(all_healthy, timeout_s, "every service healthy", interval_s=1.0)
        except AssertionError:
            unhealthy = sorted(set(containers) - set(first_pass))
            for service in unhealthy:
                print(self.stack.compose("logs", "--tail", "30", service, check=False).stdout)
            raise AssertionError(f"not healthy after {timeout_s} s: {unhealthy}")
        return first_pass

    def start_period_s(self, service):
        health = self.stack.inspect(self.stack.container(service))["Config"]["Healthcheck"]
        return health["StartPeriod"] / 1e9, health["Interval"] / 1e9

    # -- 1 -------------------------------------------------------------------------
    def test_1_every_service_healthy_within_its_start_period(self):
        healthy = self.wait_healthy(self.services)
        log(f"healthy {time.time() - self.up_wall:.1f} s after up: " +
            ", ".join(f"{s} {t:.1f}" for s, t in sorted(healthy.items())))
        for service, seconds in healthy.items():
            start_period, _ = self.start_period_s(service)
            with self.subTest(service=service):
                self.assertLessEqual(seconds, start_period,
                                     f"{service}: first passing probe {seconds:.1f} s after its "
                                     f"start, its start period is {start_period:.0f} s; the "
                                     f"failed probes before: "
                                     f"{sorted(self.failed_probes.get(service, []))}")

    # -- 2 -------------------------------------------------------------------------
    def test_2_hardening(self):
        self.wait_healthy(self.services)
        for service in self.stack.behaviorlib_services(self.services):
            container = self.stack.container(service)
            info = self.stack.inspect(container)
            with self.subTest(service=service):
                self.assertTrue(info["HostConfig"]["ReadonlyRootfs"], "root file system writable")
                self.assertEqual(info["HostConfig"]["CapDrop"], ["ALL"])
                self.assertFalse(info["HostConfig"]["Privileged"])
                status = run(["docker", "exec", container, "cat", "/proc/1/status"]).stdout
                fields = dict(line.split(":\t", 1) for line in status.splitlines()
                              if ":\t" in line)
                self.assertEqual(fields["Uid"].split()[:2], [str(UID)] * 2, "not uid 10001")
                for cap in ("CapEff", "CapPrm", "CapBnd"):
                    self.assertEqual(int(fields[cap], 16), 0, f"{cap} {fields[cap]}")
                write = run(["docker", "exec", container, "sh", "-c", "echo x > /opt/x"],
                            check=False)
                self.assertNotEqual(write.returncode, 0, "wrote into the image's files")
                self.assertIn("Read-only file system", write.stderr)
        # No compiler or toolchain in the runtime image.
        found = run(["docker", "run", "--rm", "--entrypoint", "sh", IMAGE, "-c",
                     "for c in cc gcc g++ c++ clang ld as make cmake; do command -v $c; done; "
                     "ls /usr/lib/gcc 2>/dev/null; true"]).stdout.split()
        self.assertEqual(found, [], "a compiler in the runtime image")
        # Plaintext to the published gRPC port: refused (no TLS handshake).
        with self.assertRaises(grpc.RpcError) as refused:
            rpc.health_status(self.stack.address("COORDINATOR_HOST_PORT"), timeout=5.0)
        self.assertEqual(refused.exception.code(), grpc.StatusCode.UNAVAILABLE)
        # Plain HTTP to the console's HTTPS port: no page.
        connection = http.client.HTTPConnection("127.0.0.1",
                                                self.stack.ports["CONSOLE_HOST_PORT"], timeout=5)
        try:
            connection.request("GET", "/api/world")
            status = connection.getresponse().status
        except (ConnectionError, http.client.HTTPException, OSError):
            status = None
        finally:
            connection.close()
        self.assertNotEqual(status, 200, "the console answered plain HTTP")

    # -- 3 -------------------------------------------------------------------------
    def test_3_demo_mission_console_and_prometheus(self):
        self.wait_healthy(self.services)
        started = time.monotonic()
        flown = self.stack.behaviorctl("mission", "run", DEMO_MISSION, "--mission_id=demo-1")
        log(f"demo mission: exit {flown.returncode} after {time.monotonic() - started:.1f} s")
        self.assertEqual(flown.returncode, 0, flown.stdout + flown.stderr)
        self.assertIn("SUCCEEDED", flown.stdout)

        # The console, over HTTPS against the deployment's CA.
        status, body = self.stack.console("POST", "/api/coordinator/ListMissions", {})
        self.assertEqual(status, 200, body)
        self.assertIn("demo-1", body.decode())
        status, body = self.stack.console("POST", "/api/coordinator/PauseMission",
                                          {"mission_id": "no-such-mission"})
        self.assertEqual(status, 403, body)
        self.assertIn("needs the role operator", json.loads(body).get("message", ""))
        status, body = self.stack.console("POST", "/api/coordinator/PauseMission",
                                          {"mission_id": "no-such-mission"},
                                          token=self.stack.token)
        self.assertEqual(status, 404, body)

        # Prometheus: every target up, every rule evaluated without error.
        def targets_up():
            active = self.stack.prometheus("/api/v1/targets")["data"]["activeTargets"]
            return active if active and all(t["health"] == "up" for t in active) else None

        try:
            active = wait_for(targets_up, 60, "every Prometheus target up", interval_s=2)
        except AssertionError:
            print(json.dumps(self.stack.prometheus("/api/v1/targets"), indent=1)[:4000])
            raise
        jobs = {t["labels"]["job"] for t in active}
        self.assertEqual(jobs, {"channel_broker", "simulator", "coordinator", "behavior_system",
                                "prometheus"})
        self.assertEqual(sum(t["labels"]["job"] == "behavior_system" for t in active),
                         BEHAVIOR_SYSTEMS_PER_VEHICLE)

        def rules_evaluated():
            groups = self.stack.prometheus("/api/v1/rules")["data"]["groups"]
            rules = [r for g in groups for r in g["rules"]]
            done = rules and all(r.get("lastEvaluation", "").startswith("2") and
                                 not r["lastEvaluation"].startswith("0001") for r in rules)
            return rules if done else None

        rules = wait_for(rules_evaluated, 60, "every rule evaluated", interval_s=2)
        self.assertTrue(all(r["health"] == "ok" for r in rules),
                        [(r["name"], r.get("lastError")) for r in rules if r["health"] != "ok"])
        log(f"prometheus: {len(active)} targets up, {len(rules)} rules ok")
        # The subscribers in the broker's IPC namespace read its shared-memory
        # rings: samples were written into rings.
        def ring_samples():
            result = self.stack.prometheus(
                "/api/v1/query?query=sum(behaviorlib_channel_shm_samples_total)")["data"]
            values = [float(r["value"][1]) for r in result["result"]]
            return values[0] if values and values[0] > 0 else None

        rings = wait_for(ring_samples, 60, "samples in the broker's shared-memory rings",
                         interval_s=2)
        log(f"shared-memory rings: {rings:.0f} samples written")

    # -- 4 -------------------------------------------------------------------------
    def flight_state(self):
        found = self.stack.console_latest(
            lambda event, data: event == "vehicle"
            and data.get("topic", "").endswith("drone1/flight_state"))
        return json.dumps(found[1]) if found else ""

    def test_4_behavior_system_killed_mid_mission(self):
        self.wait_healthy(self.services)
        coordinator = self.stack.coordinator()
        events = FleetEvents(self.stack)
        events.start()
        try:
            before = self.system(coordinator, "drone1", MOTION_SYSTEM)
            container = self.stack.container(MOTION_SERVICE)
            restarts = self.stack.inspect(container)["RestartCount"]
            mission = self.start_mission(coordinator, DEMO_MISSION, "drone1", "kill-system")
            wait_for(lambda: self.step_running(coordinator, "kill-system", "FOLLOW_PATH"), 120,
                     "FOLLOW_PATH running")
            state = self.flight_state()
            self.assertTrue("FLYING" in state or "HOVERING" in state, f"not airborne: {state}")
            pid = self.stack.inspect(container)["State"]["Pid"]
            log(f"kill -9 {MOTION_SERVICE} (host pid {pid})")
            os.kill(pid, 9)

            final = self.wait_mission_end(coordinator, mission)
            self.assertIn(final["state"], ("MISSION_STATE_ABORTED", "MISSION_STATE_FAILED"),
                          final)
            # Docker restarted it; it is healthy and registered again.
            wait_for(lambda: self.stack.inspect(container)["RestartCount"] == restarts + 1, 60,
                     "Docker's restart")
            self.wait_healthy([MOTION_SERVICE])

            def registered_again():
                system = self.system(coordinator, "drone1", MOTION_SYSTEM)
                return system if (system.get("state") == "SYSTEM_STATE_UP" and
                                  system.get("incarnation") != before["incarnation"]) else None

            wait_for(registered_again, 60, f"{MOTION_SYSTEM} registered again")
            # The safety rule landed the vehicle.
            wait_for(lambda: "LANDED" in self.flight_state(), 120, "the vehicle LANDED")
            self.assertIn("FLIGHT_STATE_LANDED", self.flight_state())
            coordinator_log = self.stack.compose("logs", "--no-color", "coordinator").stdout
            self.assertRegex(coordinator_log, r"coordinator: safety: drone1: .*hover, then land")
        finally:
            events.stop()
            coordinator.close()
        # The whole stream, replayed from seq 0 by a new subscriber, and the
        # one followed live: no gap, no duplicate, the same events.
        live = events.snapshot()
        replayed = self.replay_events()
        count = check_no_gap_no_duplicate(self, replayed)
        check_no_gap_no_duplicate(self, live)
        self.assertEqual([e["seq"] for e in live], [e["seq"] for e in replayed][:len(live)])
        log(f"kill of a behavior system: {count} behavior events, no gap, no duplicate")

    # -- 5 -------------------------------------------------------------------------
    def test_5_coordinator_killed_mission_resumes(self):
        self.wait_healthy(self.services)
        coordinator = self.stack.coordinator()
        wait_for(lambda: "LANDED" in self.flight_state(), 120, "the vehicle on the ground")
        container = self.stack.container("coordinator")
        restarts = self.stack.inspect(container)["RestartCount"]
        mission = self.start_mission(coordinator, DEMO_MISSION, "drone1", "kill-coordinator")
        wait_for(lambda: self.step_running(coordinator, mission, "FOLLOW_PATH"), 120,
                 "FOLLOW_PATH running")
        coordinator.close()
        pid = self.stack.inspect(container)["State"]["Pid"]
        log(f"kill -9 coordinator (host pid {pid})")
        os.kill(pid, 9)
        wait_for(lambda: self.stack.inspect(container)["RestartCount"] == restarts + 1, 60,
                 "Docker's restart of the coordinator")
        self.wait_healthy(["coordinator"])
        coordinator = wait_for(self.reconnect, 60, "the coordinator answering again")
        try:
            final = self.wait_mission_end(coordinator, mission)
            self.assertEqual(final["state"], "MISSION_STATE_SUCCEEDED", final)
        finally:
            coordinator.close()
        check_no_gap_no_duplicate(self, self.replay_events())

    # -- 6 -------------------------------------------------------------------------
    def test_6_down_up_keeps_the_journal_down_v_drops_it(self):
        coordinator = self.stack.coordinator()
        before = self.mission_ids(coordinator)
        coordinator.close()
        self.assertIn("demo-1", before)
        self.stack.down()
        self.stack.up()
        self.wait_healthy(self.services)
        coordinator = wait_for(self.reconnect, 60, "the coordinator")
        try:
            after = self.mission_ids(coordinator)
            self.assertEqual(after, before, "the missions after down and up")
            finished = coordinator.call(demo.COORDINATOR, "GetMission", {"mission_id": "demo-1"})
            self.assertEqual(finished["status"]["state"], "MISSION_STATE_SUCCEEDED")
        finally:
            coordinator.close()
        self.stack.down(volumes=True)
        self.stack.up()
        self.wait_healthy(self.services)
        coordinator = wait_for(self.reconnect, 60, "the coordinator")
        try:
            self.assertEqual(self.mission_ids(coordinator), [], "missions after down -v")
        finally:
            coordinator.close()

    # -- 7 -------------------------------------------------------------------------
    def test_7_two_vehicles_fly_the_swarm_mission(self):
        self.stack.down(volumes=True)
        self.stack.with_drone2()
        services = self.stack.up()
        self.wait_healthy(services)
        coordinator = self.stack.coordinator()
        try:
            missions = {robot: self.start_mission(coordinator, SWARM_MISSION, robot,
                                                  f"swarm-{robot}")
                        for robot in ("drone1", "drone2")}
            finals = {robot: self.wait_mission_end(coordinator, mission)
                      for robot, mission in missions.items()}
            for robot, final in finals.items():
                self.assertEqual(final["state"], "MISSION_STATE_SUCCEEDED", (robot, final))
            # Each vehicle's belief memory holds the other's position.
            for robot, other in (("drone1", "drone2"), ("drone2", "drone1")):
                beliefs = demo.list_beliefs(coordinator, f"{robot}/swarm/{other}/")
                self.assertTrue(beliefs, f"{robot} knows nothing of {other}")
        finally:
            coordinator.close()

    # -- helpers -------------------------------------------------------------------
    def reconnect(self):
        try:
            client = self.stack.coordinator()
            client.call(demo.COORDINATOR, "ListMissions", {})
            return client
        except (grpc.RpcError, rc.ReflectionError, OSError):
            return None

    def replay_events(self):
        coordinator = self.stack.coordinator()
        try:
            events = []
            for reply in coordinator.stream(demo.COORDINATOR, "WatchEvents", {"since_seq": 0},
                                            timeout=10):
                if reply.WhichOneof("kind") == "start":
                    start = rpc.to_dict(reply.start)
                    last = int(start.get("latest_seq", 0))
                    if last == 0:
                        break
                elif reply.WhichOneof("kind") == "event":
                    events.append(rpc.to_dict(reply.event))
                    if int(events[-1]["seq"]) >= last:
                        break
            return events
        finally:
            coordinator.close()

    def system(self, coordinator, robot, name):
        reply = coordinator.call(demo.COORDINATOR, "ListSystems", {"robot_id": robot})
        for system in reply.get("systems", []):
            if system.get("system") == name:
                return system
        return {}

    def start_mission(self, coordinator, path, robot, mission_id):
        coordinator.call(demo.COORDINATOR, "StartMission",
                         demo.mission_request(path, robot, mission_id))
        return mission_id

    def step_running(self, coordinator, mission_id, behavior):
        status = coordinator.call(demo.COORDINATOR, "GetMission",
                                  {"mission_id": mission_id})["status"]
        return any(s.get("behavior") == behavior and s.get("state") == "MISSION_STEP_STATE_RUNNING"
                   for s in status.get("steps", []))

    def wait_mission_end(self, coordinator, mission_id):
        def ended():
            status = coordinator.call(demo.COORDINATOR, "GetMission",
                                      {"mission_id": mission_id})["status"]
            return status if status.get("state") in demo.FINAL_MISSION_STATES else None

        return wait_for(ended, MISSION_TIMEOUT_S, f"mission {mission_id} ended", interval_s=1.0)

    def mission_ids(self, coordinator):
        reply = coordinator.call(demo.COORDINATOR, "ListMissions", {})
        return sorted(m.get("mission_id", "") for m in reply.get("missions", []))


def main():
    global BUILD_DIR
    parser = argparse.ArgumentParser()
    parser.add_argument("--build-dir", default=BUILD_DIR)
    args, rest = parser.parse_known_args()
    BUILD_DIR = os.path.abspath(args.build_dir)
    if not engine_answers():
        print("SKIPPED: no Docker engine answers (scripts/container-tests.sh starts one)")
        sys.exit(SKIP)
    if subprocess.run(["docker", "image", "inspect", IMAGE], capture_output=True).returncode:
        print(f"SKIPPED: {IMAGE} is not built (scripts/container-tests.sh builds it)")
        sys.exit(SKIP)
    unittest.main(argv=[sys.argv[0], *rest], verbosity=2, failfast=False)


if __name__ == "__main__":
    main()
