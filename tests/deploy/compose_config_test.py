"""`docker-compose config` accepts deploy/compose/docker-compose.yml alone and
with docker-compose.drone2.yml, without a warning, also with the ports and
addresses set in the environment; and the commands, health checks and ports
it resolves are those the other deployment tests read from the files (so
that what they run is what Compose would run). The world, sensor
configuration, time scale and the world and mission directories it resolves
are the shipped ones by default and the environment's when set; it refuses
the files without GRAFANA_ADMIN_PASSWORD; the data volume is a named volume;
the build context it would send (.dockerignore applied by docker-compose's
own library) holds every file the Dockerfile copies and no build tree,
history or secret.

Runs Debian's docker-compose (1.29) and, when installed, Compose v2
(`docker compose`). No Docker engine is needed. Exits 77 (skipped) when
neither is installed.

    /usr/bin/python3 tests/deploy/compose_config_test.py
"""

import os
import re
import shutil
import subprocess
import sys
import unittest

import yaml

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import deploy_support as ds  # noqa: E402
from deploy_static_test import (PORT_ENV, SCENARIO_DEFAULTS, SCENARIO_ENV,  # noqa: E402
                                SCENARIO_FLAGS, SCENARIO_MOUNTS, copied_sources)

try:  # docker-compose 1.29 builds through docker-py, which applies .dockerignore
    from docker.utils.build import exclude_paths
except ImportError:
    exclude_paths = None

FILE_SETS = {"base": [ds.COMPOSE_FILE], "drone2": [ds.COMPOSE_FILE, ds.DRONE2_FILE]}
# The environments the files are resolved in: nothing set (every default),
# and every port, address and scenario setting set at once (one run of
# Compose each: it takes seconds to start).
ENVS = {"defaults": {}, "settings set": {**PORT_ENV, **SCENARIO_ENV}}


def compose_programs():
    programs = []
    if shutil.which("docker-compose"):
        programs.append(["docker-compose"])
    if shutil.which("docker"):
        probe = subprocess.run(["docker", "compose", "version"], capture_output=True, text=True)
        if probe.returncode == 0:
            programs.append(["docker", "compose"])
    return programs


def clean_env(extra=None):
    """The environment without any variable the Compose files read (so that
    their defaults apply) nor Compose's own settings."""
    names = set(PORT_ENV) | {"BEHAVIORLIB_IMAGE", "PROMETHEUS_IMAGE", "GRAFANA_IMAGE"}
    env = {k: v for k, v in os.environ.items()
           if not k.startswith(("COMPOSE_", "SIMULATOR_", "COORDINATOR_", "GRAFANA_",
                                "PROMETHEUS_", "BEHAVIORLIB_", "DOCKER_")) and k not in names}
    env.update(extra or {})
    return env


def rendered_mounts(service):
    """{container path: (source, read-only)} of a resolved service's volumes,
    in docker-compose 1.29's short syntax or Compose v2's long one."""
    mounts = {}
    for volume in service.get("volumes", []):
        if isinstance(volume, str):
            parts = volume.split(":")
            mounts[parts[1]] = (parts[0], len(parts) > 2 and "ro" in parts[2].split(","))
        else:
            mounts[volume["target"]] = (volume.get("source"), bool(volume.get("read_only")))
    return mounts


def rendered_tmpfs(service):
    tmpfs = service.get("tmpfs") or []
    tmpfs = [tmpfs] if isinstance(tmpfs, str) else list(tmpfs)
    tmpfs += [v["target"] for v in service.get("volumes", [])
              if isinstance(v, dict) and v.get("type") == "tmpfs"]
    return [entry.split(":")[0] for entry in tmpfs]


def normalized_port(mapping):
    return mapping.split("/")[0] if isinstance(mapping, str) else (
        f"{mapping.get('host_ip', '')}:{mapping['published']}:{mapping['target']}")


class ComposeConfigTest(unittest.TestCase):
    # (program, files, environment) -> resolved project, shared by the tests.
    resolved = {}

    def run_config(self, program, files, env):
        argv = [*program, "--project-directory", ds.COMPOSE_DIR]
        for path in files:
            argv += ["-f", path]
        return argv, subprocess.run(argv + ["config"], capture_output=True, text=True,
                                    timeout=60, env=env, cwd=ds.COMPOSE_DIR)

    def config(self, program, files, env):
        key = (tuple(program), tuple(files), tuple(sorted(env.items())))
        if key not in self.resolved:
            self.resolved[key] = self.resolve(program, files, env)
        return self.resolved[key]

    def resolve(self, program, files, env):
        argv, result = self.run_config(program, files, env)
        self.assertEqual(result.returncode, 0, f"{' '.join(argv)} config:\n{result.stderr}")
        warnings = [line for line in result.stderr.splitlines()
                    if "WARN" in line.upper() and "obsolete" not in line]
        self.assertEqual(warnings, [], f"{' '.join(argv)} config warned")
        return yaml.safe_load(result.stdout)

    def test_config_accepts_the_files_and_resolves_them_as_the_tests_do(self):
        for program in compose_programs():
            for label, files in FILE_SETS.items():
                for env_label, env in ENVS.items():
                    with self.subTest(program=" ".join(program), files=label, env=env_label):
                        resolved = self.config(program, files,
                                               clean_env({**ds.REQUIRED_ENV, **env}))
                        ours = ds.load_compose(*files, env=env)
                        self.assertEqual(set(resolved["services"]), set(ours["services"]))
                        for name, service in ours["services"].items():
                            theirs = resolved["services"][name]
                            self.assertEqual(theirs.get("command"), service.get("command"), name)
                            self.assertEqual(theirs["healthcheck"]["test"],
                                             service["healthcheck"]["test"], name)
                            self.assertEqual(
                                sorted(normalized_port(p) for p in theirs.get("ports", [])),
                                sorted(service.get("ports", [])), name)
                            self.assertEqual(theirs.get("restart"), "unless-stopped", name)

    def test_scenario_defaults_and_settings_reach_the_services(self):
        shipped = {"/opt/behaviorlib/worlds": os.path.join(ds.REPO, "simulator", "worlds"),
                   "/opt/behaviorlib/missions": os.path.join(ds.REPO, "deploy", "missions")}
        for program in compose_programs():
            for label, files in FILE_SETS.items():
                for env_label, env in ENVS.items():
                    with self.subTest(program=" ".join(program), files=label, env=env_label):
                        services = self.config(program, files, clean_env(
                            {**ds.REQUIRED_ENV, **env}))["services"]
                        for name, defaults in SCENARIO_DEFAULTS.items():
                            flags = {**defaults, **(SCENARIO_FLAGS.get(name, {}) if env else {})}
                            for flag, value in flags.items():
                                self.assertEqual(ds.flag_value(services[name]["command"], flag),
                                                 value, f"{name} {flag}")
                        for name, expected in SCENARIO_MOUNTS.items():
                            mounts = rendered_mounts(services[name])
                            for target, source in expected.items():
                                self.assertEqual(mounts.get(target),
                                                 (source if env else shipped[target], True),
                                                 f"{name} {target}")

    def test_grafana_admin_password_is_required(self):
        for program in compose_programs():
            for label, files in FILE_SETS.items():
                with self.subTest(program=" ".join(program), files=label):
                    unset = [clean_env()]
                    if label == "base":  # an empty value is no password either (`:?`)
                        unset.append(clean_env({"GRAFANA_ADMIN_PASSWORD": ""}))
                    for env in unset:
                        argv, result = self.run_config(program, files, env)
                        self.assertNotEqual(result.returncode, 0,
                                            f"{' '.join(argv)} config without a Grafana password")
                        self.assertIn("set GRAFANA_ADMIN_PASSWORD", result.stderr)
                    services = self.config(program, files, clean_env(ds.REQUIRED_ENV))["services"]
                    self.assertEqual(services["grafana"]["environment"]
                                     ["GF_SECURITY_ADMIN_PASSWORD"],
                                     ds.REQUIRED_ENV["GRAFANA_ADMIN_PASSWORD"])

    def test_the_data_volume_is_a_named_volume(self):
        for program in compose_programs():
            for label, files in FILE_SETS.items():
                with self.subTest(program=" ".join(program), files=label):
                    resolved = self.config(program, files, clean_env(ds.REQUIRED_ENV))
                    self.assertIn("behaviorlib-data", resolved.get("volumes") or {})
                    for name, service in resolved["services"].items():
                        if name != "coordinator" and not name.startswith("drone"):
                            continue
                        self.assertEqual(rendered_mounts(service).get("/var/lib/behaviorlib"),
                                         ("behaviorlib-data", False), name)
                        self.assertFalse([t for t in rendered_tmpfs(service)
                                          if "/var/lib/behaviorlib".startswith(t.rstrip("/"))
                                          or t.startswith("/var/lib/behaviorlib")], name)

    @unittest.skipUnless(exclude_paths, "docker-py (python3-docker) is not installed")
    def test_build_context_holds_what_the_dockerfile_copies_and_no_more(self):
        # As docker-py reads .dockerignore before it tars the context.
        with open(os.path.join(ds.REPO, ".dockerignore")) as f:
            patterns = [line.strip() for line in f.read().splitlines()
                        if line.strip() and not line.strip().startswith("#")]
        dockerfile = os.path.relpath(ds.DOCKERFILE, ds.REPO)
        context = set(exclude_paths(ds.REPO, patterns, dockerfile=dockerfile))
        sources = copied_sources()
        files, why = ds.tracked_files(sources)
        if files is None:
            self.skipTest(f"not a git checkout: {why}")
        self.assertGreater(len(files), 100)
        self.assertEqual(sorted(set(files) - context), [])
        self.assertIn(dockerfile, context)
        left_out = re.compile(r"^(build[^/]*|\.git|deploy/certs|tests|docs)(/|$)"
                              r"|(^|/)(__pycache__|node_modules)(/|$)|\.pyc$"
                              r"|^deploy/compose/\.env$")
        self.assertEqual(sorted(p for p in context if left_out.search(p)), [])


if __name__ == "__main__":
    if not compose_programs():
        print("SKIPPED: neither docker-compose nor `docker compose` is installed; "
              "install Debian's docker-compose (scripts/install-deps.sh) to validate "
              "deploy/compose/*.yml")
        sys.exit(ds.SKIP)
    unittest.main(verbosity=2)
