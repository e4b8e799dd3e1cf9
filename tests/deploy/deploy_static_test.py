"""The deployment files agree with each other and with the code, without
running anything:

- docker-compose.yml and docker-compose.drone2.yml: every behavior system
  built from services/systems/* has a service per vehicle; only the coordinator,
  Prometheus and Grafana are published (on the publish address); every
  service has a restart policy, resource limits and a health check (the gRPC
  health check of behaviorctl on its own --listen port); every address a
  command names is a service's --listen port, also with other ports set in
  the environment; the override repeats the base file's shared settings;
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

PUBLISHED = {"coordinator", "prometheus", "grafana"}
BEHAVIORLIB_IMAGE = "${BEHAVIORLIB_IMAGE:-behaviorlib:latest}"
VEHICLES = {"drone1": [ds.COMPOSE_FILE], "drone2": [ds.COMPOSE_FILE, ds.DRONE2_FILE]}
# Every port variable set to something unusual: references must follow.
PORT_ENV = {"CHANNEL_PORT": "41001", "SIMULATOR_PORT": "41002", "COORDINATOR_PORT": "41003",
            "BEHAVIOR_SYSTEM_PORT": "41004", "COORDINATOR_HOST_PORT": "41005",
            "PROMETHEUS_HOST_PORT": "41006", "GRAFANA_HOST_PORT": "41007",
            "BEHAVIORLIB_PUBLISH_ADDRESS": "0.0.0.0"}
ADDRESS = re.compile(r"(?<![\w.-])([a-z][a-z0-9-]*):(\d+)\b")


def behaviorlib_services(project):
    return {name: s for name, s in project["services"].items()
            if (s.get("command") or [""])[0].startswith(ds.IMAGE_BIN + "/")}


def listen_port(service):
    return ds.port_of(ds.flag_value(service["command"], "--listen"))


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

    def test_only_the_coordinator_prometheus_and_grafana_are_published(self):
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
                        self.assertEqual(service["healthcheck"]["test"],
                                         ["CMD", f"{ds.IMAGE_BIN}/behaviorctl", *tls, "--target",
                                          f"localhost:{listen_port(service)}", "health"])
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
                                      "/opt/behaviorlib/worlds"})
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


class PrometheusTargetsTest(unittest.TestCase):
    def expected_targets(self, project):
        """(address, job, system, robot) of every service's /metrics."""
        targets = set()
        for name, service in behaviorlib_services(project).items():
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

    def test_the_five_dashboards(self):
        self.assertEqual(set(self.dashboards), {
            "fleet_overview.json", "behavior_activity.json", "monitoring_activation_times.json",
            "vehicle_state.json", "simulator_performance.json"})
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
