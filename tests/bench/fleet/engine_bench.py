"""Three ways to carry a vehicle's samples to the ground across a network link:
NATS, Cyclone DDS and the data channel (gRPC, channel_broker). Two network
namespaces stand for the hosts, "vehicle" (10.231.0.2) and "ground"
(10.231.0.1), joined by a veth pair; the publisher (engine_probe, in this
folder) runs in the vehicle and sends behaviorlib.v1.PoseStamped samples at
200 Hz, the subscriber runs on the ground.

    sudo python3 tests/bench/fleet/engine_bench.py --build-dir build --seconds 20 \
        --conditions clean,loss1 --out engine_bench.json

- nats, nats-asap: one nats-server on the ground; the publisher connects to
  it across the link, the subscriber locally. nats leaves the C client's
  default (a publication waits in its buffer for the flusher thread),
  nats-asap writes each at once (natsOptions_SetSendAsap).
- dds, dds-reliable: Cyclone DDS peer to peer, best-effort / reliable
  (KEEP_LAST 100); each namespace gets a configuration that binds its veth
  end (--dds-discovery: SPDP by multicast, or unicast to the other address).
- grpc: channel_broker on the ground, the publisher across the link, a QUEUE
  subscription on its stream (no shared-memory ring).

Conditions: clean (no shaping); loss1 (iptables statistic drops 1 % of the
packets arriving on the veth end in each namespace, so both directions lose
1 % and the sender does not know, as on a radio link); tbf (a tbf qdisc of
--tbf-kbit on each end's egress). Per engine and condition the table gives
the samples delivered, the one-way latency (CLOCK_REALTIME stamp to
receipt: the namespaces share the clock), the bytes on the link per second
(the ground end's tx+rx counters over the sending window) and the CPU of
publisher, subscriber (getrusage over their own windows) and server
(/proc/PID/stat over the sending window) in % of one core.

--smoke runs 2 s per engine on a clean link and exits 1 unless each engine
delivered more than 90 % of its samples. Needs root: exits 77 (skipped)
otherwise, or when the namespaces cannot be made, or without nats-server.
"""

import argparse
import json
import os
import queue
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time

CLOCK_TICKS = os.sysconf("SC_CLK_TCK")
SKIP = 77
GROUND, VEHICLE = "blbench-ground", "blbench-vehicle"
GROUND_IF, VEHICLE_IF = "blbench-g", "blbench-v"
GROUND_IP, VEHICLE_IP = "10.231.0.1", "10.231.0.2"
NATS_PORT = 4222
ENGINES = ["nats", "nats-asap", "dds", "dds-reliable", "grpc"]
CONDITIONS = ["clean", "loss1", "tbf"]
TOPIC = "robots/drone1/pose"


class Skip(Exception):
    pass


def run(*argv, check=True):
    r = subprocess.run(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    if check and r.returncode != 0:
        raise RuntimeError(f"{' '.join(argv)}: {r.stderr.strip() or r.returncode}")
    return r


def remove_namespaces():
    for ns in (GROUND, VEHICLE):
        if os.path.exists(f"/run/netns/{ns}"):
            run("ip", "netns", "del", ns, check=False)


def make_namespaces():
    remove_namespaces()  # left over from a run that was killed
    try:
        run("ip", "netns", "add", GROUND)
        run("ip", "netns", "add", VEHICLE)
    except RuntimeError as e:
        raise Skip(f"cannot make network namespaces: {e}")
    run("ip", "link", "add", GROUND_IF, "netns", GROUND, "type", "veth",
        "peer", "name", VEHICLE_IF, "netns", VEHICLE)
    for ns, dev, ip in ((GROUND, GROUND_IF, GROUND_IP), (VEHICLE, VEHICLE_IF, VEHICLE_IP)):
        run("ip", "-n", ns, "addr", "add", f"{ip}/24", "dev", dev)
        run("ip", "-n", ns, "link", "set", "lo", "up")
        run("ip", "-n", ns, "link", "set", dev, "up")


def apply_condition(condition, tbf_kbit):
    for ns, dev in ((GROUND, GROUND_IF), (VEHICLE, VEHICLE_IF)):
        if condition == "loss1":
            run("ip", "netns", "exec", ns, "iptables", "-A", "INPUT", "-i", dev, "-m",
                "statistic", "--mode", "random", "--probability", "0.01", "-j", "DROP")
        elif condition == "tbf":
            run("ip", "netns", "exec", ns, "tc", "qdisc", "add", "dev", dev, "root", "tbf",
                "rate", f"{tbf_kbit}kbit", "burst", "4kb", "latency", "400ms")


def clear_condition():
    for ns, dev in ((GROUND, GROUND_IF), (VEHICLE, VEHICLE_IF)):
        run("ip", "netns", "exec", ns, "iptables", "-F", "INPUT", check=False)
        run("ip", "-n", ns, "tc", "qdisc", "del", "dev", dev, "root", check=False)


def link_bytes():
    """tx+rx bytes of the ground end of the link (everything that crossed it)."""
    stats = f"/sys/class/net/{GROUND_IF}/statistics"
    r = run("ip", "netns", "exec", GROUND, "cat", f"{stats}/tx_bytes", f"{stats}/rx_bytes")
    return sum(int(x) for x in r.stdout.split())


def cpu_seconds(pid):
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return (int(fields[11]) + int(fields[12])) / CLOCK_TICKS


def dds_config(path, own_if, peer_ip, discovery):
    multicast = "true" if discovery == "multicast" else "false"
    peers = "" if discovery == "multicast" else f'<Peers><Peer address="{peer_ip}"/></Peers>'
    with open(path, "w") as f:
        f.write('<CycloneDDS xmlns="https://cdds.io/config"><Domain id="any"><General>'
                f'<Interfaces><NetworkInterface name="{own_if}"/></Interfaces>'
                f"<AllowMulticast>{multicast}</AllowMulticast></General><Discovery>"
                f"<ParticipantIndex>auto</ParticipantIndex>{peers}</Discovery>"
                "</Domain></CycloneDDS>\n")
    return "file://" + path


class Proc:
    """A process in a namespace; stdout lines go to a queue, stderr to a log."""
    started = []

    def __init__(self, ns, argv, log_path, env=None):
        self.log_path = log_path
        self.log = open(log_path, "w")
        self.popen = subprocess.Popen(["ip", "netns", "exec", ns, *argv], stdout=subprocess.PIPE,
                                      stderr=self.log, text=True, env=env,
                                      start_new_session=True)
        Proc.started.append(self)
        self.lines = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self):
        for line in self.popen.stdout:
            self.lines.put(line.strip())
        self.lines.put(None)

    def line(self, timeout_s):
        """The next stdout line; None at its end or after timeout_s."""
        try:
            return self.lines.get(timeout=timeout_s)
        except queue.Empty:
            return None

    def json_line(self, timeout_s):
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            line = self.line(max(0.01, deadline - time.monotonic()))
            if line is None:
                return None
            if line.startswith("{"):
                return json.loads(line)
        return None

    def stop(self, timeout_s=5):
        if self.popen.poll() is None:
            try:
                os.killpg(self.popen.pid, signal.SIGTERM)
                self.popen.wait(timeout_s)
            except subprocess.TimeoutExpired:
                os.killpg(self.popen.pid, signal.SIGKILL)
                self.popen.wait()
            except ProcessLookupError:
                pass
        self.log.close()

    def tail(self):
        with open(self.log_path) as f:
            return "".join(f.readlines()[-15:])


def wait_for(predicate, timeout_s, what, proc):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and proc.popen.poll() is None:
        if predicate():
            return
        time.sleep(0.05)
    raise RuntimeError(f"{what} within {timeout_s} s:\n{proc.tail()}")


def file_has(path, text):
    try:
        with open(path) as f:
            return text in f.read()
    except OSError:
        return False


def start_server(engine, args, tmp):
    """The server on the ground (or None) and the probe arguments that reach it."""
    if engine.startswith("nats"):
        log = os.path.join(tmp, "nats-server.log")
        server = Proc(GROUND, [args.nats_server, "-a", "0.0.0.0", "-p", str(NATS_PORT)], log)
        wait_for(lambda: file_has(log, "Server is ready"), 10, "nats-server not ready", server)
        asap = "true" if engine == "nats-asap" else "false"
        return server, ["--engine", "nats", "--url", f"nats://{GROUND_IP}:{NATS_PORT}",
                        "--nats-send-asap", asap]
    if engine == "grpc":
        port_file = os.path.join(tmp, "broker.ports")
        if os.path.exists(port_file):
            os.remove(port_file)
        broker = os.path.join(args.build_dir, "bin", "channel_broker")
        # Plaintext on the namespaces' private link (the broker refuses a
        # non-loopback address without TLS unless told).
        server = Proc(GROUND, [broker, "--listen", f"{GROUND_IP}:0", "--metrics-listen", "",
                               "--port-file", port_file, "--insecure"],
                      os.path.join(tmp, "broker.log"))
        wait_for(lambda: file_has(port_file, "grpc_port="), 10, "channel_broker not serving",
                 server)
        with open(port_file) as f:
            port = dict(line.strip().split("=", 1) for line in f if "=" in line)["grpc_port"]
        return server, ["--engine", "grpc", "--channel", f"{GROUND_IP}:{port}"]
    qos = "reliable" if engine == "dds-reliable" else "best-effort"
    return None, ["--engine", "dds", "--dds-qos", qos]


def run_engine(engine, condition, args, tmp):
    server, reach = start_server(engine, args, tmp)
    common = ["--rate-hz", str(args.rate_hz), "--seconds", str(args.seconds), "--topic", TOPIC]
    base = [args.probe, *reach]
    env_g = env_v = None
    if engine.startswith("dds"):
        env_g = dict(os.environ, CYCLONEDDS_URI=dds_config(
            os.path.join(tmp, "dds-ground.xml"), GROUND_IF, VEHICLE_IP, args.dds_discovery))
        env_v = dict(os.environ, CYCLONEDDS_URI=dds_config(
            os.path.join(tmp, "dds-vehicle.xml"), VEHICLE_IF, GROUND_IP, args.dds_discovery))
    tag = f"{engine}-{condition}"
    sub = Proc(GROUND, base + ["--role", "sub", *common],
               os.path.join(tmp, f"{tag}-sub.log"), env_g)
    procs = [p for p in (server, sub) if p]
    try:
        if sub.line(30) != "ready":
            raise RuntimeError(f"{tag}: subscriber not ready:\n{sub.tail()}")
        pub = Proc(VEHICLE, base + ["--role", "pub", *common],
                   os.path.join(tmp, f"{tag}-pub.log"), env_v)
        procs.append(pub)
        if pub.line(60) != "sending":
            raise RuntimeError(f"{tag}: publisher did not start:\n{pub.tail()}")
        t0, bytes0 = time.monotonic(), link_bytes()
        server_cpu0 = cpu_seconds(server.popen.pid) if server else None
        pub_result = pub.json_line(args.seconds + 60)
        t1, bytes1 = time.monotonic(), link_bytes()
        server_cpu1 = cpu_seconds(server.popen.pid) if server else None
        if pub_result is None:
            raise RuntimeError(f"{tag}: no result from the publisher:\n{pub.tail()}")
        pub.popen.wait(30)
        # The subscriber ends once it has every sample; the rest are lost.
        try:
            sub.popen.wait(3)
        except subprocess.TimeoutExpired:
            os.killpg(sub.popen.pid, signal.SIGTERM)
        sub_result = sub.json_line(10)
        if sub_result is None:
            raise RuntimeError(f"{tag}: no result from the subscriber:\n{sub.tail()}")
    finally:
        for p in reversed(procs):
            p.stop()
    window = t1 - t0
    server_pct = None
    if server_cpu0 is not None and server_cpu1 is not None:
        server_pct = 100 * (server_cpu1 - server_cpu0) / window
    return {
        "engine": engine, "condition": condition,
        "sent": pub_result["sent"], "expected": sub_result["expected"],
        "received": sub_result["received"],
        "delivered_pct": 100 * sub_result["received"] / max(1, sub_result["expected"]),
        "latency_ms": sub_result["latency_ms"],
        "link_bytes_per_s": (bytes1 - bytes0) / window,
        "cpu_pct": {
            "pub": 100 * pub_result["cpu_s"] / max(1e-9, pub_result["window_s"]),
            "sub": 100 * sub_result["cpu_s"] / max(1e-9, sub_result["window_s"]),
            "server": server_pct,
        },
        "window_s": window,
    }


def on_sigterm(*_):
    raise RuntimeError("stopped by SIGTERM")


def fmt(x, digits=1):
    return "–" if x is None else f"{x:.{digits}f}"


def table(rows):
    out = ["| Engine | Condition | Delivered % | Latency median ms | p99 ms | max ms | "
           "Link B/s | CPU pub % | CPU sub % | CPU server % |",
           "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lat, cpu = r["latency_ms"], r["cpu_pct"]
        out.append(f"| {r['engine']} | {r['condition']} | {r['delivered_pct']:.2f} | "
                   f"{lat['median']:.2f} | {lat['p99']:.2f} | {lat['max']:.1f} | "
                   f"{r['link_bytes_per_s']:.0f} | {fmt(cpu['pub'])} | {fmt(cpu['sub'])} | "
                   f"{fmt(cpu['server'])} |")
    return "\n".join(out)


def parse_args():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--build-dir", default="build")
    p.add_argument("--seconds", type=float, default=20)
    p.add_argument("--rate-hz", type=float, default=200)
    p.add_argument("--engines", default=",".join(ENGINES))
    p.add_argument("--conditions", default="clean,loss1")
    p.add_argument("--tbf-kbit", type=int, default=256)
    p.add_argument("--dds-discovery", choices=["multicast", "unicast"], default="unicast")
    p.add_argument("--smoke", action="store_true",
                   help="2 s per engine on a clean link; fails below 90 %% delivered")
    p.add_argument("--out", help="also write the figures as JSON here")
    args = p.parse_args()
    if args.smoke:
        args.seconds, args.conditions = 2, "clean"
    args.engines = args.engines.split(",")
    args.conditions = args.conditions.split(",")
    bad = [x for x in args.engines if x not in ENGINES]
    bad += [x for x in args.conditions if x not in CONDITIONS]
    if bad or not 0 < args.seconds <= 3600 or not 0 < args.rate_hz <= 100000:
        p.error(f"unknown engine or condition {bad}, or a value out of range")
    args.build_dir = os.path.abspath(args.build_dir)
    args.probe = os.path.join(args.build_dir, "tests", "bench", "fleet", "engine_probe")
    return args


def main():
    args = parse_args()
    if os.geteuid() != 0:
        print("engine_bench: skipped: network namespaces need root")
        return SKIP
    args.nats_server = shutil.which("nats-server") or shutil.which("/usr/sbin/nats-server")
    if any(e.startswith("nats") for e in args.engines) and not args.nats_server:
        print("engine_bench: skipped: nats-server not found")
        return SKIP
    for path in (args.probe, os.path.join(args.build_dir, "bin", "channel_broker")):
        if not os.access(path, os.X_OK):
            print(f"engine_bench: {path} not built", file=sys.stderr)
            return 1
    # SIGTERM (a ctest timeout) ends the run as a failure: the processes
    # are stopped and the namespaces removed.
    signal.signal(signal.SIGTERM, on_sigterm)
    tmp = tempfile.mkdtemp(prefix="blbench-")
    rows, failed = [], False
    try:
        make_namespaces()
        for condition in args.conditions:
            apply_condition(condition, args.tbf_kbit)
            try:
                for engine in args.engines:
                    rows.append(run_engine(engine, condition, args, tmp))
                    print(f"engine_bench: {engine} {condition}: "
                          f"{rows[-1]['delivered_pct']:.1f} % delivered", file=sys.stderr)
            finally:
                clear_condition()
    except Skip as e:
        print(f"engine_bench: skipped: {e}")
        return SKIP
    except RuntimeError as e:
        print(f"engine_bench: {e}", file=sys.stderr)
        failed = True
    finally:
        for p in Proc.started:
            p.stop()
        remove_namespaces()
    print(f"{len(args.conditions) * len(args.engines)} runs of {args.seconds:g} s at "
          f"{args.rate_hz:g} Hz, {TOPIC} (behaviorlib.v1.PoseStamped in an Any)\n")
    print(table(rows))
    if args.out:
        with open(args.out, "w") as f:
            json.dump({"seconds": args.seconds, "rate_hz": args.rate_hz, "rows": rows}, f,
                      indent=2)
    if args.smoke:
        for r in rows:
            if r["delivered_pct"] <= 90:
                print(f"engine_bench: {r['engine']} delivered only "
                      f"{r['delivered_pct']:.1f} %", file=sys.stderr)
                failed = True
    if failed:
        print(f"engine_bench: logs in {tmp}", file=sys.stderr)
        return 1
    shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
