"""Every `command:` of deploy/compose/docker-compose.yml (with
--with-drone2: merged with docker-compose.drone2.yml) runs, with its flags,
against the built binaries, as Compose would start it: in dependency order,
each one's own health check (behaviorctl --target localhost:PORT health, or
the console's --probe localhost:PORT; translated) passing before the next
starts. A renamed or removed flag, a
wrong value, a path missing from the image or a volume, or an address that
does not name a service's port fails here.

Translation from containers to this machine: each service gets a directory
standing for its file system, with the image's directories and files (the
Dockerfile's install tree) and its volumes linked in; absolute container
paths in a command point into it. Listen addresses become 127.0.0.1:0 (the
port picked is read back), and `service:port` addresses become that
service's real loopback port. Prometheus's command runs with Debian's
prometheus against the mounted configuration and rules.

Then: every behavior system is UP at the coordinator (it registered through
--coordinator), Prometheus has loaded the rules and the targets of the
mounted target files, and every process stops cleanly on SIGTERM.

    /usr/bin/python3 tests/deploy/compose_commands_test.py --build-dir build [--with-drone2]
"""

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
import unittest
import urllib.parse
import urllib.request

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import deploy_support as ds  # noqa: E402

sys.path.insert(0, os.path.join(ds.REPO, "deploy", "local"))
import demo  # noqa: E402
import rpc  # noqa: E402

BUILD_DIR = ds.DEFAULT_BUILD_DIR
FILES = [ds.COMPOSE_FILE]
LISTEN_FLAGS = ("--listen", "--metrics-listen", "--web.listen-address")
START_TIMEOUT_S = 20.0
ADDRESS = re.compile(r"(?<![\w.-])([a-z][a-z0-9-]*):(\d+)\b")


class Service:
    """One service of the project, run as a local process."""

    def __init__(self, name, spec, root, log_dir):
        self.name = name
        self.spec = spec
        self.root = root  # stands for the container's "/"
        self.log_path = os.path.join(log_dir, name + ".log")
        self.port_file = os.path.join(log_dir, name + ".ports")
        self.process = None
        self.declared = {}  # flag -> port in the compose file
        self.ports = {}  # flag -> port bound here

    @property
    def grpc_port(self):
        return self.ports.get("--listen")


class ComposeCommandsTest(unittest.TestCase):
    def setUp(self):
        self.tmp = tempfile.mkdtemp(prefix="compose-commands-")
        # The services' certificates, as `scripts/make-dev-certs.sh` makes
        # them for the deployment (BEHAVIORLIB_CERTS_DIR), here in a fresh
        # directory: every process then runs with mutual TLS, as in Compose.
        certs = os.path.join(self.tmp, "certs")
        subprocess.run([os.path.join(ds.REPO, "scripts", "make-dev-certs.sh"), "--out", certs],
                       check=True, capture_output=True)
        self.project = ds.load_compose(*FILES, env={"BEHAVIORLIB_CERTS_DIR": certs})
        # This test's own calls (registrations) as the operator on the host.
        rpc.rc.use_tls(os.path.join(certs, "operator.pem"), os.path.join(certs, "operator.key"),
                       os.path.join(certs, "ca.pem"))
        self.services = {}
        self.started = []

    def tearDown(self):
        for service in reversed(self.started):
            if service.process and service.process.poll() is None:
                service.process.kill()
                service.process.wait()
        shutil.rmtree(self.tmp, ignore_errors=True)

    # --- translation -----------------------------------------------------------

    def _file_system(self, name, spec):
        """A directory standing for the container's file system: the image's
        directories and the service's volumes, linked in."""
        root = os.path.join(self.tmp, "containers", name)
        links = {}
        files = {}
        if (spec.get("command") or [""])[0].startswith(ds.IMAGE_BIN + "/"):
            links.update(ds.image_directories())
            files.update(ds.image_files())
        for volume in spec.get("volumes", []):
            source, target = volume.split(":")[:2]
            if source.startswith(".") or source.startswith("/"):  # a bind mount
                links[target] = os.path.normpath(os.path.join(ds.COMPOSE_DIR, source))
            else:  # a named volume, shared by the services that mount it
                links[target] = os.path.join(self.tmp, "volumes", source)
                os.makedirs(links[target], exist_ok=True)
        # Shallower targets first: a file mounted into an image directory
        # (the coordinator's access policy) then replaces the image's entry.
        for target, source in sorted(links.items(), key=lambda item: item[0].count("/")):
            path = root + target
            os.makedirs(os.path.dirname(path), exist_ok=True)
            if os.path.lexists(path):
                parent = os.path.realpath(os.path.dirname(path))
                assert parent.startswith(os.path.realpath(root) + "/"), (
                    f"{target}: mounted inside a linked directory ({parent})")
                os.remove(path)
            if any(f.startswith(target + "/") for f in files):
                # A directory the image fills from several places (the
                # behavior systems' configurations added to deploy/config):
                # a real directory with each entry linked, never the
                # repository's directory itself.
                os.makedirs(path)
                for entry in os.listdir(source):
                    os.symlink(os.path.join(source, entry), os.path.join(path, entry))
            else:
                os.symlink(source, path)
        for target, source in files.items():
            path = root + target
            os.makedirs(os.path.dirname(path), exist_ok=True)
            os.symlink(source, path)
        os.makedirs(root, exist_ok=True)
        return root

    def _translate_address(self, service, value):
        def replace(match):
            host, port = match.group(1), int(match.group(2))
            if host not in self.services:
                return match.group(0)
            target = self.services[host]
            self.assertEqual(port, target.declared.get("--listen"),
                             f"{service.name}: {match.group(0)} is not {host}'s --listen port")
            self.assertIsNotNone(target.grpc_port,
                                 f"{service.name} names {host}, which is not started before it "
                                 f"(depends_on)")
            return f"127.0.0.1:{target.grpc_port}"

        return ADDRESS.sub(replace, value)

    def _translate(self, service, args):
        out = []
        for arg in args:
            flag, eq, value = arg.partition("=")
            if not eq:
                out.append(arg)
                continue
            if flag in LISTEN_FLAGS:
                service.declared[flag] = ds.port_of(value)
                value = "127.0.0.1:0"
            elif value.startswith("/"):
                value = service.root + value
            else:
                value = self._translate_address(service, value)
            out.append(f"{flag}={value}")
        return out

    def _program(self, spec):
        """(executable, arguments) of a service's command here."""
        command = spec.get("command")
        if not command:
            return None, None
        if command[0].startswith(ds.IMAGE_BIN + "/"):
            program = ds.build_binary(BUILD_DIR, os.path.basename(command[0]))
            self.assertTrue(os.access(program, os.X_OK),
                            f"{program} is not built (build {BUILD_DIR} first)")
            return program, command[1:]
        image = spec["image"].rsplit(":", 1)[0]
        self.assertIn(image, ds.UPSTREAM_PROGRAMS, f"no local program for image {image}")
        program = ds.UPSTREAM_PROGRAMS[image]
        self.assertTrue(os.access(program, os.X_OK), f"{program} is not installed")
        return program, command

    # --- running -------------------------------------------------------------------

    def _start(self, service):
        program, args = self._program(service.spec)
        if program is None:
            return False
        argv = [program, *self._translate(service, args)]
        behaviorlib = program.startswith(BUILD_DIR)
        if behaviorlib:
            argv.append(f"--port-file={service.port_file}")
        with open(service.log_path, "wb") as log:
            log.write(("$ " + " ".join(argv) + "\n").encode())
            log.flush()
            service.process = subprocess.Popen(argv, stdin=subprocess.DEVNULL, stdout=log,
                                               stderr=subprocess.STDOUT, start_new_session=True)
        self.started.append(service)

        def ports_known():
            self._assert_running(service)
            if behaviorlib:
                if not os.path.exists(service.port_file):
                    return False
                ports = ds.read_port_file(service.port_file)
                if "http_port" in ports:  # the console: HTTP(S), no /metrics
                    service.ports = {"--listen": ports["http_port"]}
                    return service.ports["--listen"]
                service.ports = {"--listen": ports.get("grpc_port"),
                                 "--metrics-listen": ports.get("metrics_port")}
                return service.ports["--listen"]
            ports = ds.listening_ports(service.process.pid)
            if ports:
                service.ports = {flag: min(ports) for flag in service.declared}
            return bool(ports)

        ds.wait_for(ports_known, START_TIMEOUT_S, f"{service.name} listening")
        if behaviorlib and "--metrics-listen" in service.declared:
            self.assertTrue(service.ports["--metrics-listen"], f"{service.name}: no /metrics")
        return True

    def _assert_running(self, service):
        if service.process.poll() is not None:
            raise AssertionError(f"{service.name} exited with code {service.process.returncode}; "
                                 f"{service.log_path}:\n{ds.log_tail(service.log_path)}")

    def _health_check(self, service):
        """Runs the service's own health check, translated, until it passes."""
        test = service.spec["healthcheck"]["test"]
        self.assertEqual(test[0], "CMD")
        if test[1] == "wget":  # an upstream image: GET the same path on the real port
            url = urllib.parse.urlsplit(test[-1])
            self.assertEqual(url.hostname, "localhost")
            port = next(p for flag, p in service.ports.items()
                        if service.declared.get(flag) == url.port)

            def check():
                self._assert_running(service)
                with urllib.request.urlopen(f"http://127.0.0.1:{port}{url.path}",
                                            timeout=2) as page:
                    return page.status == 200
        else:
            # behaviorctl's gRPC health check, or the console's --probe.
            self.assertIn(test[1], (f"{ds.IMAGE_BIN}/behaviorctl", f"{ds.IMAGE_BIN}/console"))
            argv = [ds.build_binary(BUILD_DIR, os.path.basename(test[1]))]
            for arg in test[2:]:
                flag, eq, value = arg.partition("=")
                if eq and value.startswith("/"):  # a file in the container
                    arg = f"{flag}={service.root}{value}"
                match = re.fullmatch(r"localhost:(\d+)", arg)
                if match:
                    self.assertEqual(int(match.group(1)), service.declared["--listen"],
                                     f"{service.name}: health check of another port")
                    arg = f"127.0.0.1:{service.grpc_port}"
                argv.append(arg)

            def check():
                self._assert_running(service)
                return subprocess.run(argv, capture_output=True, timeout=10).returncode == 0

        ds.wait_for(check, START_TIMEOUT_S, f"{service.name}: health check {test[1:]}",
                    interval_s=0.2)

    def test_every_command_starts_and_passes_its_health_check(self):
        started = time.monotonic()
        for name in ds.dependency_order(self.project["services"]):
            spec = self.project["services"][name]
            service = Service(name, spec, self._file_system(name, spec), self.tmp)
            self.services[name] = service
            if self._start(service):
                self._health_check(service)
                print(f"  {name}: healthy ({time.monotonic() - started:.1f} s)", flush=True)
            else:
                print(f"  {name}: no command (image default)", flush=True)
        ran = {s.name for s in self.started}
        commands = {n for n, s in self.project["services"].items() if s.get("command")}
        self.assertEqual(ran, commands)

        self._check_registrations()
        self._check_prometheus()
        self._check_clean_stop()

    def _check_registrations(self):
        """Every behavior system registered with the coordinator (through
        its --coordinator) and is UP there."""
        coordinator = rpc.Client(f"127.0.0.1:{self.services['coordinator'].grpc_port}",
                                 [demo.COORDINATOR])
        try:
            by_robot = {}
            for service in self.services.values():
                robot = ds.flag_value(service.spec.get("command") or [], "--robot-id")
                if robot:
                    system = os.path.basename(service.spec["command"][0])
                    by_robot.setdefault(robot, []).append(system)
            self.assertTrue(by_robot)
            for robot, systems in by_robot.items():
                demo.wait_for_systems(coordinator, robot, systems, timeout_s=START_TIMEOUT_S)
        finally:
            coordinator.close()

    def _check_prometheus(self):
        """The mounted rules are loaded and the mounted target files read."""
        service = self.services["prometheus"]
        base = f"http://127.0.0.1:{service.ports['--web.listen-address']}"
        prometheus = ds.PrometheusApi(service.ports["--web.listen-address"])
        rules = [r for group in prometheus.get("/api/v1/rules")["groups"]
                 for r in group["rules"]]
        self.assertGreaterEqual(len([r for r in rules if r["type"] == "alerting"]), 5, base)
        expected = set()
        for name, spec in self.project["services"].items():
            robot = ds.flag_value(spec.get("command") or [], "--robot-id")
            if robot:
                metrics = ds.port_of(ds.flag_value(spec["command"], "--metrics-listen"))
                expected.add((f"{name}:{metrics}", robot))

        def discovered():
            targets = prometheus.get("/api/v1/targets")["activeTargets"]
            return {(t["discoveredLabels"]["__address__"], t["labels"].get("robot"))
                    for t in targets if t["labels"]["job"] == "behavior_system"}

        ds.wait_for(lambda: discovered() == expected, START_TIMEOUT_S,
                    f"prometheus discovering the behavior systems {sorted(expected)}")

    def _check_clean_stop(self):
        for service in reversed(self.started):
            grace = float(str(service.spec.get("stop_grace_period", "10s")).rstrip("s"))
            code = ds.stop_process(service.process, timeout_s=grace)
            self.assertEqual(code, 0, f"{service.name} did not stop cleanly on SIGTERM "
                                      f"within {grace} s:\n{ds.log_tail(service.log_path)}")


if __name__ == "__main__":
    parser = argparse.ArgumentParser()
    parser.add_argument("--build-dir", default=BUILD_DIR)
    parser.add_argument("--with-drone2", action="store_true",
                        help="merge deploy/compose/docker-compose.drone2.yml")
    args, rest = parser.parse_known_args()
    BUILD_DIR = os.path.abspath(args.build_dir)
    if args.with_drone2:
        FILES.append(ds.DRONE2_FILE)
    unittest.main(argv=[sys.argv[0], *rest], verbosity=2)
