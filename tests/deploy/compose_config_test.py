"""`docker-compose config` accepts deploy/compose/docker-compose.yml alone and
with docker-compose.drone2.yml, without a warning, also with the ports and
addresses set in the environment; and the commands, health checks and ports
it resolves are those the other deployment tests read from the files (so
that what they run is what Compose would run).

Runs Debian's docker-compose (1.29) and, when installed, Compose v2
(`docker compose`). No Docker engine is needed. Exits 77 (skipped) when
neither is installed.

    /usr/bin/python3 tests/deploy/compose_config_test.py
"""

import os
import shutil
import subprocess
import sys
import unittest

import yaml

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import deploy_support as ds  # noqa: E402
from deploy_static_test import PORT_ENV  # noqa: E402

FILE_SETS = {"base": [ds.COMPOSE_FILE], "drone2": [ds.COMPOSE_FILE, ds.DRONE2_FILE]}


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


def normalized_port(mapping):
    return mapping.split("/")[0] if isinstance(mapping, str) else (
        f"{mapping.get('host_ip', '')}:{mapping['published']}:{mapping['target']}")


class ComposeConfigTest(unittest.TestCase):
    def config(self, program, files, env):
        argv = [*program, "--project-directory", ds.COMPOSE_DIR]
        for path in files:
            argv += ["-f", path]
        result = subprocess.run(argv + ["config"], capture_output=True, text=True, timeout=60,
                                env=env, cwd=ds.COMPOSE_DIR)
        self.assertEqual(result.returncode, 0, f"{' '.join(argv)} config:\n{result.stderr}")
        warnings = [line for line in result.stderr.splitlines()
                    if "WARN" in line.upper() and "obsolete" not in line]
        self.assertEqual(warnings, [], f"{' '.join(argv)} config warned")
        return yaml.safe_load(result.stdout)

    def test_config_accepts_the_files_and_resolves_them_as_the_tests_do(self):
        for program in compose_programs():
            for label, files in FILE_SETS.items():
                for env_label, env in (("defaults", {}), ("ports set", PORT_ENV)):
                    with self.subTest(program=" ".join(program), files=label, env=env_label):
                        resolved = self.config(program, files, clean_env(env))
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


if __name__ == "__main__":
    if not compose_programs():
        print("SKIPPED: neither docker-compose nor `docker compose` is installed; "
              "install Debian's docker-compose (scripts/install-deps.sh) to validate "
              "deploy/compose/*.yml")
        sys.exit(ds.SKIP)
    unittest.main(verbosity=2)
