"""The local launcher's supervisor (deploy/local/stack.py: Supervisor,
RestartPolicy) on stand-in servers, without the built binaries: a process
killed is restarted on its ports (its --listen rewritten), its log appended
to and pids.json rewritten; one that exits 0 is left stopped; one that keeps
crashing is restarted with a growing delay until the cap, then the
supervisor gives up; with "no" the first exit is a failure; stop() cancels a
restart in progress and nothing is restarted afterwards; a launcher killed
with SIGKILL takes its processes down, the one its supervisor restarted too.

    /usr/bin/python3 tests/deploy/local_supervisor_test.py

The stand-in server is this file run with --serve: it listens where
--listen says (port 0: a free one), answers the gRPC health check SERVING,
writes its --port-file as the stack's servers do, and exits as told.
"""

import argparse
import os
import shutil
import signal
import sys
import tempfile
import time
import unittest

REPO = os.path.abspath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", ".."))
sys.path.insert(0, os.path.join(REPO, "deploy", "local"))
from stack import Process, RestartPolicy, Stack, StartError, Supervisor  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import deploy_support as ds  # noqa: E402

# Short delays, so that the cap is reached in about a second.
FAST = {"max_restarts": 3, "window_s": 60.0, "first_delay_s": 0.1, "max_delay_s": 0.3}


def serve(argv):
    """The stand-in server (see the module's docstring)."""
    from concurrent import futures

    import grpc

    parser = argparse.ArgumentParser()
    parser.add_argument("--listen", required=True)
    parser.add_argument("--metrics-listen", default="")
    parser.add_argument("--port-file", required=True)
    parser.add_argument("--exit-after-s", type=float, default=0.0)
    parser.add_argument("--exit-code", type=int, default=0)
    args = parser.parse_args(argv)
    server = grpc.server(futures.ThreadPoolExecutor(max_workers=2))
    server.add_generic_rpc_handlers((grpc.method_handlers_generic_handler(
        "grpc.health.v1.Health",
        {"Check": grpc.unary_unary_rpc_method_handler(lambda request, context: b"\x08\x01")}),))
    port = server.add_insecure_port(args.listen)
    server.start()
    with open(args.port_file + ".tmp", "w") as f:
        f.write(f"grpc_port={port}\nmetrics_port=0\n")
    os.replace(args.port_file + ".tmp", args.port_file)
    print(f"serving on port {port}", flush=True)
    signal.signal(signal.SIGTERM, lambda *_: os._exit(0))
    if args.exit_after_s:
        time.sleep(args.exit_after_s)
        os._exit(args.exit_code)
    while True:
        time.sleep(1)


def launcher(run_dir):
    """A launcher stand-in (--launcher RUN_DIR): starts two stand-in servers,
    supervises them (on-failure), says "ready" and waits to be killed."""
    stack = Stack(run_dir)
    for name in ("first", "second"):
        argv = [sys.executable, os.path.abspath(__file__), "--serve", "--listen", "127.0.0.1:0"]
        stack.start(Process(name, argv, run_dir, "test"))
    supervisor = Supervisor(stack, RestartPolicy("on-failure", **FAST), print, poll_s=0.05,
                            start_timeout_s=10.0)
    supervisor.start()
    print("ready", flush=True)
    while True:
        time.sleep(1)


class SupervisorTest(unittest.TestCase):
    def setUp(self):
        self.run_dir = tempfile.mkdtemp(prefix="local-supervisor-test-")
        self.stack = Stack(self.run_dir)
        self.said = []
        self.supervisor = None

    def tearDown(self):
        if self.supervisor is not None:
            self.supervisor.stop()
        self.stack.stop(timeout_s=2.0, report=lambda _: None)
        shutil.rmtree(self.run_dir, ignore_errors=True)

    def _start(self, name, *extra):
        argv = [sys.executable, os.path.abspath(__file__), "--serve", "--listen", "127.0.0.1:0",
                "--metrics-listen", "127.0.0.1:0", *extra]
        return self.stack.start(Process(name, argv, self.run_dir, "test"))

    def _supervise(self, mode="on-failure"):
        self.supervisor = Supervisor(self.stack, RestartPolicy(mode, **FAST), self.said.append,
                                     poll_s=0.05, start_timeout_s=10.0)
        self.supervisor.start()

    def _log(self, process):
        with open(process.log_path) as f:
            return f.read()

    def test_killed_process_restarts_on_its_port(self):
        server = self._start("server")
        other = self._start("other")
        port, pid, other_pid = server.grpc_port, server.pid, other.pid
        self.assertIn(f"127.0.0.1:{port}", server.argv)
        self._supervise()
        os.kill(pid, signal.SIGKILL)
        ds.wait_for(lambda: server.pid != pid and server.running()
                    and any("server restarted" in line for line in self.said), 10,
                    "the restart")
        self.assertEqual(server.grpc_port, port)
        self.assertEqual(server.restarts, 1)
        self.assertEqual(self.said[0],
                         "  server exited with signal 9 (SIGKILL); restarting in 0.1 s "
                         "(restart 1)")
        self.assertEqual(ds.read_port_file(server.port_file)["grpc_port"], port)
        with open(os.path.join(self.run_dir, "pids.json")) as f:
            self.assertEqual(f.read().count(str(server.pid)), 1)
        log = self._log(server)
        self.assertEqual(log.count("$ "), 2, log)
        self.assertIn(f"--listen 127.0.0.1:{port} ", log.split("launch.py:")[1])
        self.assertEqual((other.pid, other.restarts), (other_pid, 0))
        self.assertEqual(self.supervisor.failure, "")

    def test_clean_exit_is_left_stopped(self):
        server = self._start("server", "--exit-after-s", "0.3", "--exit-code", "0")
        self._supervise()
        ds.wait_for(lambda: self.said, 10, "the supervisor's note")
        time.sleep(0.3)
        self.assertEqual(self.said, ["  server exited with code 0; not restarted "
                                     "(--restart on-failure)"])
        self.assertFalse(server.running())
        self.assertEqual(server.restarts, 0)
        self.supervisor.check()  # no failure

    def test_crash_loop_gives_up_after_the_cap(self):
        server = self._start("server", "--exit-after-s", "0.2", "--exit-code", "3")
        self._supervise()
        ds.wait_for(lambda: self.supervisor.failure, 20, "the supervisor giving up")
        self.assertEqual(server.restarts, FAST["max_restarts"])
        delays = [line.split("restarting in ")[1].split(" ")[0] for line in self.said
                  if "restarting in" in line]
        self.assertEqual(delays, ["0.1", "0.2", "0.3"])
        self.assertIn("server exited with code 3; not restarted (restarted 3 times within 60 s "
                      "already)", self.supervisor.failure)
        with self.assertRaises(StartError):
            self.supervisor.check()

    def test_restart_no_fails_at_the_first_exit(self):
        server = self._start("server")
        self._supervise("no")
        os.kill(server.pid, signal.SIGKILL)
        ds.wait_for(lambda: self.supervisor.failure, 10, "the failure")
        self.assertIn("not restarted (--restart no)", self.supervisor.failure)
        self.assertEqual(server.restarts, 0)

    def test_stop_cancels_a_restart(self):
        server = self._start("server")
        pid = server.pid
        self.supervisor = Supervisor(self.stack, RestartPolicy(first_delay_s=5.0),
                                     self.said.append, poll_s=0.05)
        self.supervisor.start()
        os.kill(pid, signal.SIGKILL)
        ds.wait_for(lambda: self.said, 10, "the restart's note")
        started = time.monotonic()
        self.supervisor.stop()
        self.assertLess(time.monotonic() - started, 1.0, "stop() waited for the delay")
        self.assertEqual(server.pid, pid, "restarted after stop()")

    def test_a_killed_launcher_takes_its_processes_down(self):
        # Linux's parent-death signal follows the thread that forked: the
        # process the supervisor's thread restarted is the one to check.
        import json
        import subprocess
        output = os.path.join(self.run_dir, "launcher.out")
        with open(output, "w") as out:
            stand_in = subprocess.Popen([sys.executable, os.path.abspath(__file__), "--launcher",
                                         self.run_dir], stdout=out, stderr=subprocess.STDOUT,
                                        stdin=subprocess.DEVNULL)
        try:
            def said(text):
                with open(output) as f:
                    return text in f.read()

            def pids():
                try:
                    with open(os.path.join(self.run_dir, "pids.json")) as f:
                        return json.load(f)
                except (OSError, ValueError):
                    return {}

            ds.wait_for(lambda: said("ready"), 30, "the launcher's two servers")
            first, second = pids()["first"], pids()["second"]
            os.kill(second, signal.SIGKILL)
            ds.wait_for(lambda: said("second restarted"), 30, "the supervisor's restart")
            restarted = pids()["second"]
            self.assertNotEqual(restarted, second)
            self.assertTrue(ds.alive(first) and ds.alive(restarted))

            stand_in.kill()
            stand_in.wait()
            ds.wait_for(lambda: not ds.alive(first) and not ds.alive(restarted), 30,
                        "the launcher's processes to end after it was killed")
        finally:
            if stand_in.poll() is None:
                stand_in.kill()
                stand_in.wait()
            for pid in pids().values():
                if ds.alive(pid):
                    os.kill(pid, signal.SIGKILL)


if __name__ == "__main__":
    if sys.argv[1:2] == ["--serve"]:
        serve(sys.argv[2:])
    if sys.argv[1:2] == ["--launcher"]:
        launcher(sys.argv[2])
    unittest.main(verbosity=2)
