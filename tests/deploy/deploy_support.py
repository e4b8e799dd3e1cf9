"""Shared by the deployment tests (tests/deploy/*_test.py): the Compose files
as Compose reads them (variables interpolated with their defaults, an
override merged), the Dockerfile's install tree, server processes on
loopback with the ports they actually bound, and Prometheus's HTTP API.

Needs Debian's python3-yaml (and, for rpc, python3-grpcio/python3-protobuf).
"""

import hashlib
import json
import os
import re
import shutil
import signal
import socket
import subprocess
import time
import urllib.parse
import urllib.request

import yaml

REPO = os.path.abspath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", ".."))
COMPOSE_DIR = os.path.join(REPO, "deploy", "compose")
COMPOSE_FILE = os.path.join(COMPOSE_DIR, "docker-compose.yml")
DRONE2_FILE = os.path.join(COMPOSE_DIR, "docker-compose.drone2.yml")
DOCKERFILE = os.path.join(COMPOSE_DIR, "Dockerfile")
PROMETHEUS_DIR = os.path.join(REPO, "deploy", "prometheus")
GRAFANA_DIR = os.path.join(REPO, "deploy", "grafana")
DASHBOARDS_DIR = os.path.join(GRAFANA_DIR, "dashboards")
DEFAULT_BUILD_DIR = os.environ.get("BEHAVIORLIB_BUILD_DIR", os.path.join(REPO, "build"))

# Exit code ctest reports as "skipped" (SKIP_RETURN_CODE in CMakeLists.txt).
SKIP = 77

# Where the image's binaries come from in a build tree: the Dockerfile copies
# them from bin/.
IMAGE_BIN = "/opt/behaviorlib/bin"
# The programs of the image besides the behavior systems.
INFRASTRUCTURE_PROGRAMS = ["channel_broker", "simulator", "coordinator", "console", "behaviorctl"]
# Upstream images whose commands run against Debian's package of the same
# program.
UPSTREAM_PROGRAMS = {"prom/prometheus": "/usr/bin/prometheus"}


# --- Compose files ------------------------------------------------------------

_VARIABLE = re.compile(
    r"\$(?:(?P<escaped>\$)|\{(?P<name>[A-Za-z_][A-Za-z0-9_]*)(?:(?P<op>:?[-?])(?P<arg>[^}]*))?\}"
    r"|(?P<bare>[A-Za-z_][A-Za-z0-9_]*))")


def interpolate(value, env):
    """Compose's variable substitution: $$, $NAME, ${NAME}, ${NAME:-default},
    ${NAME-default}, ${NAME:?error}, ${NAME?error}."""
    if isinstance(value, dict):
        return {k: interpolate(v, env) for k, v in value.items()}
    if isinstance(value, list):
        return [interpolate(v, env) for v in value]
    if not isinstance(value, str):
        return value

    def replace(match):
        if match.group("escaped"):
            return "$"
        name = match.group("name") or match.group("bare")
        op, arg = match.group("op"), match.group("arg") or ""
        current = env.get(name)
        if op in (":-", ":?"):
            missing = not current
        else:
            missing = current is None
        if op in ("-", ":-"):
            return arg if missing else current
        if op in ("?", ":?"):
            if missing:
                raise ValueError(f"variable {name} is required: {arg}")
            return current
        return current or ""

    return _VARIABLE.sub(replace, value)


def _volume_target(entry):
    return entry.split(":")[1] if ":" in entry else entry


def _merge_service(base, override):
    """Compose's merge of one service: a command, an entrypoint or a
    healthcheck test is replaced, volumes merge by container path, mappings
    merge, other values are replaced."""
    merged = dict(base)
    for key, value in override.items():
        if key == "volumes":
            by_target = {_volume_target(v): v for v in base.get("volumes", [])}
            by_target.update({_volume_target(v): v for v in value})
            merged[key] = list(by_target.values())
        elif isinstance(value, dict) and isinstance(base.get(key), dict):
            merged[key] = {**base[key], **value}
        else:
            merged[key] = value
    return merged


def read_yaml(path):
    with open(path) as f:
        return yaml.safe_load(f)


# The variables the Compose files require (`${NAME:?message}`, no default),
# with the value a deployment would set in the environment or
# deploy/compose/.env.
REQUIRED_ENV = {"GRAFANA_ADMIN_PASSWORD": "deploy-tests-password"}


def load_compose(*paths, env=None):
    """The Compose project of these files, as Compose reads them: variables
    interpolated from REQUIRED_ENV and `env` (default: nothing more, so every
    default applies), later files merged over earlier ones."""
    env = {**REQUIRED_ENV, **(env or {})}
    project = {"services": {}, "volumes": {}}
    for path in paths:
        data = interpolate(read_yaml(path), env)
        for name, service in (data.get("services") or {}).items():
            base = project["services"].get(name)
            project["services"][name] = _merge_service(base, service) if base else service
        project["volumes"].update(data.get("volumes") or {})
    return project


def dependency_order(services):
    """Service names, every service after those it depends on."""
    order, seen = [], set()

    def visit(name, path=()):
        if name in seen:
            return
        if name in path:
            raise ValueError(f"depends_on cycle: {' -> '.join(path + (name,))}")
        depends = services[name].get("depends_on") or {}
        for dep in sorted(depends):
            visit(dep, path + (name,))
        seen.add(name)
        order.append(name)

    for name in sorted(services):
        visit(name)
    return order


def flag_value(command, flag):
    """The value of --flag=value (or --flag value) in a command list, or None."""
    for i, arg in enumerate(command):
        if arg.startswith(flag + "="):
            return arg[len(flag) + 1:]
        if arg == flag and i + 1 < len(command):
            return command[i + 1]
    return None


def port_of(address):
    return int(address.rsplit(":", 1)[1])


def behavior_systems_in_source():
    """Every behavior system built from services/systems/* (a main() that
    calls runBehaviorSystem)."""
    systems = []
    for name in sorted(os.listdir(os.path.join(REPO, "services", "systems"))):
        main = os.path.join(REPO, "services", "systems", name, "main.cc")
        if os.path.isfile(main):
            with open(main) as f:
                if "runBehaviorSystem" in f.read():
                    systems.append(name)
    return systems


def image_directories():
    """{container directory: repository directory} of what the Dockerfile
    copies into the image (`cp -r SRC /opt/behaviorlib/...`)."""
    with open(DOCKERFILE) as f:
        text = f.read()
    return {dst: os.path.join(REPO, src)
            for src, dst in re.findall(r"cp -r (\S+) (/opt/behaviorlib/\S+)", text)}


# How the Dockerfile puts each behavior system's configuration into the image.
SYSTEM_CONFIG_COPY = 'cp "$dir/config.yaml" "/opt/behaviorlib/config/$name.yaml"'


def image_files():
    """{container file: repository file} of the files the Dockerfile copies
    one by one into the image's directories: each behavior system's
    services/systems/<name>/config.yaml as /opt/behaviorlib/config/<name>.yaml
    ({} when the Dockerfile does not copy them)."""
    with open(DOCKERFILE) as f:
        if SYSTEM_CONFIG_COPY not in f.read():
            return {}
    systems_dir = os.path.join(REPO, "services", "systems")
    files = {}
    for name in sorted(os.listdir(systems_dir)):
        config = os.path.join(systems_dir, name, "config.yaml")
        if os.path.isfile(config):
            files[f"/opt/behaviorlib/config/{name}.yaml"] = config
    return files


def build_binary(build_dir, name):
    return os.path.join(build_dir, "bin", name)


# --- processes ------------------------------------------------------------------

def listening_ports(pid):
    """TCP ports on which process `pid` listens (from /proc: its socket
    inodes, matched in /proc/net/tcp{,6} in state LISTEN)."""
    inodes = set()
    fd_dir = f"/proc/{pid}/fd"
    try:
        for fd in os.listdir(fd_dir):
            try:
                target = os.readlink(os.path.join(fd_dir, fd))
            except OSError:
                continue
            if target.startswith("socket:["):
                inodes.add(target[8:-1])
    except OSError:
        return set()
    ports = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        try:
            with open(table) as f:
                next(f)
                for line in f:
                    fields = line.split()
                    if fields[3] == "0A" and fields[9] in inodes:
                        ports.add(int(fields[1].rsplit(":", 1)[1], 16))
        except OSError:
            continue
    return ports


def wait_for(predicate, timeout_s, what, interval_s=0.1):
    """Polls `predicate` until it returns a true value (returned), or raises
    AssertionError naming `what` after `timeout_s`."""
    deadline = time.monotonic() + timeout_s
    last_error = None
    while True:
        try:
            value = predicate()
            if value:
                return value
        except (OSError, ValueError, KeyError) as error:
            last_error = error
        if time.monotonic() >= deadline:
            raise AssertionError(f"{what}: not within {timeout_s} s"
                                 + (f" (last error: {last_error})" if last_error else ""))
        time.sleep(interval_s)


def log_tail(path, lines=20):
    try:
        with open(path, errors="replace") as f:
            return "".join(f.readlines()[-lines:])
    except OSError:
        return ""


def alive(pid):
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def stop_process(process, timeout_s=10.0):
    """SIGTERM, then SIGKILL after `timeout_s`; the exit code."""
    if process.poll() is None:
        process.send_signal(signal.SIGTERM)
        try:
            process.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
    return process.returncode


def read_port_file(path):
    ports = {}
    with open(path) as f:
        for line in f:
            key, _, value = line.strip().partition("=")
            if value:
                ports[key] = int(value)
    return ports


def free_port():
    """A port free now on 127.0.0.1 (for programs that cannot report the port
    they bound; prefer --listen 127.0.0.1:0 and a port file)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# --- Prometheus -----------------------------------------------------------------

class PrometheusApi:
    """Prometheus's HTTP API on 127.0.0.1:port."""

    def __init__(self, port=None):
        self.port = port

    def get(self, path, **params):
        url = f"http://127.0.0.1:{self.port}{path}"
        if params:
            url += "?" + urllib.parse.urlencode(params)
        with urllib.request.urlopen(url, timeout=10) as page:
            body = json.load(page)
        if body.get("status") != "success":
            raise AssertionError(f"{path} {params}: {body}")
        return body["data"]

    def query(self, expr, at=None):
        params = {"query": expr}
        if at is not None:
            params["time"] = f"{at:.3f}"
        return self.get("/api/v1/query", **params)

    def query_range(self, expr, start, end, step_s):
        return self.get("/api/v1/query_range", query=expr, start=f"{start:.3f}",
                        end=f"{end:.3f}", step=f"{step_s}s")

    def scalar(self, expr, at=None):
        """The single value of an expression that returns one series (a sum)."""
        result = self.query(expr, at)["result"]
        if len(result) != 1:
            raise AssertionError(f"{expr}: expected one series, got {result}")
        return float(result[0]["value"][1])


class Prometheus(PrometheusApi):
    """Debian's prometheus on 127.0.0.1, on a port of its choosing (read
    back from /proc)."""

    def __init__(self, config_file, data_dir, log_path, extra_args=()):
        super().__init__()
        self.log_path = log_path
        argv = ["/usr/bin/prometheus", f"--config.file={config_file}",
                f"--storage.tsdb.path={data_dir}", "--web.listen-address=127.0.0.1:0",
                *extra_args]
        self.log = open(log_path, "wb")
        self.process = subprocess.Popen(argv, stdin=subprocess.DEVNULL, stdout=self.log,
                                        stderr=subprocess.STDOUT, start_new_session=True)

    def wait_ready(self, timeout_s=20.0):
        def ready():
            if self.process.poll() is not None:
                raise AssertionError(f"prometheus exited with code {self.process.returncode}:\n"
                                     f"{log_tail(self.log_path)}")
            ports = listening_ports(self.process.pid)
            if not ports:
                return False
            self.port = min(ports)
            with urllib.request.urlopen(f"http://127.0.0.1:{self.port}/-/ready",
                                        timeout=2) as page:
                return page.status == 200

        wait_for(ready, timeout_s, "prometheus ready")

    def stop(self):
        code = stop_process(self.process)
        self.log.close()
        return code


def tracked_files(paths):
    """The files of the checkout under `paths` (git ls-files), or None with
    the reason when this is not a git checkout."""
    listed = subprocess.run(["git", "-C", REPO, "ls-files", "-z", "--", *paths],
                            capture_output=True, text=True)
    if listed.returncode != 0:
        return None, listed.stderr.strip()
    return [f for f in listed.stdout.split("\0") if f], ""


class RegistryUnreachable(Exception):
    """npm could not reach its registry (a test then exits 77: skipped)."""


def npm_ci(source, work):
    """npm ci of `source`'s package.json and package-lock.json in `work` (a
    build directory, never the sources), unless node_modules already holds
    that lockfile. Install scripts do not run. RegistryUnreachable when the
    registry cannot be reached."""
    os.makedirs(work, exist_ok=True)
    with open(os.path.join(source, "package-lock.json"), "rb") as f:
        lock = f.read()
    stamp_path = os.path.join(work, "node_modules", ".behaviorlib-lock-sha256")
    digest = hashlib.sha256(lock).hexdigest()
    try:
        with open(stamp_path) as f:
            if f.read().strip() == digest:
                return
    except OSError:
        pass
    for name in ("package.json", "package-lock.json"):
        shutil.copyfile(os.path.join(source, name), os.path.join(work, name))
    result = subprocess.run(["npm", "ci", "--no-audit", "--no-fund", "--ignore-scripts"],
                            cwd=work, capture_output=True, text=True, timeout=240)
    output = result.stdout + result.stderr
    # No route, no name resolution, a refusing proxy: the registry, not the
    # lockfile, is the problem.
    if result.returncode != 0 and re.search(
            r"\b(ENOTFOUND|EAI_AGAIN|ECONNREFUSED|ECONNRESET|ETIMEDOUT|ENETUNREACH|EHOSTUNREACH"
            r"|E403|E407|E5\d\d|SELF_SIGNED_CERT_IN_CHAIN|UNABLE_TO_GET_ISSUER_CERT_LOCALLY)\b"
            r"|network request|request to https?://\S+ failed", output):
        raise RegistryUnreachable(f"npm ci in {work}: the npm registry is unreachable:\n"
                                  f"{output[-2000:]}")
    if result.returncode != 0:
        raise AssertionError(f"npm ci in {work} failed:\n{output}")
    with open(stamp_path, "w") as f:
        f.write(digest + "\n")
