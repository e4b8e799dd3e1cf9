#!/usr/bin/python3
"""A fleet across hosts on one machine: a ground station, a simulation host
and one host per vehicle, each a network namespace with its own addresses,
joined by radio links that lag, drop packets and can be cut (decision 39).

    sudo deploy/fleet/fleet.py --build-dir build            # 3 vehicles fly the swarm mission
    sudo deploy/fleet/fleet.py --vehicles 4 --loss 0 --delay-ms 0 --keep   # until Ctrl-C
    sudo deploy/fleet/fleet.py --no-secure       # the data engine in plaintext

Hosts and what runs on them (every port fixed: each host has its own):

  ground   10.77.0.1   nats-server (the hub), channel_broker (linked),
                       coordinator, console (8090), flight recorder
                       (behaviorctl record)
  sim      10.78.0.1   simulator, standing in for every vehicle's autopilot and
           10.77.0.2   sensors, publishing each vehicle's topics to that
                       vehicle's broker over its onboard link (the "bus"), and
                       the clock to its own linked broker
  droneK   10.77.0.1K  channel_broker (linked: a client of the hub, through the
           10.78.0.1K  radio), the behavior systems, radio_relay.py

The data engine is secure by default (--no-secure: plaintext): the run
directory gets a CA and a certificate for the hub, each vehicle's broker and
the ground's and the simulation host's brokers (scripts/make-dev-certs.sh);
the hub takes only mutual TLS, maps each certificate to a NATS user and holds
it to that user's permissions: a vehicle publishes only its own topics and the
swarm's, and receives only the swarm's (engine_users() says why each subject).
Every broker is a client of the hub, so the hub checks each message itself
(docs/deploying-a-fleet.md says why not a leaf node per vehicle).
The control plane (gRPC) stays plaintext here.

The radio network (10.77.0.0/24) joins the ground and the vehicles; its
links to the vehicles are shaped: every TCP connection that crosses one goes
through the vehicle's radio_relay.py (--delay-ms, --jitter-ms per direction),
iptables' statistic match drops --loss of the packets in each direction (where
they arrive), tbf bounds --rate-kbit, and Fleet.cut() sets the vehicle's veth
down. The bus network (10.78.0.0/24) stands for each vehicle's onboard link
to its autopilot: never shaped, never cut. This machine is on both networks
(10.77.0.254, 10.78.0.254), as an operator's laptop would be, to start and
watch the processes.

Needs root (namespaces, veths, iptables, /etc/netns), iproute2, iptables,
nats-server and (secure) openssl.
"""

import argparse
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import urllib.request

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(os.path.dirname(HERE))
sys.path.insert(0, os.path.join(REPO, "deploy", "local"))

import demo  # noqa: E402
import rpc  # noqa: E402
import stack  # noqa: E402

RADIO_NET, BUS_NET = "10.77.0", "10.78.0"
GROUND_RADIO, SIM_RADIO, SIM_BUS = f"{RADIO_NET}.1", f"{RADIO_NET}.2", f"{BUS_NET}.1"
OPERATOR_SUFFIX = "254"

NATS_CLIENT_PORT, NATS_MONITOR_PORT = 4222, 8222
# Every broker repeats its host's wants every 3 s (and at once on a change),
# not every second: each vehicle hears every other broker's, across its radio.
# A broker that went silent stops counting after 10 s.
ANNOUNCE_PERIOD_S, WANT_TTL_S = 3.0, 10.0
# Systems configured for a vehicle whose ground link is a radio (else their
# own config.yaml): the swarm's belief writes, each a call to the ground.
RADIO_CONFIGS = {"swarm_interaction": os.path.join(HERE, "swarm_interaction.yaml")}
# The local ports of outgoing connections on every host: above all of the above.
EPHEMERAL_PORTS = (61000, 65000)
BROKER_PORT, COORDINATOR_PORT, SIMULATOR_PORT = 50051, 50060, 50070
# A behavior system listens on 50061 + i and is reached through the radio on
# 60061 + i; the vehicle's autopilot (the simulator) on 60070.
SYSTEM_PORT, RELAYED_OFFSET = 50061, 10000
METRICS_OFFSET = 1000  # a server's /metrics: its gRPC port + 1000 (9xxx clash with nothing)

SWARM_MISSION = os.path.join(REPO, "deploy", "missions", "swarm_member.yaml")
CATALOG = os.path.join(REPO, "deploy", "config", "catalog.yaml")
SYSTEMS_DIR = os.path.join(REPO, "services", "systems")
DEFAULT_SYSTEMS = ["basic_quadrotor_behaviors", "multi_sensor_fusion", "swarm_interaction"]
# The coordinator's supervision in the deterministic mode (deploy/local/launch.py).
DETERMINISTIC_GRACE_S = 5.0
# A vehicle that has lost the ground this long (its own time) lands by itself
# (basic_quadrotor_behaviors --link-loss-action LAND).
LINK_LOSS_S = 10.0
# A vehicle's broker sends each topic at most this often over its radio
# (--link-max-rate-hz): the ground follows a pose at 10 Hz, not 100.
RADIO_MAX_RATE_HZ = 10.0

# The secure engine's certificates (scripts/make-dev-certs.sh, in the run
# directory): the hub's, the ground's and the simulation host's brokers', and
# one per vehicle named by its robot id, held by its broker. Each carries the
# URI SAN behaviorlib:NAME, the NATS user it maps to.
MAKE_CERTS = os.path.join(REPO, "scripts", "make-dev-certs.sh")
HUB_CERT, GROUND_CERT, SIM_CERT = "nats-hub", "ground-broker", "sim-broker"
# Whoever connects to the hub checks its certificate for the name it dials:
# the ground's broker and the vehicles' brokers (through their relays) dial
# 127.0.0.1, which every certificate names; the simulation host dials
# the hub by the name its certificate carries, mapped to its radio address in
# the host's own hosts file (/etc/netns/<namespace>/hosts, which ip netns
# exec mounts over /etc/hosts).
HUB_NAME = HUB_CERT
NETNS_ETC = "/etc/netns"
# The swarm's shared topics (swarm_interaction's swarm_topics.h), whose
# samples name their sender: swarm_interaction publishes this vehicle's pose
# and messages there, and reads the other vehicles'.
SWARM_SUBJECTS = ["bl.t.robots.swarm.positions", "bl.t.robots.swarm.messages"]
# A TLS handshake across a lossy radio takes a few round trips (and more on a
# busy machine): nats-server's default of 2 s is too short.
TLS_TIMEOUT_S = 5


def run(*argv, check=True):
    """Runs a command; its output, or raises with it."""
    result = subprocess.run(argv, capture_output=True, text=True)
    if check and result.returncode != 0:
        raise RuntimeError(f"{' '.join(argv)}: exit {result.returncode}: "
                           f"{(result.stderr or result.stdout).strip()}")
    return result.stdout


def vehicle_radio(index):
    return f"{RADIO_NET}.{10 + index}"


def vehicle_bus(index):
    return f"{BUS_NET}.{10 + index}"


class NsProcess(stack.Process):
    """A server of ours in a host's namespace, reached at the host's
    address; ready when its gRPC health check answers."""

    def __init__(self, name, ns, host_ip, argv, run_dir, role, robot_id="", system=""):
        # The control plane: plaintext on the fleet's private networks, which
        # nothing else reaches (the data engine has mutual TLS: Fleet.secure).
        super().__init__(name, ["ip", "netns", "exec", ns, *argv, "--insecure"], run_dir, role,
                         robot_id, system)
        self.host_ip = host_ip

    @property
    def address(self):
        return f"{self.host_ip}:{self.grpc_port}"

    @property
    def metrics_address(self):
        return f"{self.host_ip}:{self.metrics_port}" if self.metrics_port else ""


class NsHttpProcess(stack.HttpProcess):
    """The console in a host's namespace: ready when GET /healthz answers."""

    def __init__(self, name, ns, host_ip, argv, run_dir, role):
        super().__init__(name, ["ip", "netns", "exec", ns, *argv, "--insecure"], run_dir, role)
        self.host_ip = host_ip

    @property
    def address(self):
        return f"{self.host_ip}:{self.http_port}"


class PlainProcess:
    """A program that is not ours (nats-server) or writes no port file (the
    relay): ready when `ready()` says so."""

    def __init__(self, name, ns, argv, run_dir, ready, role="", robot_id=""):
        self.name, self.role, self.robot_id, self.system = name, role, robot_id, name
        self.argv = ["ip", "netns", "exec", ns, *argv]
        self.log_path = os.path.join(run_dir, "logs", name + ".log")
        self.ready = ready
        self.process = None
        self.metrics_port = 0
        self.exit_code = None
        self.restarts = 0

    @property
    def pid(self):
        return self.process.pid if self.process else None

    def running(self):
        return self.process is not None and self.process.poll() is None

    def start(self, timeout_s=20.0, on_spawn=None, cancel=None):
        os.makedirs(os.path.dirname(self.log_path), exist_ok=True)
        with open(self.log_path, "ab") as log:
            log.write(("$ " + " ".join(self.argv) + "\n").encode())
            log.flush()
            self.process = stack.popen_with_launcher(
                self.argv, stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT,
                start_new_session=True)
        if on_spawn:
            on_spawn()
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise stack.StartError(f"{self.name} exited with {self.process.returncode}; "
                                       f"see {self.log_path}")
            if self.ready():
                return
            time.sleep(0.05)
        raise stack.StartError(f"{self.name} was not ready within {timeout_s} s; "
                               f"see {self.log_path}")

    def stop(self, timeout_s=10.0):
        return stack.Process.stop(self, timeout_s)


def http_ok(url):
    def ready():
        try:
            with urllib.request.urlopen(url, timeout=1.0) as reply:
                return reply.status == 200
        except OSError:
            return False
    return ready


def file_exists(path):
    return lambda: os.path.exists(path)


class Fleet:
    """The namespaces, links and processes of one fleet. Use as a context
    manager: leaving it stops every process and removes the network, even
    after a failure."""

    def __init__(self, build_dir, run_dir, vehicles=3, prefix="blf", delay_ms=30.0,
                 jitter_ms=10.0, loss=0.01, rate_kbit=0, systems=None, seed=1, say=print,
                 link_loss_s=LINK_LOSS_S, data_path="nats", time_scale="max", console=True,
                 secure=None):
        if not 1 <= vehicles <= 9:
            raise ValueError("a fleet of 1 to 9 vehicles")
        if not (len(prefix) <= 4 and prefix.isalnum()):
            raise ValueError("the prefix names interfaces: at most 4 letters or digits")
        self.build_dir = os.path.abspath(build_dir)
        self.run_dir = os.path.abspath(run_dir)
        self.robots = [f"drone{i}" for i in range(1, vehicles + 1)]
        self.prefix = prefix
        self.delay_ms, self.jitter_ms = delay_ms, jitter_ms
        self.loss, self.rate_kbit = loss, rate_kbit
        self.systems = list(systems or DEFAULT_SYSTEMS)
        self.seed = seed
        self.link_loss_s = link_loss_s
        # "nats": a broker per host, linked (decision 39); "broker": the one
        # broker on the ground that every vehicle's systems and the simulator
        # use over gRPC, as before (for comparison, benchmarks only).
        if data_path not in ("nats", "broker"):
            raise ValueError("data_path is 'nats' or 'broker'")
        self.data_path = data_path
        # Mutual TLS and per-identity permissions on the data engine (NATS):
        # by default whenever there is one.
        self.secure = data_path == "nats" if secure is None else bool(secure)
        if self.secure and data_path != "nats":
            raise ValueError("secure is for the data engine: data_path 'nats'")
        self.certs_dir = os.path.join(self.run_dir, "certs")
        # "max": the deterministic mode (tests); a number: free running at
        # that many simulated seconds per wall second (a radio's budget is
        # per wall second).
        self.time_scale = str(time_scale)
        self.deterministic = self.time_scale == "max"
        self.with_console = console
        self.console = None
        # The flight recorder's file; each restart of the ground starts a new one.
        self.recording = os.path.join(self.run_dir, "recordings", "flight.mcap")
        self.recordings = [self.recording]
        self.say = say
        self.stack = stack.Stack(self.run_dir)
        self.namespaces = []
        self.links = []  # root-side veths
        self.bridges = []
        self.forward_rules = []
        self.etc_dirs = []  # /etc/netns/<namespace>
        self.coordinator = None
        self.ground_broker = None
        self.recorder = None
        self.simulator = None
        self.sim_broker = None
        self.ground = []  # the ground host's processes, in start order
        self.by_robot = {robot: [] for robot in self.robots}  # the vehicle host's processes
        self.vehicle_brokers = {}  # {robot: its broker} (the data path "nats")

    # --- names ----------------------------------------------------------------

    def ns(self, host):
        return f"{self.prefix}-{host}"

    def radio_veth(self, robot):
        return f"{self.prefix}{self.robots.index(robot) + 1}r"

    def binary(self, name):
        path = os.path.join(self.build_dir, "bin", name)
        if not os.access(path, os.X_OK):
            raise stack.StartError(f"{path} is not built (scripts/build.sh)")
        return path

    # --- the network -------------------------------------------------------------

    def _bridge(self, name, net):
        run("ip", "link", "add", name, "type", "bridge")
        self.bridges.append(name)
        run("ip", "addr", "add", f"{net}.{OPERATOR_SUFFIX}/24", "dev", name)
        run("ip", "link", "set", name, "up")
        # Where bridged frames pass iptables (br_netfilter, loaded by a
        # Docker engine whose FORWARD policy is DROP), ours go through.
        if os.path.exists("/proc/sys/net/bridge/bridge-nf-call-iptables"):
            rule = ["FORWARD", "-i", name, "-o", name, "-j", "ACCEPT"]
            run("iptables", "-I", *rule)
            self.forward_rules.append(rule)

    def _host(self, host):
        ns = self.ns(host)
        run("ip", "netns", "add", ns)
        self.namespaces.append(ns)
        run("ip", "-n", ns, "link", "set", "lo", "up")
        # Outgoing connections take their local ports above every fixed port
        # of the fleet (the default range, 32768-60999, holds the servers'
        # and the relays' ports: a client could take one before its server
        # binds it). The range is the namespace's own.
        run("ip", "netns", "exec", ns, "sh", "-c",
            f"echo {EPHEMERAL_PORTS[0]} {EPHEMERAL_PORTS[1]} "
            "> /proc/sys/net/ipv4/ip_local_port_range")
        return ns

    def _attach(self, ns, root_name, bridge, inside, ip):
        run("ip", "link", "add", root_name, "type", "veth", "peer", "name", root_name + "p")
        self.links.append(root_name)
        run("ip", "link", "set", root_name + "p", "netns", ns)
        run("ip", "-n", ns, "link", "set", root_name + "p", "name", inside)
        run("ip", "-n", ns, "addr", "add", f"{ip}/24", "dev", inside)
        run("ip", "-n", ns, "link", "set", inside, "up")
        run("ip", "link", "set", root_name, "master", bridge)
        run("ip", "link", "set", root_name, "up")

    def _hosts_file(self, ns, names):
        """The host's own /etc/hosts: localhost and `names` {name: address}."""
        path = os.path.join(NETNS_ETC, ns, "hosts")
        os.makedirs(os.path.dirname(path), exist_ok=True)
        self.etc_dirs.append(os.path.dirname(path))
        with open(path, "w") as f:
            f.write("127.0.0.1 localhost\n::1 localhost\n")
            f.write("".join(f"{address} {name}\n" for name, address in names.items()))

    def _remove_leftovers(self):
        """What a fleet of the same prefix left behind when it was killed."""
        for line in run("ip", "netns", "list", check=False).splitlines():
            name = line.split()[0] if line.split() else ""
            if name.startswith(self.prefix + "-"):
                run("ip", "netns", "del", name, check=False)
        for name in (f"{self.prefix}r", f"{self.prefix}b"):
            run("ip", "link", "del", name, check=False)
        if os.path.isdir(NETNS_ETC):
            for name in os.listdir(NETNS_ETC):
                if name.startswith(self.prefix + "-"):
                    shutil.rmtree(os.path.join(NETNS_ETC, name), ignore_errors=True)

    def create_network(self):
        p = self.prefix
        self._remove_leftovers()
        self._bridge(f"{p}r", RADIO_NET)
        self._bridge(f"{p}b", BUS_NET)
        ground = self._host("ground")
        self._attach(ground, f"{p}gr", f"{p}r", "radio", GROUND_RADIO)
        sim = self._host("sim")
        self._attach(sim, f"{p}sb", f"{p}b", "bus", SIM_BUS)
        self._attach(sim, f"{p}sr", f"{p}r", "radio", SIM_RADIO)
        self._hosts_file(sim, {HUB_NAME: GROUND_RADIO})
        for i, robot in enumerate(self.robots, start=1):
            ns = self._host(robot)
            self._attach(ns, self.radio_veth(robot), f"{p}r", "radio", vehicle_radio(i))
            self._attach(ns, f"{p}{i}b", f"{p}b", "bus", vehicle_bus(i))
            if self.loss > 0:
                # Dropped where they arrive, in each direction: a drop on
                # OUTPUT would tell the sender's TCP at once, as no radio does.
                loss = ["-m", "statistic", "--mode", "random", "--probability",
                        f"{self.loss:g}", "-j", "DROP"]
                run("ip", "netns", "exec", ns, "iptables", "-A", "INPUT", "-i", "radio", *loss)
                run("ip", "netns", "exec", ground, "iptables", "-A", "INPUT", "-i", "radio",
                    "-s", vehicle_radio(i), *loss)
            if self.rate_kbit > 0:
                tbf = ["tbf", "rate", f"{self.rate_kbit}kbit", "burst", "16kb", "latency", "200ms"]
                run("ip", "netns", "exec", ns, "tc", "qdisc", "add", "dev", "radio", "root", *tbf)
                run("tc", "qdisc", "add", "dev", self.radio_veth(robot), "root", *tbf)

    def destroy_network(self):
        for rule in self.forward_rules:
            run("iptables", "-D", *rule, check=False)
        for name in self.links + self.bridges:
            run("ip", "link", "del", name, check=False)
        for ns in self.namespaces:
            run("ip", "netns", "del", ns, check=False)
        for path in self.etc_dirs:
            shutil.rmtree(path, ignore_errors=True)
        if self.etc_dirs:
            try:
                os.rmdir(NETNS_ETC)  # when no other namespace has its files there
            except OSError:
                pass
        self.links, self.bridges, self.namespaces, self.forward_rules = [], [], [], []
        self.etc_dirs = []

    # --- the link faults -------------------------------------------------------

    def cut(self, robot):
        """The vehicle's radio goes silent: nothing in, nothing out."""
        run("ip", "link", "set", self.radio_veth(robot), "down")

    def restore(self, robot):
        run("ip", "link", "set", self.radio_veth(robot), "up")

    def kill_host(self, robot):
        """Every process of the vehicle's host dies at once (SIGKILL)."""
        for process in self.by_robot[robot]:
            if process.running():
                process.process.kill()
                process.process.wait()

    def restart_ground(self, down_s=0.0):
        """The ground station goes down at once and comes back: every
        process of the ground host (the hub, its broker, the coordinator,
        the console and the flight recorder) is killed (SIGKILL), and after
        `down_s` all are started again in the order start() started them.
        The coordinator takes its missions up from its state directory; the
        recorder writes a new file (self.recording names it)."""
        for process in self.ground:
            if process.running():
                process.process.kill()
        for process in self.ground:
            if process.process is not None:
                process.process.wait()
        left = run("ip", "netns", "pids", self.ns("ground"), check=False).split()
        if left:
            raise RuntimeError(f"the ground host still runs {', '.join(left)}")
        time.sleep(down_s)
        if self.recorder is not None:
            stem, ext = os.path.splitext(self.recordings[0])
            self.recording = f"{stem}-{len(self.recordings) + 1}{ext}"
            self.recordings.append(self.recording)
            self.recorder.argv[-1] = self.recording
        for process in self.ground:
            self.stack.restart(process)
            process.restarts += 1

    # --- the engine's certificates and users (secure) ------------------------------

    def tls_files(self, name):
        """A certificate of the run directory: (chain, key, CA)."""
        return (os.path.join(self.certs_dir, f"{name}.pem"),
                os.path.join(self.certs_dir, f"{name}.key"),
                os.path.join(self.certs_dir, "ca.pem"))

    def make_certs(self):
        run("bash", MAKE_CERTS, "--out", self.certs_dir, HUB_CERT, GROUND_CERT, SIM_CERT,
            *self.robots)

    def engine_users(self):
        """The hub's users, one per certificate: [(certificate name, the
        connection it may make, [(publish subject, why)], [(subscribe
        subject, why)])]. `publish` bounds what the user may send to the hub,
        `subscribe` what the hub sends it. Every broker publishes its wants
        on bl.want.<its link name> and bl.hello when it (re)connects, and
        subscribes to every broker's wants (bl.want.*) and to bl.hello
        (nats_link.h); it makes no request, so no reply subject is needed."""
        wants = [("bl.want.*", "the other brokers' wants: a topic is sent only while wanted"),
                 ("bl.hello", "a broker (re)connected: announce the wants again")]
        users = [
            (GROUND_CERT, "STANDARD",
             [("bl.want.ground", "the ground's wants"),
              ("bl.hello", "its broker (re)connected")],
             # (no bl.t: nothing published on the ground crosses; a ground tool
             # that publishes for the vehicles would add its topics here)
             [("bl.t.>", "the console and the recorder follow every vehicle; "
                         "the coordinator reads the simulation's clock")] + wants),
            (SIM_CERT, "STANDARD",
             [("bl.t.clock", "the simulated time, for the ground (the vehicles take "
                             "theirs over the bus: --link-local clock)"),
              ("bl.want.sim", "the simulation host's wants"),
              ("bl.hello", "its broker (re)connected")],
             # (it reads nothing across: its vehicles' topics come over the bus)
             wants),
        ]
        for robot in self.robots:
            # Its broker, across the radio: a client, whose every message the
            # hub checks (a leaf node's it would not).
            users.append((robot, "STANDARD",
                          [(f"bl.t.robots.{robot}.>", "its own topics: state, sensors, "
                                                      "estimates (the ground's console)")]
                          + [(subject, "the swarm's, whose samples name their sender")
                             for subject in SWARM_SUBJECTS]
                          + [(f"bl.want.{robot}", "its wants"),
                             ("bl.hello", "its broker (re)connected")],
                          [(subject, "the other vehicles' (swarm_interaction)")
                           for subject in SWARM_SUBJECTS]
                          # Its broker subscribes to every topic its host
                          # wants, its own among them; only it may publish
                          # there, and none of its own comes back (no echo):
                          # allowed, so that the hub has no violation to log.
                          + [(f"bl.t.robots.{robot}.>", "its own topics: nothing arrives")]
                          + wants))
        return users

    def _tls_block(self, name, indent, verify_and_map=False):
        cert, key, ca = self.tls_files(name)
        lines = [f'cert_file: "{cert}"', f'key_file: "{key}"', f'ca_file: "{ca}"',
                 f"timeout: {TLS_TIMEOUT_S}"]
        if verify_and_map:
            lines.append("verify_and_map: true")
        pad = " " * indent
        return f"{pad}tls {{\n" + "".join(f"{pad}  {line}\n" for line in lines) + f"{pad}}}\n"

    def hub_config(self):
        """The hub's nats-server configuration."""
        text = (f'listen: "0.0.0.0:{NATS_CLIENT_PORT}"\n'
                f'http: "0.0.0.0:{NATS_MONITOR_PORT}"\n'
                'ping_interval: "1s"\nping_max: 3\n')
        if not self.secure:
            return text
        text = ("# Mutual TLS. verify_and_map: a certificate is its user below, matched\n"
                "# by its URI SAN (behaviorlib:NAME; no user is named after a DNS SAN,\n"
                "# which would match first); a certificate without a user is refused.\n"
                "# Every broker, the vehicles' too (through their radios), is a client:\n"
                "# the hub checks each message it takes against the sender's permissions\n"
                "# (nats-server 2.9 does not check what a leaf node sends against its\n"
                "# user's permissions: it relies on the leaf node to filter).\n") + text
        text += self._tls_block(HUB_CERT, 0, verify_and_map=True)
        text += "authorization {\n  users = [\n"
        for name, connection, publish, subscribe in self.engine_users():
            text += (f"    {{\n      user: \"behaviorlib:{name}\"\n"
                     f"      allowed_connection_types: [\"{connection}\"]\n"
                     "      permissions: {\n")
            for verb, subjects, what in (("publish", publish, "it may send to the hub"),
                                         ("subscribe", subscribe, "the hub sends it")):
                text += f"        # What {what}.\n        {verb}: {{ allow: [\n"
                text += "".join(f'          "{subject}"  # {why}\n' for subject, why in subjects)
                text += "        ] }\n"
            text += "      }\n    }\n"
        return text + "  ]\n}\n"

    # --- the processes ------------------------------------------------------------

    def _nats_config(self, name, text):
        path = os.path.join(self.run_dir, "nats", name + ".conf")
        os.makedirs(os.path.dirname(path), exist_ok=True)
        with open(path, "w") as f:
            f.write(text)
        return path

    def _nats(self, host, ns, monitor_ip, config_text):
        config = self._nats_config(host, config_text)
        process = PlainProcess(f"nats-{host}", ns, ["nats-server", "-c", config],
                               self.run_dir,
                               http_ok(f"http://{monitor_ip}:{NATS_MONITOR_PORT}/healthz"))
        return self.stack.start(process)

    def _broker(self, host, ns, ip, link_url, robot_id="", local="", max_rate_hz=0.0, cert=""):
        argv = [self.binary("channel_broker"), "--listen", f"0.0.0.0:{BROKER_PORT}",
                "--metrics-listen", f"0.0.0.0:{BROKER_PORT + METRICS_OFFSET}"]
        if link_url:
            argv += ["--link-url", link_url, "--link-name", host,
                     "--link-announce-period-s", f"{ANNOUNCE_PERIOD_S:g}",
                     "--link-want-ttl-s", f"{WANT_TTL_S:g}"]
        if cert:
            link_cert, link_key, link_ca = self.tls_files(cert)
            argv += ["--link-tls-cert", link_cert, "--link-tls-key", link_key,
                     "--link-tls-ca", link_ca]
        if local:
            argv += ["--link-local", local]
        if max_rate_hz:
            argv += ["--link-max-rate-hz", f"{max_rate_hz:g}"]
        return self.stack.start(NsProcess(f"channel_broker-{host}", ns, ip, argv, self.run_dir,
                                          "channel_broker", robot_id))

    def start(self):
        os.makedirs(self.run_dir, exist_ok=True)
        ground, sim = self.ns("ground"), self.ns("sim")
        linked = self.data_path == "nats"
        scheme = "tls" if self.secure else "nats"
        if self.secure:
            self.make_certs()
        if linked:
            self.ground.append(self._nats("ground", ground, GROUND_RADIO, self.hub_config()))
        self.ground_broker = self._broker(
            "ground", ground, GROUND_RADIO,
            f"{scheme}://127.0.0.1:{NATS_CLIENT_PORT}" if linked else "",
            cert=GROUND_CERT if self.secure else "")
        self.ground.append(self.ground_broker)
        if linked:
            hub = HUB_NAME if self.secure else GROUND_RADIO
            self.sim_broker = self._broker("sim", sim, SIM_BUS,
                                           f"{scheme}://{hub}:{NATS_CLIENT_PORT}",
                                           cert=SIM_CERT if self.secure else "")

        # The vehicles' hosts, up to their brokers: the simulator publishes to them.
        for i, robot in enumerate(self.robots, start=1):
            ns = self.ns(robot)
            relays = [f"127.0.0.1:{COORDINATOR_PORT}={GROUND_RADIO}:{COORDINATOR_PORT}",
                      f"{vehicle_radio(i)}:{SIMULATOR_PORT + RELAYED_OFFSET}={SIM_BUS}:"
                      f"{SIMULATOR_PORT}"]
            for j, _ in enumerate(self.systems):
                relays.append(f"{vehicle_radio(i)}:{SYSTEM_PORT + j + RELAYED_OFFSET}="
                              f"127.0.0.1:{SYSTEM_PORT + j}")
            if linked:  # the hub, across the radio
                relays.append(f"127.0.0.1:{NATS_CLIENT_PORT}={GROUND_RADIO}:{NATS_CLIENT_PORT}")
            else:  # the ground's broker, across the radio
                relays.append(f"127.0.0.1:{BROKER_PORT}={GROUND_RADIO}:{BROKER_PORT}")
            ready_file = os.path.join(self.run_dir, "relays", robot + ".ready")
            os.makedirs(os.path.dirname(ready_file), exist_ok=True)
            if os.path.exists(ready_file):
                os.remove(ready_file)
            relay_argv = [sys.executable, os.path.join(HERE, "radio_relay.py"),
                          "--delay-ms", str(self.delay_ms), "--jitter-ms", str(self.jitter_ms),
                          "--seed", str(self.seed + i), "--ready-file", ready_file]
            for relay in relays:
                relay_argv += ["--map", relay]
            self.by_robot[robot].append(self.stack.start(PlainProcess(
                f"radio_relay-{robot}", ns, relay_argv, self.run_dir, file_exists(ready_file),
                robot_id=robot)))
            if not linked:
                continue
            # A client of the hub, through the radio's relay (the hub's
            # certificate names the relay's 127.0.0.1): the hub holds it to
            # its user's permissions. The NATS client reconnects by itself
            # when the radio comes back, and buffers what it publishes
            # meanwhile (up to 64 KiB); the broker keeps serving its host.
            broker = self._broker(robot, ns, vehicle_bus(i),
                                  f"{scheme}://127.0.0.1:{NATS_CLIENT_PORT}", robot,
                                  local="clock", max_rate_hz=RADIO_MAX_RATE_HZ,
                                  cert=robot if self.secure else "")
            self.vehicle_brokers[robot] = broker
            self.by_robot[robot].append(broker)

        sim_argv = [self.binary("simulator"), "--listen", f"0.0.0.0:{SIMULATOR_PORT}",
                    "--metrics-listen", f"0.0.0.0:{SIMULATOR_PORT + METRICS_OFFSET}"]
        if linked:
            sim_argv += ["--channel", f"127.0.0.1:{BROKER_PORT}",
                         "--vehicle-channels", ",".join(
                             f"{robot}={vehicle_bus(i)}:{BROKER_PORT}"
                             for i, robot in enumerate(self.robots, start=1))]
        else:
            sim_argv += ["--channel", f"{GROUND_RADIO}:{BROKER_PORT}"]
        sim_argv += ["--vehicles", ",".join(self.robots), "--time-scale", self.time_scale,
                     "--seed", str(self.seed)]
        if self.deterministic:
            sim_argv += ["--min-followers", str(len(self.systems) * len(self.robots))]
        self.simulator = self.stack.start(NsProcess("simulator", sim, SIM_BUS, sim_argv,
                                                    self.run_dir, "simulator"))

        coordinator_argv = [
            self.binary("coordinator"), "--listen", f"0.0.0.0:{COORDINATOR_PORT}",
            "--metrics-listen", f"0.0.0.0:{COORDINATOR_PORT + METRICS_OFFSET}",
            "--state-dir", os.path.join(self.run_dir, "coordinator"),
            "--mission-dir", os.path.join(REPO, "deploy", "missions"),
            "--catalog", CATALOG,
            "--flight-controller", ",".join(
                f"{robot}={vehicle_radio(i)}:{SIMULATOR_PORT + RELAYED_OFFSET}"
                for i, robot in enumerate(self.robots, start=1)),
            "--channel", f"127.0.0.1:{BROKER_PORT}", "--clock", "sim"]
        if self.deterministic:
            coordinator_argv += ["--grace-period-s", str(DETERMINISTIC_GRACE_S)]
        self.coordinator = self.stack.start(NsProcess("coordinator", ground, GROUND_RADIO,
                                                      coordinator_argv, self.run_dir,
                                                      "coordinator"))
        self.ground.append(self.coordinator)
        if self.with_console:
            # The ground station's console and flight recorder, on its broker.
            os.makedirs(os.path.dirname(self.recording), exist_ok=True)
            self.console = self.stack.start(NsHttpProcess(
                "console", ground, GROUND_RADIO,
                [self.binary("console"), "--listen", "0.0.0.0:8090",
                 "--coordinator", f"127.0.0.1:{COORDINATOR_PORT}",
                 "--channel", f"127.0.0.1:{BROKER_PORT}",
                 "--web-dir", os.path.join(REPO, "console", "web"),
                 "--recordings-dir", os.path.dirname(self.recording)],
                self.run_dir, "console"))
            self.recorder = self.stack.start(PlainProcess(
                "recorder", ground,
                [self.binary("behaviorctl"), "--coordinator", f"127.0.0.1:{COORDINATOR_PORT}",
                 "--channel", f"127.0.0.1:{BROKER_PORT}", "record", self.recording],
                self.run_dir, lambda: True))
            self.ground += [self.console, self.recorder]

        for i, robot in enumerate(self.robots, start=1):
            ns = self.ns(robot)
            for j, name in enumerate(self.systems):
                port = SYSTEM_PORT + j
                argv = [self.binary(name), "--robot-id", robot,
                        "--listen", f"0.0.0.0:{port}",
                        "--metrics-listen", f"0.0.0.0:{port + METRICS_OFFSET}",
                        "--advertise", f"{vehicle_radio(i)}:{port + RELAYED_OFFSET}",
                        "--channel", f"127.0.0.1:{BROKER_PORT}", "--clock", "sim",
                        "--coordinator", f"127.0.0.1:{COORDINATOR_PORT}",
                        "--flight-controller", f"{SIM_BUS}:{SIMULATOR_PORT}"]
                if self.deterministic:
                    argv += ["--follow-time", f"{SIM_BUS}:{SIMULATOR_PORT}"]
                if name == "basic_quadrotor_behaviors" and self.link_loss_s > 0:
                    argv += ["--link-loss-timeout-s", str(self.link_loss_s),
                             "--link-loss-action", "LAND"]
                config = RADIO_CONFIGS.get(name, os.path.join(SYSTEMS_DIR, name, "config.yaml"))
                if os.path.exists(config):
                    argv += ["--config", config]
                self.by_robot[robot].append(self.stack.start(NsProcess(
                    f"{name}-{robot}", ns, vehicle_bus(i), argv, self.run_dir,
                    "behavior_system", robot, system=name)))
        return self

    def coordinator_client(self):
        return rpc.Client(self.coordinator.address, [demo.COORDINATOR])

    def wait_for_systems(self, client, timeout_s=60.0):
        for robot in self.robots:
            demo.wait_for_systems(client, robot, self.systems, timeout_s)

    def stop(self):
        self.stack.stop(timeout_s=10.0, report=lambda text: None)

    def __enter__(self):
        try:
            self.create_network()
            return self.start()
        except BaseException:
            self.__exit__(None, None, None)
            raise

    def __exit__(self, *exc):
        try:
            self.stop()
        finally:
            self.destroy_network()
        return False


def fly_swarm(fleet, client, timeout_s=300.0, out=print):
    """Every vehicle flies the swarm mission at once; {robot: final status}."""
    stamp = f"{time.strftime('%Y%m%d-%H%M%S')}-{os.getpid()}"
    missions = [(robot, SWARM_MISSION, f"fleet-{stamp}-{robot}") for robot in fleet.robots]
    return demo.run_missions(client, missions, timeout_s, out, lambda robot, status: None)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--build-dir", default=os.path.join(REPO, "build"))
    parser.add_argument("--run-dir", default="")
    parser.add_argument("--vehicles", type=int, default=3)
    parser.add_argument("--delay-ms", type=float, default=30.0)
    parser.add_argument("--jitter-ms", type=float, default=10.0)
    parser.add_argument("--loss", type=float, default=0.01, help="each direction, 0..1")
    parser.add_argument("--rate-kbit", type=int, default=0, help="tbf on each radio link; 0: none")
    parser.add_argument("--prefix", default="blf", help="of the namespaces and interfaces")
    parser.add_argument("--keep", action="store_true",
                        help="fly nothing; keep the fleet up until Ctrl-C")
    parser.add_argument("--mission-timeout-s", type=float, default=300.0)
    parser.add_argument("--no-secure", dest="secure", action="store_false",
                        help="the data engine in plaintext, every host allowed everything "
                             "(for comparison)")
    args = parser.parse_args()
    if os.geteuid() != 0:
        parser.error("needs root: it makes network namespaces, veths and iptables rules")
    for tool in ("ip", "iptables", "tc", "nats-server") + (("openssl",) if args.secure else ()):
        if shutil.which(tool) is None:
            parser.error(f"{tool} is not installed (scripts/install-deps.sh)")
    run_dir = args.run_dir or tempfile.mkdtemp(prefix="behaviorlib-fleet-")
    signal.signal(signal.SIGTERM, lambda *_: (_ for _ in ()).throw(KeyboardInterrupt()))
    print(f"fleet: {args.vehicles} vehicles, radio {args.delay_ms:g} +- {args.jitter_ms:g} ms, "
          f"loss {args.loss * 100:g} %; engine {'mutual TLS' if args.secure else 'plaintext'}; "
          f"logs in {run_dir}/logs")
    try:
        with Fleet(args.build_dir, run_dir, args.vehicles, args.prefix, args.delay_ms,
                   args.jitter_ms, args.loss, args.rate_kbit, secure=args.secure) as fleet:
            client = fleet.coordinator_client()
            fleet.wait_for_systems(client)
            print(f"fleet: up; coordinator {fleet.coordinator.address}, "
                  f"ground broker {fleet.ground_broker.address}")
            if args.keep:
                while True:
                    time.sleep(1)
            statuses = fly_swarm(fleet, client, args.mission_timeout_s)
            failed = [robot for robot, status in statuses.items()
                      if status.get("state") != "MISSION_STATE_SUCCEEDED"]
            for robot, status in statuses.items():
                print(f"fleet: {robot}: {status.get('state')} {status.get('message', '')}")
            client.close()
            return 1 if failed else 0
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
