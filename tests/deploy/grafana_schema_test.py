"""Type-checks every Grafana dashboard of deploy/grafana/dashboards against
Grafana's published schema types: `npm ci` installs @grafana/schema and
TypeScript at the versions pinned by tests/deploy/grafana_schema/
package-lock.json into --work-dir (the build tree, never the sources), then
`tsc` compiles tests/deploy/grafana_schema/check_dashboards.ts, which types
each dashboard JSON as the schema's Dashboard (and rejects keys it does not
know). Also checks that the checker catches a broken dashboard, that every
dashboard file is checked, that panel types are Grafana panel plugins the
schema describes, and that the schema's version is the Grafana image's.

Exits 77 (skipped) when npm is not installed or its registry cannot be reached,
which the first `npm ci` of a work directory needs.

    /usr/bin/python3 tests/deploy/grafana_schema_test.py --work-dir build/tests/deploy/grafana_schema
"""

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import unittest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import deploy_support as ds  # noqa: E402

SOURCE = os.path.join(ds.REPO, "tests", "deploy", "grafana_schema")
CHECK_TS = os.path.join(SOURCE, "check_dashboards.ts")
WORK_DIR = None  # set in main


def tsc(work, check_ts):
    """Runs tsc on `check_ts` with the schema installed in `work`; returns
    (exit code, output)."""
    config = os.path.join(work, f"tsconfig.{os.path.basename(check_ts)}.json")
    with open(config, "w") as f:
        json.dump({"extends": os.path.join(SOURCE, "tsconfig.json"),
                   "compilerOptions": {"paths": {"@grafana/schema": [
                       os.path.join(work, "node_modules", "@grafana", "schema")]}},
                   "files": [check_ts]}, f, indent=2)
    result = subprocess.run([os.path.join(work, "node_modules", ".bin", "tsc"), "-p", config],
                            capture_output=True, text=True, timeout=180)
    return result.returncode, result.stdout + result.stderr


class GrafanaSchemaTest(unittest.TestCase):
    def test_every_dashboard_is_checked(self):
        with open(CHECK_TS) as f:
            source = f.read()
        imports = dict((path, name) for name, path in re.findall(
            r"^import (\w+) from '\.\./\.\./\.\./deploy/grafana/dashboards/([\w.]+)';$", source,
            re.MULTILINE))
        self.assertEqual(set(imports), set(os.listdir(ds.DASHBOARDS_DIR)),
                         "check_dashboards.ts must import every dashboard")
        for name in imports.values():
            self.assertRegex(source, rf"export const \w+: Schema = {name};")
            self.assertRegex(source, rf"export const \w+: Exact<typeof {name}, Schema> =\s+{name};")

    def test_dashboards_type_check_against_the_schema(self):
        code, output = tsc(WORK_DIR, CHECK_TS)
        self.assertEqual(code, 0, f"tsc found dashboards that do not fit @grafana/schema:\n"
                                  f"{output}")

    def test_the_check_rejects_a_broken_dashboard(self):
        with tempfile.TemporaryDirectory(dir=WORK_DIR) as tmp:
            dashboards = os.path.join(tmp, "dashboards")
            os.makedirs(dashboards)
            for name in os.listdir(ds.DASHBOARDS_DIR):
                with open(os.path.join(ds.DASHBOARDS_DIR, name)) as f:
                    dashboard = json.load(f)
                if name == "fleet_overview.json":
                    panel = dashboard["panels"][1]
                    panel["gridpos"] = panel.pop("gridPos")  # misspelt key
                if name == "vehicle_state.json":
                    dashboard["schemaVersion"] = "42"  # wrong type
                with open(os.path.join(dashboards, name), "w") as f:
                    json.dump(dashboard, f)
            with open(CHECK_TS) as f:
                source = f.read().replace("'../../../deploy/grafana/dashboards/",
                                          "'./dashboards/")
            check = os.path.join(tmp, "check_broken.ts")
            with open(check, "w") as f:
                f.write(source)
            code, output = tsc(WORK_DIR, check)
        self.assertNotEqual(code, 0, output)
        self.assertIn('key \\"gridpos\\" is not in the Grafana dashboard schema', output)
        self.assertRegex(output, r"Type 'string' is not assignable to type 'number'")

    def test_panel_types_are_panels_the_schema_describes(self):
        composable = os.path.join(WORK_DIR, "node_modules", "@grafana", "schema", "dist", "types",
                                  "raw", "composable")
        known = {name for name in os.listdir(composable)
                 if os.path.isdir(os.path.join(composable, name, "panelcfg"))} | {"row"}
        for name in os.listdir(ds.DASHBOARDS_DIR):
            with open(os.path.join(ds.DASHBOARDS_DIR, name)) as f:
                dashboard = json.load(f)
            for panel in dashboard["panels"]:
                with self.subTest(dashboard=name, panel=panel.get("title")):
                    self.assertIn(panel["type"].replace("-", ""), known)

    def test_schema_version_is_the_grafana_images(self):
        with open(os.path.join(WORK_DIR, "node_modules", "@grafana", "schema",
                               "package.json")) as f:
            version = json.load(f)["version"]
        image = ds.read_yaml(ds.COMPOSE_FILE)["services"]["grafana"]["image"]
        self.assertEqual(image, "${GRAFANA_IMAGE:-grafana/grafana:" + version + "}")


def main():
    global WORK_DIR
    parser = argparse.ArgumentParser()
    parser.add_argument("--work-dir", default="",
                        help="where npm ci installs (default: a temporary directory)")
    args, rest = parser.parse_known_args()
    if not shutil.which("npm"):
        print("SKIPPED: npm is not installed, so the Grafana dashboards cannot be type-checked "
              "against @grafana/schema (install Node.js with npm to run this test)")
        return ds.SKIP
    WORK_DIR = os.path.abspath(args.work_dir) if args.work_dir else tempfile.mkdtemp(
        prefix="grafana-schema-")
    try:
        ds.npm_ci(SOURCE, WORK_DIR)
    except ds.RegistryUnreachable as error:
        print(f"SKIPPED: {error}")
        return ds.SKIP
    program = unittest.main(argv=[sys.argv[0], *rest], verbosity=2, exit=False)
    return 0 if program.result.wasSuccessful() else 1


if __name__ == "__main__":
    sys.exit(main())
