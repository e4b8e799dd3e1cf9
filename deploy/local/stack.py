"""The processes of the local stack: started in dependency order on loopback
with free ports (--listen 127.0.0.1:0 and --port-file), health checked over
the gRPC health protocol, one log file each, stopped in reverse order
(SIGTERM, wait, SIGKILL after a timeout).

Each process runs in a session of its own, so a Ctrl-C at the terminal
reaches only the launcher, which then stops them in order.
"""

import json
import os
import signal
import subprocess
import time

import rpc

_CLOCK_TICKS = os.sysconf("SC_CLK_TCK")


class StartError(RuntimeError):
    """A process did not start, or did not become healthy."""


class Process:
    """One server process started with --port-file; its output goes to
    <run-dir>/logs/<name>.log."""

    def __init__(self, name, argv, run_dir, role, robot_id="", system=""):
        self.name = name
        self.role = role  # Prometheus job: channel_broker, simulator, coordinator, behavior_system
        self.robot_id = robot_id
        # The system's own name (a behavior system's binary), which the
        # process name extends with the robot when several robots run.
        self.system = system or name
        self.port_file = os.path.join(run_dir, "ports", name + ".ports")
        self.log_path = os.path.join(run_dir, "logs", name + ".log")
        self.argv = list(argv) + ["--port-file", self.port_file]
        self.process = None
        self.grpc_port = 0
        self.metrics_port = 0
        self.exit_code = None

    @property
    def pid(self):
        return self.process.pid if self.process else None

    @property
    def address(self):
        return f"127.0.0.1:{self.grpc_port}"

    @property
    def metrics_address(self):
        return f"127.0.0.1:{self.metrics_port}" if self.metrics_port else ""

    def _log_tail(self, lines=15):
        try:
            with open(self.log_path, errors="replace") as f:
                return "".join(f.readlines()[-lines:])
        except OSError:
            return ""

    def start(self, timeout_s=20.0, on_spawn=None):
        """Starts the process and waits until it reports its ports and its
        gRPC health check answers SERVING. `on_spawn` is called once the
        process exists."""
        os.makedirs(os.path.dirname(self.port_file), exist_ok=True)
        os.makedirs(os.path.dirname(self.log_path), exist_ok=True)
        with open(self.log_path, "wb") as log:
            log.write(("$ " + " ".join(self.argv) + "\n").encode())
            log.flush()
            self.process = subprocess.Popen(self.argv, stdin=subprocess.DEVNULL, stdout=log,
                                            stderr=subprocess.STDOUT, start_new_session=True)
        if on_spawn:
            on_spawn()
        deadline = time.monotonic() + timeout_s
        health = "no answer"
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                self.exit_code = self.process.returncode
                raise StartError(f"{self.name} exited with code {self.exit_code} before it was "
                                 f"ready; {self.log_path} ends with:\n{self._log_tail()}")
            if not self.grpc_port and os.path.exists(self.port_file):
                ports = {}
                with open(self.port_file) as f:
                    for line in f:
                        key, _, value = line.strip().partition("=")
                        if value:
                            ports[key] = int(value)
                self.grpc_port = ports.get("grpc_port", 0)
                self.metrics_port = ports.get("metrics_port", 0)
            if self.grpc_port:
                try:
                    health = rpc.health_status(self.address, timeout=1.0)
                    if health == "SERVING":
                        return
                except rpc.grpc.RpcError as error:
                    health = error.code().name
            time.sleep(0.02)
        raise StartError(f"{self.name} was not healthy within {timeout_s} s (health: {health}); "
                         f"log {self.log_path}")

    def running(self):
        return self.process is not None and self.process.poll() is None

    def proc_stats(self):
        """Memory and CPU time from /proc/<pid> while it runs, else None."""
        if not self.running():
            return None
        try:
            with open(f"/proc/{self.pid}/status") as f:
                status = dict(line.split(":", 1) for line in f if ":" in line)
            with open(f"/proc/{self.pid}/stat") as f:
                # Fields after the command name (which may hold spaces).
                fields = f.read().rsplit(")", 1)[1].split()
        except OSError:
            return None

        def kib(key):
            return int(status[key].split()[0]) if key in status else 0

        return {
            "rss_kib": kib("VmRSS"),
            "peak_rss_kib": kib("VmHWM"),
            "threads": int(status.get("Threads", "0").strip() or 0),
            # utime and stime are fields 14 and 15 of stat (1-based).
            "cpu_user_s": int(fields[11]) / _CLOCK_TICKS,
            "cpu_system_s": int(fields[12]) / _CLOCK_TICKS,
        }

    def stop(self, timeout_s=10.0):
        """SIGTERM, wait up to timeout_s, then SIGKILL; the exit code
        (negative: the signal that ended it)."""
        if self.process is None:
            return None
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            try:
                self.process.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        self.exit_code = self.process.returncode
        return self.exit_code


class Stack:
    """Processes in start order; stop() stops them in reverse order."""

    def __init__(self, run_dir):
        self.run_dir = run_dir
        self.processes = []

    def start(self, process, timeout_s=20.0):
        self.processes.append(process)
        process.start(timeout_s, on_spawn=self._write_pids)
        return process

    def find(self, name):
        return next((p for p in self.processes if p.name == name), None)

    def _write_pids(self):
        path = os.path.join(self.run_dir, "pids.json")
        with open(path + ".tmp", "w") as f:
            json.dump({p.name: p.pid for p in self.processes if p.pid}, f, indent=1)
        os.replace(path + ".tmp", path)

    def write_prometheus_targets(self):
        """Prometheus file-based service discovery: one target per metrics
        port, labelled job (the process's role), system (the process name
        without its robot suffix) and robot. Returns the file's path."""
        targets = []
        for p in self.processes:
            if not p.metrics_port:
                continue
            labels = {"job": p.role, "system": p.system}
            if p.robot_id:
                labels["robot"] = p.robot_id
            targets.append({"targets": [p.metrics_address], "labels": labels})
        path = os.path.join(self.run_dir, "prometheus_targets.json")
        with open(path + ".tmp", "w") as f:
            json.dump(targets, f, indent=2)
            f.write("\n")
        os.replace(path + ".tmp", path)  # Prometheus may read it at any time
        return path

    def stop(self, timeout_s=10.0, report=print):
        """Stops every process in reverse start order; True when each exited
        with code 0."""
        clean = True
        for p in reversed(self.processes):
            if p.process is None:
                continue
            was_running = p.running()
            code = p.stop(timeout_s)
            how = "exited" if was_running else "had already exited"
            report(f"  {p.name:<40} {how} with code {code}")
            clean = clean and code == 0
        self._write_pids()
        return clean
