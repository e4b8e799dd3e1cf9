"""The deployment files agree with each other and with the code, without
running anything:

- docker-compose.yml and docker-compose.drone2.yml: every behavior system
  built from services/systems/* has a service per vehicle; only the coordinator,
  Prometheus and Grafana are published (on the publish address); every
  service has a restart policy, resource limits and a health check (the gRPC
  health check of behaviorctl on its own --listen port); every address a
  command names is a service's --listen port, also with other ports set in
  the environment; the override repeats the base file's shared settings;
  the world, sensor configuration, time scale and the mission and world
  directories come from the environment, their defaults being what the
  image ships; Grafana's admin password has no default; the coordinator's
  journal and saved maps are on the named volume;
- .dockerignore keeps build trees, the history and secrets out of the build
  context and nothing the Dockerfile copies;
- deploy/README.md names every behavior system and every variable of the
  Compose files;
- the Dockerfile: Debian 12 build stage with install-deps.sh --build and
  scripts/build.sh, a slim runtime stage with --runtime, a non-root user;
  every container path a command names is in the image or a volume;
- Prometheus: the scrape targets of prometheus.yml and compose-targets/ are
  exactly the services' /metrics ports, with the launcher's labels;
- Grafana: the provisioned data source is the one every dashboard names;
  variables, panel types and enum values are valid.

    /usr/bin/python3 tests/deploy/deploy_static_test.py
"""

import json
import os
import re
import subprocess
import sys
import tempfile
import unittest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import deploy_support as ds  # noqa: E402

PUBLISHED = {"coordinator", "console", "prometheus", "grafana"}
# Services of our image that serve HTTP, not gRPC: the console (decision 35),
# health checked with its own --probe, and without /metrics.
HTTP_SERVICES = {"console"}
BEHAVIORLIB_IMAGE = "${BEHAVIORLIB_IMAGE:-behaviorlib:latest}"
VEHICLES = {"drone1": [ds.COMPOSE_FILE], "drone2": [ds.COMPOSE_FILE, ds.DRONE2_FILE]}
# Every port variable set to something unusual: references must follow.
PORT_ENV = {"CHANNEL_PORT": "41001", "SIMULATOR_PORT": "41002", "COORDINATOR_PORT": "41003",
            "BEHAVIOR_SYSTEM_PORT": "41004", "COORDINATOR_HOST_PORT": "41005",
            "PROMETHEUS_HOST_PORT": "41006", "GRAFANA_HOST_PORT": "41007",
            "CONSOLE_PORT": "41008", "CONSOLE_HOST_PORT": "41009",
            "BEHAVIORLIB_PUBLISH_ADDRESS": "0.0.0.0"}
ADDRESS = re.compile(r"(?<![\w.-])([a-z][a-z0-9-]*):(\d+)\b")
# What the simulator and the coordinator fly with when nothing is set: the
# settings the deployment had before they came from the environment (an
# empty field at real time, the shipped sensors, worlds and missions).
SCENARIO_DEFAULTS = {
    "simulator": {"--world": "", "--time-scale": "1",
                  "--sensor-config": "/opt/behaviorlib/config/simulator_sensors.yaml",
                  "--worlds-dir": "/opt/behaviorlib/worlds"},
    "coordinator": {"--mission-dir": "/opt/behaviorlib/missions"},
}
# Each scenario variable set to something other than its default, and what
# must then reach the commands (flags) and mounts (container path -> host
# directory).
SCENARIO_ENV = {"SIMULATOR_WORLD": "aircraft", "SIMULATOR_TIME_SCALE": "2.5",
                "SIMULATOR_SENSOR_CONFIG":
                    "/opt/behaviorlib/config/simulator_sensors_aircraft.yaml",
                "BEHAVIORLIB_WORLDS_DIR": "/srv/scenario/worlds",
                "BEHAVIORLIB_MISSIONS_DIR": "/srv/scenario/missions"}
SCENARIO_FLAGS = {"simulator": {"--world": "aircraft", "--time-scale": "2.5",
                                "--sensor-config":
                                    "/opt/behaviorlib/config/simulator_sensors_aircraft.yaml"}}
SCENARIO_MOUNTS = {"simulator": {"/opt/behaviorlib/worlds": "/srv/scenario/worlds"},
                   "coordinator": {"/opt/behaviorlib/missions": "/srv/scenario/missions"}}
# Flags naming where a server writes what must outlive its container.
DATA_FLAGS = ("--state-dir", "--map-dir", "--audit-log")


def behaviorlib_services(project):
    return {name: s for name, s in project["services"].items()
            if (s.get("command") or [""])[0].startswith(ds.IMAGE_BIN + "/")}


def listen_port(service):
    return ds.port_of(ds.flag_value(service["command"], "--listen"))


def mounts(service):
    """{container path: source} of a service's volumes (a bind mount's
    source as written, relative to deploy/compose; a named volume's name)."""
    return {ds._volume_target(v): v.split(":")[0] for v in service.get("volumes", [])}


def host_directory(source):
    """The host directory of a bind mount's source (relative to the
    directory of the Compose files, as Compose resolves it)."""
    return os.path.normpath(os.path.join(ds.COMPOSE_DIR, source))


def under(path, directory):
    return path == directory or path.startswith(directory.rstrip("/") + "/")


class ComposeTest(unittest.TestCase):
    def projects(self, env=None):
        return {"docker-compose.yml": ds.load_compose(ds.COMPOSE_FILE, env=env),
                "docker-compose.yml + drone2": ds.load_compose(ds.COMPOSE_FILE, ds.DRONE2_FILE,
                                                               env=env)}

    def test_every_behavior_system_has_a_service_per_vehicle(self):
        systems = ds.behavior_systems_in_source()
        self.assertIn("basic_quadrotor_behaviors", systems)
        for robot, files in VEHICLES.items():
            services = behaviorlib_services(ds.load_compose(*files))
            for system in systems:
                name = f"{robot}-{system.replace('_', '-')}"
                with self.subTest(service=name):
                    self.assertIn(name, services, f"{system} has no service for {robot}")
                    service = services[name]
                    command = service["command"]
                    self.assertEqual(command[0], f"{ds.IMAGE_BIN}/{system}")
                    self.assertEqual(ds.flag_value(command, "--robot-id"), robot)
                    self.assertEqual(ds.flag_value(command, "--clock"), "sim")
                    # Registered under its host name: resolvable by service name.
                    self.assertEqual(service.get("hostname"), name)
                    for flag in ("--channel", "--flight-controller", "--coordinator",
                                 "--metrics-listen"):
                        self.assertTrue(ds.flag_value(command, flag), f"{name} lacks {flag}")
                    config = os.path.join(ds.REPO, "services", "systems", system,
                                          "config.yaml")
                    if os.path.exists(config):
                        self.assertEqual(ds.flag_value(command, "--config"),
                                         f"/opt/behaviorlib/config/{system}.yaml")
                        self.assertEqual(ds.image_files().get(
                            f"/opt/behaviorlib/config/{system}.yaml"), config)

    def test_only_the_coordinator_console_prometheus_and_grafana_are_published(self):
        for label, project in self.projects().items():
            for name, service in project["services"].items():
                with self.subTest(project=label, service=name):
                    if name not in PUBLISHED:
                        self.assertNotIn("ports", service)
                        continue
                    for mapping in service["ports"]:
                        # Published on the publish address only (loopback by default).
                        self.assertRegex(mapping, r"^127\.0\.0\.1:\d+:\d+$")
        project = ds.load_compose(ds.COMPOSE_FILE, env=PORT_ENV)
        self.assertEqual(project["services"]["coordinator"]["ports"], ["0.0.0.0:41005:41003"])
        self.assertEqual(project["services"]["prometheus"]["ports"], ["0.0.0.0:41006:9090"])
        self.assertEqual(project["services"]["grafana"]["ports"], ["0.0.0.0:41007:3000"])
        self.assertEqual(project["services"]["console"]["ports"], ["0.0.0.0:41009:41008"])

    def test_every_service_has_restart_limits_and_a_health_check(self):
        for label, project in self.projects().items():
            for name, service in project["services"].items():
                with self.subTest(project=label, service=name):
                    self.assertEqual(service.get("restart"), "unless-stopped")
                    self.assertGreater(float(service.get("cpus", 0)), 0)
                    self.assertRegex(str(service.get("mem_limit", "")), r"^\d+[mg]$")
                    health = service.get("healthcheck") or {}
                    self.assertEqual(health.get("test", [None])[0], "CMD")
                    for key in ("interval", "timeout", "retries", "start_period"):
                        self.assertIn(key, health)

    def test_behaviorlib_services_share_the_image_and_run_unprivileged(self):
        base = ds.read_yaml(ds.COMPOSE_FILE)
        for label, project in self.projects().items():
            for name, service in behaviorlib_services(project).items():
                with self.subTest(project=label, service=name):
                    self.assertEqual(service["image"], "behaviorlib:latest")
                    self.assertEqual(service["build"], {"context": "../..",
                                                        "dockerfile": "deploy/compose/Dockerfile"})
                    self.assertTrue(service.get("read_only"))
                    self.assertEqual(service.get("cap_drop"), ["ALL"])
        self.assertEqual(base["x-behaviorlib"]["image"], BEHAVIORLIB_IMAGE)

    def test_health_checks_ask_the_service_itself_over_grpc_health(self):
        for env in (None, PORT_ENV):
            for label, project in self.projects(env).items():
                for name, service in behaviorlib_services(project).items():
                    with self.subTest(project=label, service=name, env=bool(env)):
                        # With the service's own certificate, as its server requires.
                        tls = [f"--tls-{part}=/etc/behaviorlib/tls/{file}"
                               for part, file in (("cert", "cert.pem"), ("key", "key.pem"),
                                                  ("ca", "ca.pem"))]
                        if name in HTTP_SERVICES:
                            expected = ["CMD", f"{ds.IMAGE_BIN}/console", *tls, "--probe",
                                        f"localhost:{listen_port(service)}"]
                        else:
                            expected = ["CMD", f"{ds.IMAGE_BIN}/behaviorctl", *tls, "--target",
                                        f"localhost:{listen_port(service)}", "health"]
                        self.assertEqual(service["healthcheck"]["test"], expected)
                        self.assertTrue(ds.flag_value(service["command"],
                                                      "--listen").startswith("0.0.0.0:"))

    def test_addresses_in_commands_are_services_listen_ports(self):
        for env in (None, PORT_ENV):
            for label, project in self.projects(env).items():
                services = project["services"]
                for name, service in behaviorlib_services(project).items():
                    for arg in service["command"][1:]:
                        if arg.startswith(("--listen=", "--metrics-listen=")):
                            continue
                        for host, port in ADDRESS.findall(arg.partition("=")[2]):
                            with self.subTest(project=label, service=name, arg=arg):
                                self.assertIn(host, services, f"{arg}: no service {host}")
                                self.assertEqual(int(port), listen_port(services[host]), arg)
                                if env:
                                    self.assertIn(int(port), {int(v) for k, v in env.items()
                                                              if k.endswith("_PORT")})

    def test_depends_on_waits_for_health(self):
        for label, project in self.projects().items():
            services = project["services"]
            ds.dependency_order(services)  # no cycle
            for name, service in services.items():
                for dep, condition in (service.get("depends_on") or {}).items():
                    with self.subTest(project=label, service=name, dep=dep):
                        self.assertIn(dep, services)
                        self.assertEqual(condition, {"condition": "service_healthy"})
            for name in behaviorlib_services(project):
                if name.startswith("drone"):
                    self.assertEqual(set(services[name]["depends_on"]),
                                     {"channel-broker", "simulator", "coordinator"})

    def test_the_override_repeats_the_shared_settings_of_the_base_file(self):
        base, override = ds.read_yaml(ds.COMPOSE_FILE), ds.read_yaml(ds.DRONE2_FILE)
        shared = {k for k in base if k.startswith("x-")}
        self.assertEqual({k for k in override if k.startswith("x-")}, shared)
        for key in shared:
            self.assertEqual(override[key], base[key], key)
        self.assertEqual(override.get("version"), base.get("version"))

    def test_drone2_reaches_the_simulator_and_the_coordinators_safety(self):
        project = ds.load_compose(ds.COMPOSE_FILE, ds.DRONE2_FILE)
        simulator = project["services"]["simulator"]["command"]
        self.assertEqual(ds.flag_value(simulator, "--vehicles"), "drone1,drone2")
        coordinator = project["services"]["coordinator"]["command"]
        robots = [entry.split("=")[0]
                  for entry in ds.flag_value(coordinator, "--flight-controller").split(",")]
        self.assertEqual(robots, ["drone1", "drone2"])
        # The safety rules' hover runs on the vehicles' simulated time.
        self.assertEqual(ds.flag_value(coordinator, "--clock"), "sim")
        # Apart from the vehicles, the override's commands are the base file's.
        base = ds.load_compose(ds.COMPOSE_FILE)["services"]
        for name, flag in (("simulator", "--vehicles"), ("coordinator", "--flight-controller")):
            strip = [a for a in base[name]["command"] if not a.startswith(flag + "=")]
            self.assertEqual([a for a in project["services"][name]["command"]
                              if not a.startswith(flag + "=")], strip, name)

    def test_data_volume_holds_the_coordinator_state_and_system_data(self):
        for label, project in self.projects().items():
            self.assertIn("behaviorlib-data", project["volumes"])
            coordinator = project["services"]["coordinator"]
            self.assertIn("behaviorlib-data:/var/lib/behaviorlib", coordinator["volumes"])
            self.assertTrue(ds.flag_value(coordinator["command"], "--state-dir")
                            .startswith("/var/lib/behaviorlib/"))
            for name, service in behaviorlib_services(project).items():
                if name.startswith("drone"):
                    self.assertIn("behaviorlib-data:/var/lib/behaviorlib", service["volumes"])

    def test_scenario_defaults_are_what_the_image_ships(self):
        image = ds.image_directories()
        for label, project in self.projects().items():
            for name, flags in SCENARIO_DEFAULTS.items():
                service = project["services"][name]
                for flag, value in flags.items():
                    with self.subTest(project=label, service=name, flag=flag):
                        self.assertEqual(ds.flag_value(service["command"], flag), value)
            # The worlds and missions mounted by default are the directories
            # the Dockerfile copies to the same paths: the same files.
            for name, flag in (("simulator", "--worlds-dir"), ("coordinator", "--mission-dir")):
                with self.subTest(project=label, service=name):
                    target = ds.flag_value(project["services"][name]["command"], flag)
                    source = mounts(project["services"][name]).get(target)
                    self.assertIsNotNone(source, f"{name}: {target} is not mounted")
                    self.assertEqual(host_directory(source), image[target])

    def test_scenario_comes_from_the_environment(self):
        for label, project in self.projects(SCENARIO_ENV).items():
            for name, flags in SCENARIO_FLAGS.items():
                command = project["services"][name]["command"]
                for flag, value in flags.items():
                    with self.subTest(project=label, service=name, flag=flag):
                        self.assertEqual(ds.flag_value(command, flag), value)
            for name, expected in SCENARIO_MOUNTS.items():
                service = project["services"][name]
                for target, source in expected.items():
                    with self.subTest(project=label, service=name, target=target):
                        self.assertEqual(mounts(service).get(target), source)
                        # Read-only: the servers only read worlds and missions.
                        self.assertIn(f"{source}:{target}:ro", service["volumes"])
            # Nothing else changed: the other services' commands are the defaults'.
            defaults = ds.load_compose(*VEHICLES["drone2" if "drone2" in label else "drone1"])
            for name, service in project["services"].items():
                if name not in SCENARIO_FLAGS:
                    self.assertEqual(service.get("command"),
                                     defaults["services"][name].get("command"), name)

    def test_grafana_admin_password_has_no_default(self):
        raw = ds.read_yaml(ds.COMPOSE_FILE)["services"]["grafana"]["environment"]
        self.assertRegex(raw["GF_SECURITY_ADMIN_PASSWORD"],
                         r"^\$\{GRAFANA_ADMIN_PASSWORD:\?set GRAFANA_ADMIN_PASSWORD .+\}$")
        # Compose refuses the files without it (the message says what to set).
        for files in VEHICLES.values():
            data = [ds.read_yaml(path) for path in files]
            with self.assertRaisesRegex(ValueError, "GRAFANA_ADMIN_PASSWORD is required: "
                                                    "set GRAFANA_ADMIN_PASSWORD"):
                for document in data:
                    ds.interpolate(document, {})
            # An empty value counts as unset (`:?`).
            with self.assertRaises(ValueError):
                for document in data:
                    ds.interpolate(document, {"GRAFANA_ADMIN_PASSWORD": ""})
        grafana = ds.load_compose(ds.COMPOSE_FILE, env={"GRAFANA_ADMIN_PASSWORD": "s3cret"})
        self.assertEqual(grafana["services"]["grafana"]["environment"]
                         ["GF_SECURITY_ADMIN_PASSWORD"], "s3cret")

    def test_saved_maps_and_the_journal_are_on_the_named_volume(self):
        for label, project in self.projects().items():
            written = 0
            for name, service in behaviorlib_services(project).items():
                # A tmpfs for scratch space only, never over the data.
                self.assertEqual(service.get("tmpfs"), ["/tmp"], name)
                for flag in DATA_FLAGS:
                    path = ds.flag_value(service["command"], flag)
                    if path is None:
                        continue
                    written += 1
                    with self.subTest(project=label, service=name, flag=flag):
                        target = max((t for t in mounts(service) if under(path, t)),
                                     key=len, default=None)
                        self.assertIsNotNone(target, f"{flag}={path} is on no volume")
                        source = mounts(service)[target]
                        # A named volume declared at the top level (not a
                        # bind mount, which depends on the host's directories).
                        self.assertNotRegex(source, r"^[./$~]", f"{flag}={path}")
                        self.assertIn(source, project["volumes"])
                        self.assertFalse(any(under(path, t) for t in service["tmpfs"]))
            # The coordinator's journal and every vehicle's saved maps.
            self.assertGreaterEqual(written, 1 + len([n for n in project["services"]
                                                      if n.endswith("navigation-with-lidar")]))

    def test_bind_mounts_exist(self):
        # The certificates are made by scripts/make-dev-certs.sh (into
        # BEHAVIORLIB_CERTS_DIR, deploy/certs by default): its default names
        # must cover every service that mounts one.
        with tempfile.TemporaryDirectory() as tmp:
            certs = os.path.join(tmp, "certs")
            subprocess.run([os.path.join(ds.REPO, "scripts", "make-dev-certs.sh"), "--out", certs],
                           check=True, capture_output=True)
            for label, project in self.projects({"BEHAVIORLIB_CERTS_DIR": certs}).items():
                for name, service in project["services"].items():
                    for volume in service.get("volumes", []):
                        source = volume.split(":")[0]
                        if source.startswith(".") or source.startswith("/"):
                            with self.subTest(project=label, service=name, volume=volume):
                                self.assertTrue(
                                    os.path.exists(os.path.join(ds.COMPOSE_DIR, source)))

    def test_every_behaviorlib_server_runs_with_mutual_tls(self):
        for label, project in self.projects().items():
            for name, service in behaviorlib_services(project).items():
                with self.subTest(project=label, service=name):
                    command = service["command"]
                    self.assertNotIn("--insecure", command)
                    for flag in ("--tls-cert", "--tls-key", "--tls-ca"):
                        self.assertTrue(ds.flag_value(command, flag), f"{name}: no {flag}")
                    test = service["healthcheck"]["test"]
                    self.assertTrue(any(a.startswith("--tls-cert=") for a in test),
                                    f"{name}: the health check has no certificate")


class DockerfileTest(unittest.TestCase):
    def setUp(self):
        with open(ds.DOCKERFILE) as f:
            self.text = f.read()

    def test_stages_install_with_the_ci_script(self):
        self.assertRegex(self.text, r"ARG DEBIAN_IMAGE=debian:12\n")
        self.assertRegex(self.text, r"ARG DEBIAN_SLIM_IMAGE=debian:12-slim\n")
        self.assertIn("FROM ${DEBIAN_IMAGE} AS build", self.text)
        self.assertIn("FROM ${DEBIAN_SLIM_IMAGE} AS runtime", self.text)
        self.assertIn("scripts/install-deps.sh --build", self.text)
        self.assertIn("scripts/build.sh", self.text)
        self.assertIn("/tmp/install-deps.sh --runtime", self.text)
        runtime = self.text[self.text.index("AS runtime"):]
        self.assertRegex(runtime, r"\nUSER behaviorlib:behaviorlib\n")
        self.assertNotIn("--build", runtime)
        with open(os.path.join(ds.REPO, ".ci", "run")) as f:
            ci = f.read()
        self.assertIn("scripts/run-tests.sh", ci)
        with open(os.path.join(ds.REPO, "scripts", "run-tests.sh")) as f:
            self.assertIn("scripts/install-deps.sh", f.read())

    def test_the_image_holds_every_binary_the_commands_run(self):
        self.assertIn("for name in " + " ".join(ds.INFRASTRUCTURE_PROGRAMS) + "; do", self.text)
        self.assertIn("for dir in services/systems/*/; do", self.text)
        self.assertEqual(self.text.count('cp "/build/bin/$name" /opt/behaviorlib/bin/'), 2)
        project = ds.load_compose(ds.COMPOSE_FILE, ds.DRONE2_FILE)
        systems = set(ds.behavior_systems_in_source())
        for name, service in behaviorlib_services(project).items():
            program = os.path.basename(service["command"][0])
            with self.subTest(service=name):
                self.assertTrue(program in ds.INFRASTRUCTURE_PROGRAMS or program in systems,
                                program)

    def test_container_paths_are_in_the_image_or_a_volume(self):
        image = ds.image_directories()
        self.assertEqual(set(image), {"/opt/behaviorlib/config", "/opt/behaviorlib/missions",
                                      "/opt/behaviorlib/worlds", "/opt/behaviorlib/console/web"})
        files = ds.image_files()
        self.assertIn("/opt/behaviorlib/config/basic_quadrotor_behaviors.yaml", files)
        project = ds.load_compose(ds.COMPOSE_FILE, ds.DRONE2_FILE)
        for name, service in behaviorlib_services(project).items():
            volumes = [ds._volume_target(v) for v in service.get("volumes", [])]
            for arg in service["command"][1:]:
                value = arg.partition("=")[2]
                if not value.startswith("/"):
                    continue
                with self.subTest(service=name, arg=arg):
                    in_image = [d for d in image if value.startswith(d + "/") or value == d]
                    in_volume = [v for v in volumes if value.startswith(v + "/") or value == v]
                    self.assertTrue(in_image or in_volume, f"{arg}: not in the image nor a volume")
                    if value in files:
                        self.assertTrue(os.path.exists(files[value]),
                                        f"{arg}: {files[value]} does not exist")
                    elif in_image:
                        local = image[in_image[0]] + value[len(in_image[0]):]
                        self.assertTrue(os.path.exists(local), f"{arg}: {local} does not exist")


DOCKERIGNORE = os.path.join(ds.REPO, ".dockerignore")
README = os.path.join(ds.REPO, "deploy", "README.md")


def copied_sources():
    """The repository paths the Dockerfile's COPY lines take from the build
    context (not those copied from another stage)."""
    with open(ds.DOCKERFILE) as f:
        return [os.path.normpath(src) for src in
                re.findall(r"^COPY\s+(?!--)(\S+)\s+\S+\s*$", f.read(), re.MULTILINE)]


def dockerignore_patterns():
    """(excluded, regex) of each pattern of .dockerignore, in order, as
    Docker reads them: comments and blank lines skipped, `!` re-includes,
    leading and trailing slashes dropped, `*` and `?` within one path
    component, `**` across any number of them."""
    patterns = []
    with open(DOCKERIGNORE) as f:
        for line in f:
            line = line.strip()
            if not line or line.startswith("#"):
                continue
            excluded = not line.startswith("!")
            pattern = "/".join(p for p in line.lstrip("!").split("/") if p and p != ".")
            regex = ""
            for part in re.split(r"(\*\*/?|\*|\?)", pattern):
                if part.startswith("**"):
                    regex += "(.*/)?" if part.endswith("/") else ".*"
                elif part == "*":
                    regex += "[^/]*"
                elif part == "?":
                    regex += "[^/]"
                else:
                    regex += re.escape(part)
            patterns.append((excluded, re.compile(regex + "$")))
    return patterns


def dockerignored(path, patterns):
    """Whether Docker leaves `path` (relative to the repository) out of the
    build context: the last pattern matching it or a directory above it
    decides."""
    parts = path.split("/")
    prefixes = ["/".join(parts[:i]) for i in range(1, len(parts) + 1)]
    result = False
    for excluded, regex in patterns:
        if any(regex.match(prefix) for prefix in prefixes):
            result = excluded
    return result


class DockerignoreTest(unittest.TestCase):
    def setUp(self):
        self.assertTrue(os.path.isfile(DOCKERIGNORE), "no .dockerignore at the repository root")
        self.patterns = dockerignore_patterns()

    def test_build_trees_history_and_secrets_stay_out_of_the_context(self):
        for path in ("build/bin/coordinator", "build-asan/CMakeCache.txt",
                     "build-release/bin/simulator", ".git/HEAD", ".git",
                     "deploy/certs/ca.pem", "deploy/certs/coordinator.key",
                     "deploy/compose/.env", "clients/python/build/lib/x.py",
                     "tests/deploy/grafana_schema/node_modules/x/index.js",
                     "services/shared/x/__pycache__/y.cpython-311.pyc", "deploy/local/z.pyc",
                     "clients/python/behaviorlib.egg-info/PKG-INFO"):
            with self.subTest(path=path):
                self.assertTrue(dockerignored(path, self.patterns), path)

    def test_nothing_the_dockerfile_copies_is_excluded(self):
        sources = copied_sources()
        self.assertIn("deploy", sources)
        self.assertIn("services", sources)
        for source in sources:
            with self.subTest(source=source):
                self.assertTrue(os.path.exists(os.path.join(ds.REPO, source)), source)
                self.assertFalse(dockerignored(source, self.patterns), source)
        # Every file of the checkout under those paths reaches the context.
        files, why = ds.tracked_files(sources)
        if files is None:
            self.skipTest(f"not a git checkout: {why}")
        self.assertGreater(len(files), 100)
        self.assertEqual([f for f in files if dockerignored(f, self.patterns)], [])


class DeployReadmeTest(unittest.TestCase):
    NUMBERS = {"one": 1, "two": 2, "three": 3, "four": 4, "five": 5, "six": 6, "seven": 7,
               "eight": 8, "nine": 9, "ten": 10, "eleven": 11, "twelve": 12}

    def setUp(self):
        with open(README) as f:
            self.text = f.read()

    def test_names_every_behavior_system_of_the_compose_files(self):
        for robot, files in VEHICLES.items():
            systems = sorted({os.path.basename(s["command"][0])
                              for s in behaviorlib_services(ds.load_compose(*files)).values()
                              if ds.flag_value(s["command"], "--robot-id") == robot})
            self.assertEqual(systems, ds.behavior_systems_in_source())
        for system in ds.behavior_systems_in_source():
            self.assertTrue(f"`{system}`" in self.text, f"deploy/README.md does not name {system}")
        # A count of the behavior systems, where the text gives one, is right.
        count = len(ds.behavior_systems_in_source())
        for match in re.finditer(r"\b(\w+) behavior systems\b", self.text):
            number = self.NUMBERS.get(match.group(1).lower(),
                                      int(match.group(1)) if match.group(1).isdigit() else None)
            if number is not None:
                self.assertEqual(number, count, match.group(0))

    def test_documents_every_variable_of_the_compose_files(self):
        variables = set()

        def collect(value):  # the values only: comments may show ${NAME} too
            if isinstance(value, dict):
                for item in value.values():
                    collect(item)
            elif isinstance(value, list):
                for item in value:
                    collect(item)
            elif isinstance(value, str):
                variables.update(re.findall(r"\$\{([A-Za-z_][A-Za-z0-9_]*)", value))

        for path in (ds.COMPOSE_FILE, ds.DRONE2_FILE):
            collect(ds.read_yaml(path))
        self.assertIn("GRAFANA_ADMIN_PASSWORD", variables)
        for name in sorted(variables):
            with self.subTest(variable=name):
                self.assertTrue(re.search(r"^\| [^\n]*`" + name + r"`[^\n]*\|$", self.text,
                                          re.MULTILINE), f"{name} is not in the settings table")

    def test_has_no_leftover_suggested_text(self):
        self.assertFalse("suggested text" in self.text.lower(), "a \"suggested text\" section")
        self.assertFalse("admin`/`admin" in self.text, "Grafana's admin password has no default")


class PrometheusTargetsTest(unittest.TestCase):
    def expected_targets(self, project):
        """(address, job, system, robot) of every service's /metrics."""
        targets = set()
        for name, service in behaviorlib_services(project).items():
            if name in HTTP_SERVICES:
                self.assertIsNone(ds.flag_value(service["command"], "--metrics-listen"), name)
                continue
            metrics = ds.flag_value(service["command"], "--metrics-listen")
            self.assertTrue(metrics, f"{name} has no --metrics-listen")
            self.assertTrue(metrics.startswith("0.0.0.0:"), name)
            system = os.path.basename(service["command"][0])
            robot = ds.flag_value(service["command"], "--robot-id") or ""
            job = "behavior_system" if robot else system
            targets.add((f"{name}:{ds.port_of(metrics)}", job, system, robot))
        return targets

    def configured_targets(self, project):
        config = ds.read_yaml(os.path.join(ds.PROMETHEUS_DIR, "prometheus.yml"))
        mounted = {}
        for volume in project["services"]["prometheus"]["volumes"]:
            source, target = volume.split(":")[:2]
            mounted[target] = os.path.normpath(os.path.join(ds.COMPOSE_DIR, source))
        targets = set()
        for job in config["scrape_configs"]:
            if job["job_name"] == "prometheus":
                continue
            self.assertTrue(job.get("honor_labels"), job["job_name"])
            groups = list(job.get("static_configs", []))
            for sd in job.get("file_sd_configs", []):
                for pattern in sd["files"]:
                    directory, glob = os.path.split("/etc/prometheus/" + pattern)
                    self.assertEqual(glob, "*.yml")
                    for target, source in mounted.items():
                        if os.path.dirname(target) == directory:
                            groups += ds.read_yaml(source)
            for group in groups:
                labels = group.get("labels", {})
                for address in group["targets"]:
                    targets.add((address, labels.get("job", job["job_name"]),
                                 labels.get("system", ""), labels.get("robot", "")))
        return targets

    def test_prometheus_scrapes_exactly_the_services(self):
        for files in ([ds.COMPOSE_FILE], [ds.COMPOSE_FILE, ds.DRONE2_FILE]):
            project = ds.load_compose(*files)
            with self.subTest(files=[os.path.basename(f) for f in files]):
                self.assertEqual(self.configured_targets(project), self.expected_targets(project))

    def test_prometheus_mounts_its_configuration(self):
        project = ds.load_compose(ds.COMPOSE_FILE)
        command = project["services"]["prometheus"]["command"]
        self.assertEqual(ds.flag_value(command, "--config.file"),
                         "/etc/prometheus/prometheus.yml")
        volumes = project["services"]["prometheus"]["volumes"]
        self.assertIn("../prometheus/prometheus.yml:/etc/prometheus/prometheus.yml:ro", volumes)
        self.assertIn("../prometheus/rules:/etc/prometheus/rules:ro", volumes)

    def test_local_config_reads_the_launchers_targets(self):
        config = ds.read_yaml(os.path.join(ds.PROMETHEUS_DIR, "prometheus-local.yml"))
        (job,) = config["scrape_configs"]
        self.assertTrue(job["honor_labels"])
        self.assertEqual(job["file_sd_configs"][0]["files"], ["local-targets/*.json"])
        self.assertEqual(config["rule_files"], ["rules/*.yml"])


class GrafanaFilesTest(unittest.TestCase):
    PANEL_TYPES = {"row", "timeseries", "stat", "table", "heatmap", "bargauge", "gauge",
                   "state-timeline", "status-history", "text", "piechart", "barchart",
                   "histogram", "logs"}
    VARIABLE_TYPES = {"query", "adhoc", "groupby", "constant", "datasource", "interval",
                      "textbox", "custom", "system", "snapshot", "switch"}

    def setUp(self):
        datasources = ds.read_yaml(os.path.join(ds.GRAFANA_DIR, "provisioning", "datasources",
                                                "prometheus.yml"))
        (self.datasource,) = datasources["datasources"]
        self.dashboards = {}
        for name in sorted(os.listdir(ds.DASHBOARDS_DIR)):
            with open(os.path.join(ds.DASHBOARDS_DIR, name)) as f:
                self.dashboards[name] = json.load(f)

    def test_datasource_is_the_compose_prometheus(self):
        self.assertEqual(self.datasource["type"], "prometheus")
        self.assertEqual(self.datasource["url"], "http://prometheus:9090")
        self.assertEqual(self.datasource["uid"], "behaviorlib-prometheus")

    def test_dashboards_provider_reads_the_mounted_directory(self):
        provider = ds.read_yaml(os.path.join(ds.GRAFANA_DIR, "provisioning", "dashboards",
                                             "behaviorlib.yml"))
        (entry,) = provider["providers"]
        grafana = ds.load_compose(ds.COMPOSE_FILE)["services"]["grafana"]
        self.assertIn(f"../grafana/dashboards:{entry['options']['path']}:ro", grafana["volumes"])
        self.assertIn("../grafana/provisioning:/etc/grafana/provisioning:ro", grafana["volumes"])
        home = grafana["environment"]["GF_DASHBOARDS_DEFAULT_HOME_DASHBOARD_PATH"]
        self.assertTrue(home.startswith(entry["options"]["path"] + "/"))
        self.assertIn(os.path.basename(home), self.dashboards)

    def test_the_six_dashboards(self):
        self.assertEqual(set(self.dashboards), {
            "fleet_overview.json", "behavior_activity.json", "monitoring_activation_times.json",
            "vehicle_state.json", "simulator_performance.json", "missions.json"})
        uids = [d["uid"] for d in self.dashboards.values()]
        self.assertEqual(len(set(uids)), len(uids))

    def panels(self, dashboard):
        for panel in dashboard["panels"]:
            yield panel
            yield from panel.get("panels", [])

    def test_panels_name_the_datasource_and_valid_types(self):
        uid = self.datasource["uid"]
        for name, dashboard in self.dashboards.items():
            ids = [p["id"] for p in self.panels(dashboard)]
            self.assertEqual(len(set(ids)), len(ids), f"{name}: panel ids repeat")
            for panel in self.panels(dashboard):
                with self.subTest(dashboard=name, panel=panel.get("title")):
                    self.assertIn(panel["type"], self.PANEL_TYPES)
                    grid = panel["gridPos"]
                    self.assertLessEqual(grid["x"] + grid["w"], 24)
                    if panel["type"] == "row":
                        continue
                    self.assertEqual(panel["datasource"]["uid"], uid)
                    self.assertTrue(panel["targets"])
                    for target in panel["targets"]:
                        self.assertEqual(target["datasource"]["uid"], uid)
                        self.assertTrue(target["expr"].strip())
                    thresholds = panel.get("fieldConfig", {}).get("defaults", {}).get("thresholds")
                    if thresholds:
                        self.assertIn(thresholds["mode"], {"absolute", "percentage"})

    def test_variables_are_defined_and_used_as_regular_expressions(self):
        for name, dashboard in self.dashboards.items():
            variables = {v["name"] for v in dashboard["templating"]["list"]}
            for variable in dashboard["templating"]["list"]:
                self.assertIn(variable["type"], self.VARIABLE_TYPES)
                self.assertEqual(variable["datasource"]["uid"], self.datasource["uid"])
                self.assertRegex(variable["query"], r"^label_values\(.+, \w+\)$")
            exprs = [t["expr"] for p in self.panels(dashboard) for t in p.get("targets", [])]
            exprs += [v["query"] for v in dashboard["templating"]["list"]]
            for expr in exprs:
                with self.subTest(dashboard=name, expr=expr):
                    used = set(re.findall(r"\$\{?(\w+)", expr)) - {"__rate_interval", "__range",
                                                                    "__interval"}
                    self.assertLessEqual(used, variables)
                    # Multi-value variables only inside =~"..." (Grafana writes a regex).
                    for var in used:
                        for match in re.finditer(r"\$\{?" + var + r"\b", expr):
                            self.assertRegex(expr[:match.start()], r'=~"$', expr)


if __name__ == "__main__":
    unittest.main(verbosity=2)
