#!/usr/bin/env python3
"""Starts the behaviorlib stack on this machine, without Docker.

Starts the data channel broker and the behavior systems on loopback (ports
chosen free at run time unless given), prints where each one listens, and
either runs the demo mission (--demo) or serves until Ctrl-C.

    deploy/local/launch.py --build-dir build --demo
    deploy/local/launch.py --build-dir build          # serve until Ctrl-C

Uses only the Python standard library.
"""
import argparse
import json
import shutil
import os
import signal
import subprocess
import sys
import tempfile
import time


CONFIG_DIR = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "config")
# frequency_hz of WAIT in deploy/config/basic_quadrotor_behaviors.yaml
CONFIGURED_WAIT_HZ = 50


class Service:
    """One server process started with --port-file."""

    def __init__(self, name, argv, port_dir):
        self.name = name
        self.port_file = os.path.join(port_dir, name + ".ports")
        self.argv = argv + ["--port-file", self.port_file]
        self.process = None
        self.grpc_port = 0
        self.metrics_port = 0

    def start(self, timeout_s=15.0):
        self.process = subprocess.Popen(self.argv)
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise RuntimeError(f"{self.name} exited with code {self.process.returncode} "
                                   f"before it was ready: {' '.join(self.argv)}")
            if os.path.exists(self.port_file):
                ports = dict(line.strip().split("=", 1)
                             for line in open(self.port_file) if "=" in line)
                self.grpc_port = int(ports.get("grpc_port", 0))
                self.metrics_port = int(ports.get("metrics_port", 0))
                if self.grpc_port:
                    return
            time.sleep(0.02)
        raise RuntimeError(f"{self.name} did not report its ports within {timeout_s} s")

    @property
    def address(self):
        return f"127.0.0.1:{self.grpc_port}"

    def stop(self, timeout_s=10.0):
        """SIGTERM, wait; returns the exit code (killed: -9)."""
        if self.process is None or self.process.poll() is not None:
            return self.process.returncode if self.process else 0
        self.process.send_signal(signal.SIGTERM)
        try:
            return self.process.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()
            return -9


def binary(build_dir, relative):
    path = os.path.join(build_dir, relative)
    if not os.access(path, os.X_OK):
        sys.exit(f"launch.py: {path} not found; build first (cmake --build {build_dir})")
    return path


def run_demo(build_dir, system):
    """WAIT activated end to end through the generic API; events printed."""
    ctl = binary(build_dir, "coordinator/cli/behaviorctl")
    target = ["--target", system.address]
    print("\n== behaviors hosted by basic_quadrotor_behaviors ==", flush=True)
    listing = json.loads(subprocess.run([ctl, *target, "list"], check=True,
                                        capture_output=True, text=True).stdout)
    for b in listing["behaviors"]:
        params = ", ".join(f"{p['name']} [{p.get('unit', '')}]" for p in b.get("parameters", []))
        print(f"  {b['name']:<6} {b.get('service', '')}: {b.get('description', '')} ({params}; "
              f"{b.get('frequency_hz')} Hz)")
    wait = next((b for b in listing["behaviors"] if b["name"] == "WAIT"), None)
    if wait is None or wait.get("frequency_hz") != CONFIGURED_WAIT_HZ:
        raise RuntimeError("WAIT is missing or did not take its frequency from --config")

    print("\n== events (WatchEvents) ==", flush=True)
    watcher = subprocess.Popen([ctl, *target, "watch", "--until-finished", "WAIT",
                                "--timeout-s", "30"], stdout=subprocess.PIPE, text=True)
    first = watcher.stdout.readline()  # the stream's start message: subscribed
    print("  " + first.strip(), flush=True)
    print("\n== activate WAIT {duration_s: 2} ==", flush=True)
    activated = subprocess.run([ctl, *target, "activate", "WAIT", '{"duration_s": 2}'],
                               check=True, capture_output=True, text=True).stdout
    print("  " + activated.strip(), flush=True)
    finished = None
    for line in watcher.stdout:
        print("  " + line.strip(), flush=True)
        event = json.loads(line).get("event", {})
        if "finished" in event:
            finished = event
    watcher.wait(timeout=10)
    if not finished or finished["finished"]["cause"] != "TERMINATION_CAUSE_GOAL_ACHIEVED":
        raise RuntimeError("WAIT did not finish with GOAL_ACHIEVED")
    print(f"\nWAIT finished: {finished['finished']['cause']} after "
          f"{finished['finished'].get('active_duration', '?')} "
          f"({finished['finished'].get('message', '')})", flush=True)


def main():
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--build-dir", default="build")
    parser.add_argument("--robot-id", default="drone1")
    parser.add_argument("--demo", action="store_true",
                        help="run the demo mission, then stop everything")
    args = parser.parse_args()
    build_dir = os.path.abspath(args.build_dir)

    port_dir = tempfile.mkdtemp(prefix="behaviorlib-local-")
    broker = Service("channel_broker",
                     [binary(build_dir, "services/channel/channel_broker"),
                      "--listen", "127.0.0.1:0", "--metrics-listen", "127.0.0.1:0"], port_dir)
    system = None
    services = [broker]
    status = 0
    try:
        broker.start()
        system = Service("basic_quadrotor_behaviors",
                         [binary(build_dir,
                                 "services/basic_quadrotor_behaviors/basic_quadrotor_behaviors"),
                          "--robot-id", args.robot_id, "--listen", "127.0.0.1:0",
                          "--metrics-listen", "127.0.0.1:0", "--channel", broker.address,
                          "--config", os.path.join(CONFIG_DIR, "basic_quadrotor_behaviors.yaml")],
                         port_dir)
        services.append(system)
        system.start()
        print("\n== running ==")
        for s in services:
            print(f"  {s.name:<26} gRPC {s.address}   metrics "
                  f"http://127.0.0.1:{s.metrics_port}/metrics")
        sys.stdout.flush()
        if args.demo:
            run_demo(build_dir, system)
        else:
            print("Ctrl-C stops everything.")
            signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM})
            signal.sigwait({signal.SIGINT, signal.SIGTERM})
    except (RuntimeError, subprocess.CalledProcessError) as e:
        print(f"launch.py: {e}", file=sys.stderr)
        status = 1
    finally:
        print("\n== stopping ==")
        for s in reversed(services):
            code = s.stop()
            print(f"  {s.name} exited with code {code}")
            if code != 0:
                status = status or 1
        shutil.rmtree(port_dir, ignore_errors=True)
    return status


if __name__ == "__main__":
    sys.exit(main())
