"""The processes of the local stack: started in dependency order on loopback
with free ports (--listen 127.0.0.1:0 and --port-file), health checked over
the gRPC health protocol, one log file each, stopped in reverse order
(SIGTERM, wait, SIGKILL after a timeout).

Each process runs in a session of its own, so a Ctrl-C at the terminal
reaches only the launcher, which then stops them in order. Each also gets
SIGTERM when the launcher dies, even by SIGKILL (popen_with_launcher): no
stack outlives its launcher.

A Supervisor thread applies a RestartPolicy (compose's `restart:`) to a
process that exits while the stack runs: with "on-failure" one that failed
is started again with the same arguments, on the ports it had (the others
dial them), its output appended to its log and pids.json rewritten.
"""

import json
import os
import queue
import signal
import ssl
import subprocess
import threading
import time
import urllib.request
from concurrent.futures import Future

import rpc

_CLOCK_TICKS = os.sysconf("SC_CLK_TCK")


class StartError(RuntimeError):
    """A process did not start, or did not become healthy."""


# Sets the parent-death signal, then execs the process (util-linux, which
# every Debian system has). Not a preexec_fn: that makes Python fork()
# instead of vfork(), and fork() runs the gRPC library's fork handlers in a
# launcher with gRPC threads, which crashed it (SIGSEGV) now and then.
_DIE_WITH_LAUNCHER = ["setpriv", "--pdeathsig", "TERM", "--"]


class _Spawner:
    """Forks from one thread that lives as long as the launcher. Linux sends
    the parent-death signal when the *thread* that forked a child ends, not
    the process: a process the supervisor's thread restarted would be
    stopped as soon as the supervision ends, before the stack's ordered
    stop. Every fork goes through here instead (a daemon thread, which ends
    only with the launcher)."""

    def __init__(self):
        self._lock = threading.Lock()
        self._requests = queue.SimpleQueue()
        self._thread = None

    def popen(self, argv, **kwargs):
        with self._lock:
            if self._thread is None:
                self._thread = threading.Thread(target=self._run, name="spawner", daemon=True)
                self._thread.start()
        done = Future()
        self._requests.put((argv, kwargs, done))
        return done.result()

    def _run(self):
        while True:
            argv, kwargs, done = self._requests.get()
            try:
                done.set_result(subprocess.Popen(argv, **kwargs))
            except BaseException as error:  # handed to the caller
                done.set_exception(error)


_SPAWNER = _Spawner()


def popen_with_launcher(argv, **kwargs):
    """subprocess.Popen(argv, **kwargs), for a child that gets SIGTERM when
    the launcher dies, however it dies (unless it dies in the instant
    between the fork and setpriv's arming the signal)."""
    return _SPAWNER.popen(_DIE_WITH_LAUNCHER + list(argv), **kwargs)


def read_ports(path):
    """The ports a process wrote to its --port-file ({"grpc_port": ...,
    "metrics_port": ...})."""
    ports = {}
    with open(path) as f:
        for line in f:
            key, _, value = line.strip().partition("=")
            if value:
                ports[key] = int(value)
    return ports


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
        self.restarts = 0  # how many times the supervisor started it again
        self.restart_times = []  # time.monotonic() of each restart

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

    def start(self, timeout_s=20.0, on_spawn=None, cancel=None):
        """Starts the process and waits until it reports its ports and its
        gRPC health check answers SERVING. `on_spawn` is called once the
        process exists; `cancel` (a threading.Event), once set, ends the
        wait with a StartError. Once healthy the process keeps its ports:
        starting it again (a restart) serves on the same ones and appends to
        its log."""
        restarting = self.process is not None
        if restarting:
            self.grpc_port = self.metrics_port = 0
        # Its new port file says when it is listening (a reused run
        # directory holds the last run's).
        if os.path.exists(self.port_file):
            os.remove(self.port_file)
        os.makedirs(os.path.dirname(self.port_file), exist_ok=True)
        os.makedirs(os.path.dirname(self.log_path), exist_ok=True)
        with open(self.log_path, "ab" if restarting else "wb") as log:
            log.write(("$ " + " ".join(self.argv) + "\n").encode())
            log.flush()
            self.process = popen_with_launcher(self.argv, stdin=subprocess.DEVNULL, stdout=log,
                                               stderr=subprocess.STDOUT, start_new_session=True)
        if on_spawn:
            on_spawn()
        deadline = time.monotonic() + timeout_s
        health = "no answer"
        while time.monotonic() < deadline:
            if cancel is not None and cancel.is_set():
                raise StartError(f"{self.name}: start cancelled")
            if self.process.poll() is not None:
                self.exit_code = self.process.returncode
                raise StartError(f"{self.name} exited with {self.exit_description()} before it "
                                 f"was ready; {self.log_path} ends with:\n{self._log_tail()}")
            ready, health = self._probe(health)
            if ready:
                self._keep_ports()
                return
            time.sleep(0.02)
        raise StartError(f"{self.name} was not healthy within {timeout_s} s (health: {health}); "
                         f"log {self.log_path}")

    def _probe(self, health):
        """(ready, what the health check said): its ports reported and its
        gRPC health check SERVING."""
        if not self.grpc_port and os.path.exists(self.port_file):
            ports = read_ports(self.port_file)
            self.grpc_port = ports.get("grpc_port", 0)
            self.metrics_port = ports.get("metrics_port", 0)
        if not self.grpc_port:
            return False, health
        try:
            health = rpc.health_status(self.address, timeout=1.0)
        except rpc.grpc.RpcError as error:
            health = error.code().name
        return health == "SERVING", health

    def _keep_ports(self):
        """Rewrites the --listen and --metrics-listen arguments to the ports
        bound (a first start asks for port 0): a restart then serves where
        the other processes dial."""
        bound = {"--listen": self.grpc_port, "--metrics-listen": self.metrics_port}
        for i, arg in enumerate(self.argv[:-1]):
            if bound.get(arg):
                host = self.argv[i + 1].rpartition(":")[0]
                self.argv[i + 1] = f"{host}:{bound[arg]}"

    def running(self):
        return self.process is not None and self.process.poll() is None

    def exit_description(self):
        """How the process ended: "code 1", "signal 9 (SIGKILL)"."""
        code = self.process.returncode
        if code is None or code >= 0:
            return f"code {code}"
        try:
            return f"signal {-code} ({signal.Signals(-code).name})"
        except ValueError:
            return f"signal {-code}"

    def log_note(self, text):
        """Appends a line of the launcher's to the process's log."""
        with open(self.log_path, "a") as log:
            log.write(f"launch.py: {text}\n")

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

    def restart(self, process, timeout_s=20.0, cancel=None):
        """Starts a process of the stack that exited again, with the same
        arguments and ports; pids.json then names its new pid."""
        process.start(timeout_s, on_spawn=self._write_pids, cancel=cancel)

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
            restarts = (f"; restarted {p.restarts} time{'s' if p.restarts > 1 else ''}"
                        if p.restarts else "")
            report(f"  {p.name:<40} {how} with code {code}{restarts}")
            clean = clean and code == 0
        self._write_pids()
        return clean


class RestartPolicy:
    """compose's `restart:` for the stack's processes. "on-failure": a
    process that exits with a non-zero code or is killed by a signal is
    started again, after a delay that doubles with each restart of the last
    `window_s` (from `first_delay_s` up to `max_delay_s`); after
    `max_restarts` restarts within `window_s` it is not, and the launcher
    gives up. One that exits with code 0 is left stopped. "no": no process is
    restarted, and any exit stops the stack."""

    MODES = ("on-failure", "no")

    def __init__(self, mode="on-failure", max_restarts=5, window_s=60.0, first_delay_s=0.5,
                 max_delay_s=5.0):
        if mode not in self.MODES:
            raise ValueError(f"restart policy {mode!r} is not one of {', '.join(self.MODES)}")
        self.mode = mode
        self.max_restarts = max_restarts
        self.window_s = window_s
        self.first_delay_s = first_delay_s
        self.max_delay_s = max_delay_s

    def leaves_stopped(self, process):
        """True for a process that exited cleanly and stays so (on-failure)."""
        return self.mode == "on-failure" and process.process.returncode == 0

    def _recent(self, process, now):
        return [t for t in process.restart_times if now - t < self.window_s]

    def refusal(self, process, now):
        """Why `process`, which exited, is not restarted; "" when it is."""
        if self.mode == "no":
            return "--restart no"
        if len(self._recent(process, now)) >= self.max_restarts:
            return f"restarted {self.max_restarts} times within {self.window_s:g} s already"
        return ""

    def delay_s(self, process, now):
        """How long to wait before restarting `process`."""
        return min(self.first_delay_s * 2 ** len(self._recent(process, now)), self.max_delay_s)


class Supervisor:
    """Watches the stack's processes on a thread of its own and applies the
    restart policy to one that exits: restarts it (Stack.restart, after the
    policy's delay), prints and appends to its log why, or gives up (then
    `failure` says why and check() raises). Call stop() before Stack.stop():
    a process stopped on purpose is never restarted.

        supervisor = Supervisor(stack, RestartPolicy("on-failure"), say)
        supervisor.start()
        ...
        supervisor.check()   # StartError once it gave up
        supervisor.stop()
        stack.stop()
    """

    def __init__(self, stack, policy, report=print, poll_s=0.2, start_timeout_s=20.0):
        self._stack = stack
        self._policy = policy
        self._report = report
        self._poll_s = poll_s
        self._start_timeout_s = start_timeout_s
        self._stopping = threading.Event()
        self._left_stopped = set()  # names of processes that exited cleanly
        self._thread = threading.Thread(target=self._run, name="supervisor", daemon=True)
        self.failure = ""

    def start(self):
        self._thread.start()

    def stop(self):
        """Ends the supervision; waits for a restart in progress to give up."""
        self._stopping.set()
        if self._thread.is_alive():
            self._thread.join()

    def check(self):
        """Raises StartError once the supervisor gave up on a process."""
        if self.failure:
            raise StartError(self.failure)

    def _run(self):
        while not self._stopping.wait(self._poll_s) and not self.failure:
            for process in list(self._stack.processes):
                if self._stopping.is_set() or self.failure:
                    break
                if (process.process is not None and not process.running()
                        and process.name not in self._left_stopped):
                    self._on_exit(process)

    def _note(self, process, text):
        self._report(f"  {text}")
        process.log_note(text)

    def _on_exit(self, process):
        process.exit_code = process.process.returncode
        exited = f"{process.name} exited with {process.exit_description()}"
        if self._policy.leaves_stopped(process):
            self._left_stopped.add(process.name)
            self._note(process, f"{exited}; not restarted (--restart on-failure)")
            return
        now = time.monotonic()
        refusal = self._policy.refusal(process, now)
        if refusal:
            self.failure = f"{exited}; not restarted ({refusal}); log {process.log_path}"
            self._note(process, f"{exited}; not restarted ({refusal}): giving up")
            return
        delay_s = self._policy.delay_s(process, now)
        process.restarts += 1
        process.restart_times.append(now)
        self._note(process, f"{exited}; restarting in {delay_s:g} s (restart {process.restarts})")
        if not self._stopping.wait(delay_s):
            self._restart(process)

    def _restart(self, process):
        try:
            self._stack.restart(process, self._start_timeout_s, cancel=self._stopping)
        except StartError as error:
            self._note(process, f"restart {process.restarts} of {process.name} failed: {error}")
            if process.running() and not self._stopping.is_set():
                process.stop()  # not healthy: the next poll sees it exited
            return
        self._note(process, f"{process.name} restarted: pid {process.pid}, gRPC "
                            f"{process.address}")


class HttpProcess(Process):
    """A process that serves HTTP, not gRPC (the console): ready once its
    port file names its http_port and GET /healthz answers 200. Its
    `address` is the HTTP one; it has no metrics. With `ca_file` it serves
    HTTPS with a certificate from that CA."""

    def __init__(self, name, argv, run_dir, role, ca_file=None):
        super().__init__(name, argv, run_dir, role)
        self.http_port = 0
        self.context = ssl.create_default_context(cafile=ca_file) if ca_file else None

    @property
    def address(self):
        return f"127.0.0.1:{self.http_port}"

    @property
    def url(self):
        return f"{'https' if self.context else 'http'}://{self.address}/"

    def _probe(self, health):
        if not self.http_port and os.path.exists(self.port_file):
            self.http_port = read_ports(self.port_file).get("http_port", 0)
        if not self.http_port:
            return False, health
        try:
            with urllib.request.urlopen(self.url + "healthz", timeout=1.0,
                                        context=self.context) as reply:
                return reply.status == 200, f"HTTP {reply.status}"
        except OSError as error:
            return False, str(error)

    def _keep_ports(self):
        for i, arg in enumerate(self.argv[:-1]):
            if arg == "--listen" and self.http_port:
                host = self.argv[i + 1].rpartition(":")[0]
                self.argv[i + 1] = f"{host}:{self.http_port}"
