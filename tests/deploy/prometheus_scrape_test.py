"""A real scrape: Debian's Prometheus, on 127.0.0.1 with
deploy/prometheus/prometheus-local.yml and the alert rules, scrapes the
local launcher's processes (deploy/local/launch.py, its
prometheus_targets.json linked into local-targets/ as the configuration's
comment says) while the demo mission flies through the coordinator. Then,
through Prometheus's HTTP API:

- every target is up, with the launcher's job/system/robot labels;
- behaviorlib_activations_total, behaviorlib_terminations_total by cause
  (all six causes, GOAL_ACHIEVED and INTERRUPTED moved) and the
  activation-time histogram (behaviorlib_activation_seconds) exist and
  moved during the mission;
- the coordinator counted the mission (started, succeeded by GOAL_ACHIEVED),
  and every process exposes its gRPC calls, process_* and build info;
- `promtool check metrics` accepts every process's /metrics page;
- every alert rule evaluates without error;
- every PromQL expression of the Grafana dashboards (panel queries and
  variable queries, with Grafana's variables substituted) returns data.

    /usr/bin/python3 tests/deploy/prometheus_scrape_test.py --build-dir build
"""

import argparse
import json
import math
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import unittest
import urllib.request

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import deploy_support as ds  # noqa: E402

LAUNCHER = os.path.join(ds.REPO, "deploy", "local", "launch.py")
sys.path.insert(0, os.path.dirname(LAUNCHER))
import demo  # noqa: E402
import rpc  # noqa: E402

BUILD_DIR = ds.DEFAULT_BUILD_DIR
ROBOT = "drone1"
# As tests/e2e/local_demo_test.py: the deterministic mode, where a loaded
# machine slows the mission instead of failing it.
TIME_SCALE = "max"
MISSION = os.path.join(ds.REPO, "deploy", "missions", "demo.yaml")
MISSION_TIMEOUT_S = 40.0
FLOWN = ("TAKE_OFF", "FOLLOW_PATH", "ROTATE_WITH_PID_CONTROL", "LAND")
CAUSES = ("GOAL_ACHIEVED", "TIME_OUT", "WRONG_PROGRESS", "SITUATION_CHANGE", "PROCESS_FAILURE",
          "INTERRUPTED")
SCRAPE_INTERVAL_S = 2  # prometheus-local.yml
PROMTOOL = shutil.which("promtool") or "/usr/bin/promtool"
# Grafana's $__rate_interval is at least four scrape intervals.
RATE_INTERVAL = f"{4 * SCRAPE_INTERVAL_S + SCRAPE_INTERVAL_S}s"


def dashboard_queries():
    """(dashboard, what, expression, instant) of every query of every
    dashboard: panel targets and variable queries."""
    queries = []
    for name in sorted(os.listdir(ds.DASHBOARDS_DIR)):
        with open(os.path.join(ds.DASHBOARDS_DIR, name)) as f:
            dashboard = json.load(f)
        for variable in dashboard["templating"]["list"]:
            queries.append((name, f"variable ${variable['name']}", variable["query"], True))
        panels = []
        for panel in dashboard["panels"]:
            panels += [panel, *panel.get("panels", [])]
        for panel in panels:
            for target in panel.get("targets", []):
                queries.append((name, f"{panel['title']} [{target['refId']}]", target["expr"],
                                bool(target.get("instant"))))
    return queries


def substitute(expr, range_s):
    """Grafana's substitutions: its interval variables, and every dashboard
    variable set to All (allValue ".+"); label_values(m, l) as PromQL."""
    expr = (expr.replace("$__rate_interval", RATE_INTERVAL)
            .replace("$__range", f"{range_s}s").replace("$__interval", f"{SCRAPE_INTERVAL_S}s"))
    expr = re.sub(r"\$\{?(\w+)\}?", ".+", expr)
    match = re.fullmatch(r"label_values\((.+), (\w+)\)", expr)
    if match:
        expr = f"count by ({match.group(2)}) ({match.group(1)})"
    return expr


class PrometheusScrapeTest(unittest.TestCase):
    def setUp(self):
        self.started = time.monotonic()
        self.tmp = tempfile.mkdtemp(prefix="prometheus-scrape-")
        self.run_dir = os.path.join(self.tmp, "run")
        self.launcher = None
        self.launcher_log = os.path.join(self.tmp, "launcher.log")
        self.prometheus = None

    def tearDown(self):
        if self.prometheus:
            self.prometheus.stop()
        if self.launcher and self.launcher.poll() is None:
            self.launcher.send_signal(signal.SIGINT)  # stops the stack in order
            try:
                self.launcher.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.launcher.kill()
                self.launcher.wait()
        try:
            with open(os.path.join(self.run_dir, "pids.json")) as f:
                for pid in json.load(f).values():
                    if ds.alive(pid):
                        os.kill(pid, signal.SIGKILL)
        except (OSError, ValueError):
            pass
        shutil.rmtree(self.tmp, ignore_errors=True)

    def say(self, text):
        print(f"[{time.monotonic() - self.started:5.1f} s] {text}", flush=True)

    def start_stack(self):
        log = open(self.launcher_log, "wb")
        self.launcher = subprocess.Popen(
            [sys.executable, LAUNCHER, "--build-dir", BUILD_DIR, "--run-dir", self.run_dir,
             "--time-scale", TIME_SCALE, "--robot-id", ROBOT],
            stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT)
        log.close()

        def serving():
            if self.launcher.poll() is not None:
                raise AssertionError(f"the launcher exited with code {self.launcher.returncode}:"
                                     f"\n{ds.log_tail(self.launcher_log, 40)}")
            with open(self.launcher_log, errors="replace") as f:
                return "Ctrl-C stops everything." in f.read()

        ds.wait_for(serving, 45, "the local stack serving", interval_s=0.2)
        with open(os.path.join(self.run_dir, "prometheus_targets.json")) as f:
            return json.load(f)

    def start_prometheus(self):
        """prometheus-local.yml and the rules from their place in the tree
        (linked, so that relative paths resolve as beside the file), the
        launcher's targets linked into local-targets/."""
        directory = os.path.join(self.tmp, "prometheus")
        os.makedirs(os.path.join(directory, "local-targets"))
        config = os.path.join(directory, "prometheus-local.yml")
        os.symlink(os.path.join(ds.PROMETHEUS_DIR, "prometheus-local.yml"), config)
        os.symlink(os.path.join(ds.PROMETHEUS_DIR, "rules"), os.path.join(directory, "rules"))
        os.symlink(os.path.join(self.run_dir, "prometheus_targets.json"),
                   os.path.join(directory, "local-targets", "run.json"))
        self.prometheus = ds.Prometheus(config, os.path.join(directory, "data"),
                                        os.path.join(self.tmp, "prometheus.log"),
                                        ["--log.level=warn"])
        self.prometheus.wait_ready()

    def wait_scraped_after(self, t, what):
        """Until every target has been scraped after wall time `t`."""
        ds.wait_for(lambda: self.prometheus.scalar("min(timestamp(up))") > t,
                    4 * SCRAPE_INTERVAL_S + 5, f"a scrape of every target after {what}", 0.2)

    def totals(self):
        p = self.prometheus

        def by(label, expr):
            return {r["metric"][label]: float(r["value"][1])
                    for r in p.query(expr)["result"]}

        return {
            "activations": p.scalar("sum(behaviorlib_activations_total)"),
            "activation_count": p.scalar("sum(behaviorlib_activation_seconds_count)"),
            "by_behavior": by("behavior", "sum by (behavior) (behaviorlib_activations_total)"),
            "by_cause": by("cause", "sum by (cause) (behaviorlib_terminations_total)"),
        }

    def fly_demo(self):
        with open(os.path.join(self.run_dir, "ports", "coordinator.ports")) as f:
            port = dict(line.strip().split("=") for line in f if "=" in line)["grpc_port"]
        coordinator = rpc.Client(f"127.0.0.1:{port}", [demo.COORDINATOR])
        try:
            status = demo.run_mission(coordinator, MISSION, ROBOT, f"scrape-{os.getpid()}",
                                      MISSION_TIMEOUT_S, self.say, lambda status: None)
        finally:
            coordinator.close()
        return status

    def test_prometheus_scrapes_the_stack_during_the_demo_mission(self):
        targets = self.start_stack()
        self.say(f"stack serving: {len(targets)} targets")
        self.start_prometheus()
        self.say(f"prometheus ready on 127.0.0.1:{self.prometheus.port}")

        # Every target up, with the launcher's labels.
        expected = {t["targets"][0]: t["labels"] for t in targets}
        self.assertIn("behavior_system", {labels["job"] for labels in expected.values()})

        def all_up():
            active = self.prometheus.get("/api/v1/targets")["activeTargets"]
            up = {t["discoveredLabels"]["__address__"]: t for t in active if t["health"] == "up"}
            return set(up) == set(expected) and up

        active = ds.wait_for(all_up, 20, f"every target of {sorted(expected)} up", 0.2)
        for address, labels in expected.items():
            for key, value in labels.items():
                self.assertEqual(active[address]["labels"].get(key), value, address)

        self.wait_scraped_after(time.time(), "the start")
        before = self.totals()
        self.say(f"before the mission: {before['activations']:.0f} activations")
        mission_start = time.time()
        status = self.fly_demo()
        self.assertEqual(status.get("state"), "MISSION_STATE_SUCCEEDED", status)
        self.say("mission succeeded")

        # The recurrent localization is ended by the mission's end.
        ds.wait_for(lambda: self.totals()["by_cause"].get("INTERRUPTED", 0) >
                    before["by_cause"].get("INTERRUPTED", 0), 15,
                    "an INTERRUPTED termination scraped", 0.5)
        self.wait_scraped_after(time.time(), "the mission")
        after = self.totals()
        window_s = math.ceil(time.time() - mission_start) + 2 * SCRAPE_INTERVAL_S
        self.say(f"after the mission: {after}")

        # Activations moved: one per step the mission ran (demo.yaml may fly
        # FOLLOW_PATH again after WRONG_PROGRESS).
        self.assertGreaterEqual(after["activations"] - before["activations"], 6)
        for behavior in FLOWN:
            steps = [s for s in status.get("steps", []) if s.get("behavior") == behavior]
            self.assertTrue(steps, f"no {behavior} step in {status}")
            self.assertEqual(after["by_behavior"].get(behavior, 0) -
                             before["by_behavior"].get(behavior, 0), len(steps), behavior)
        moved = self.prometheus.scalar(
            f"sum(increase(behaviorlib_activations_total[{window_s}s]))")
        self.assertGreater(moved, 0)

        # Terminations: a series per cause, GOAL_ACHIEVED and INTERRUPTED moved.
        self.assertEqual(set(after["by_cause"]), set(CAUSES))
        self.assertGreaterEqual(after["by_cause"]["GOAL_ACHIEVED"] -
                                before["by_cause"]["GOAL_ACHIEVED"], len(FLOWN))
        self.assertGreater(after["by_cause"]["INTERRUPTED"], before["by_cause"]["INTERRUPTED"])
        labels = self.prometheus.query(
            'behaviorlib_terminations_total{behavior="TAKE_OFF", cause="GOAL_ACHIEVED"}')["result"]
        self.assertEqual(len(labels), 1, labels)
        self.assertEqual(labels[0]["metric"]["robot"], ROBOT)
        self.assertEqual(labels[0]["metric"]["system"], "basic_quadrotor_behaviors")
        self.assertEqual(labels[0]["metric"]["job"], "behavior_system")

        # The activation-time histogram: every bucket, counts moved, a p99.
        self.assertGreaterEqual(after["activation_count"] - before["activation_count"], 6)
        buckets = {r["metric"]["le"] for r in self.prometheus.query(
            'behaviorlib_activation_seconds_bucket{behavior="TAKE_OFF"}')["result"]}
        self.assertIn("+Inf", buckets)
        self.assertGreaterEqual(len(buckets), 10)
        p99 = self.prometheus.scalar(
            "histogram_quantile(0.99, sum by (le) (increase("
            f"behaviorlib_activation_seconds_bucket[{window_s}s])))")
        self.assertTrue(0 < p99 <= 1.0, p99)
        self.say(f"activation time p99 during the mission: {p99 * 1e3:.3f} ms")

        # The coordinator counted the mission; every process its gRPC calls,
        # its resources and its build.
        started = self.prometheus.scalar(
            f'sum(behaviorlib_coordinator_missions_started_total{{robot="{ROBOT}"}})')
        self.assertEqual(started, 1)
        finished = self.prometheus.query("behaviorlib_coordinator_missions_finished_total")
        self.assertEqual([(r["metric"]["robot"], r["metric"]["outcome"], r["metric"]["cause"],
                           r["value"][1]) for r in finished["result"]],
                         [(ROBOT, "succeeded", "GOAL_ACHIEVED", "1")])
        handled = self.prometheus.scalar(
            'sum(grpc_server_handled_total{job="coordinator", grpc_service='
            '"behaviorlib.v1.Coordinator", grpc_method="StartMission", grpc_code="OK"})')
        self.assertEqual(handled, 1)
        for metric in ("behaviorlib_build_info", "process_resident_memory_bytes",
                       "process_cpu_seconds_total", "grpc_server_started_total"):
            instances = {r["metric"]["instance"] for r in self.prometheus.query(metric)["result"]}
            self.assertEqual(instances, set(expected), metric)
        self.assertEqual(self.prometheus.query(
            'grpc_server_handled_total{grpc_code=~"INTERNAL|UNKNOWN|DATA_LOSS"}')["result"], [])

        # promtool accepts every process's page (names, units, help, types).
        for address in sorted(expected):
            with urllib.request.urlopen(f"http://{address}/metrics", timeout=10) as reply:
                page = reply.read()
            result = subprocess.run([PROMTOOL, "check", "metrics"], input=page,
                                    capture_output=True, timeout=30)
            output = (result.stdout + result.stderr).decode(errors="replace")
            self.assertEqual((result.returncode, output), (0, ""), address)
        self.say(f"promtool check metrics: {len(expected)} pages clean")

        # The alert rules evaluate without error.
        def rules_evaluated():
            rules = [r for g in self.prometheus.get("/api/v1/rules")["groups"] for r in g["rules"]]
            return rules if all(r.get("lastEvaluation", "").startswith("20") for r in rules) \
                else None

        rules = ds.wait_for(rules_evaluated, 10, "every rule evaluated", 0.5)
        self.assertGreaterEqual(len(rules), 5)
        for rule in rules:
            self.assertEqual(rule["health"], "ok", f"{rule['name']}: {rule.get('lastError')}")

        # Every dashboard expression returns data.
        query_time = time.time()
        range_s = math.ceil(query_time - mission_start) + 2 * SCRAPE_INTERVAL_S
        range_steps = math.ceil((query_time - mission_start) / SCRAPE_INTERVAL_S) + 1
        empty, nan_only = [], []
        queries = dashboard_queries()
        self.assertGreater(len(queries), 40)
        for dashboard, what, expr, instant in queries:
            promql = substitute(expr, range_s)
            try:
                if instant:
                    result = self.prometheus.query(promql, at=query_time)["result"]
                    values = [r["value"][1] for r in result]
                else:
                    # The last step is the query time itself, after the
                    # scrape that followed the mission: a series born at the
                    # mission's end (missions finished) is inside the range
                    # whatever the steps' phase against the scrapes.
                    result = self.prometheus.query_range(
                        promql, query_time - range_steps * SCRAPE_INTERVAL_S, query_time,
                        SCRAPE_INTERVAL_S)["result"]
                    values = [v[1] for r in result for v in r["values"]]
            except (OSError, AssertionError) as error:  # a 400: not valid PromQL
                body = error.read().decode() if hasattr(error, "read") else ""
                empty.append(f"{dashboard}: {what}: {promql}: {error} {body}")
                continue
            if not result:
                empty.append(f"{dashboard}: {what}: {promql}")
            elif all(v == "NaN" for v in values):
                nan_only.append(f"{dashboard}: {what}")
        self.say(f"{len(queries)} dashboard queries run; only NaN (no observation in the "
                 f"window, e.g. no camera subscribed): {nan_only}")
        self.assertEqual(empty, [], "dashboard expressions that failed or returned nothing")
        self.say("done")


if __name__ == "__main__":
    parser = argparse.ArgumentParser()
    parser.add_argument("--build-dir", default=BUILD_DIR)
    args, rest = parser.parse_known_args()
    BUILD_DIR = os.path.abspath(args.build_dir)
    unittest.main(argv=[sys.argv[0], *rest], verbosity=2)
