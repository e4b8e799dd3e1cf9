"""The launcher's report (deploy/local/report.py) lists a mission's step
records as a tree, without the built binaries: depth-first in mission order
(the node compared part by part, numbers as numbers; a step's attempts, each
followed by the steps it ran, then its fallback), though the records of
parallel branches interleave; each step indented by its depth (↳ after
non-breaking spaces), labelled with its iteration, branch (and robot) or
fallback, with its node, and its robot for a fleet mission; report.md holds
that table.

    /usr/bin/python3 tests/deploy/report_test.py
"""

import os
import shutil
import sys
import tempfile
import unittest

REPO = os.path.abspath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", ".."))
sys.path.insert(0, os.path.join(REPO, "deploy", "local"))
import report  # noqa: E402

DONE = "MISSION_STEP_STATE_FINISHED"
RUNNING = "MISSION_STEP_STATE_RUNNING"
OK = "TERMINATION_CAUSE_GOAL_ACHIEVED"
B0 = "steps/3/attempt/1/branch/0/steps/"
B1 = "steps/3/attempt/1/branch/1/steps/"
LOOP = "steps/2/attempt/1/iteration/"


def record(node, robot="drone1", **fields):
    r = {"node": node, "robot_id": robot, "attempt": 1, "state": DONE, "cause": OK}
    r.update(fields)
    return r


# A fleet mission's status, its records in the order the coordinator created
# them: the call `hop` timed out in its attempt 1 and ran again; the loop ran
# twice; the parallel step's branches (one per robot) interleave; `land` was
# refused and its fallback ran.
STATUS = {
    "mission_id": "m1", "name": "tree", "robot_id": "drone1",
    "robot_ids": ["drone1", "drone2"], "state": "MISSION_STATE_RUNNING",
    "steps": [
        record("steps/0", name="settle", behavior="WAIT"),
        record("steps/1", name="hop", call="hop", cause="TERMINATION_CAUSE_TIME_OUT"),
        record("steps/1/attempt/1/call/steps/0", behavior="GO_TO",
               cause="TERMINATION_CAUSE_TIME_OUT", message="too slow | twice"),
        record("steps/1", name="hop", call="hop", attempt=2),
        record("steps/1/attempt/2/call/steps/0", behavior="GO_TO"),
        record("steps/2", name="twice", loop="repeat 2 times"),
        record(LOOP + "0/steps/0", behavior="WAIT"),
        record(LOOP + "1/steps/0", behavior="WAIT"),
        record("steps/3", name="both", parallel="all of 2 branches", state=RUNNING, cause=""),
        record(B0 + "0", name="up", behavior="TAKE_OFF"),
        record(B1 + "0", robot="drone2", name="up2", behavior="TAKE_OFF"),
        record(B1 + "1", robot="drone2", name="meet", wait_for="step 'up' achieved"),
        record(B0 + "1", name="sub", call="hop", state=RUNNING, cause=""),
        record(B1 + "2", robot="drone2", name="nap", behavior="WAIT", state=RUNNING, cause=""),
        record(B0 + "1/attempt/1/call/steps/0", behavior="GO_TO", state=RUNNING, cause=""),
        record("steps/4", name="land", behavior="LAND", state="MISSION_STEP_STATE_REFUSED",
               cause=""),
        record("steps/4/fallback/0", name="hover", behavior="WAIT"),
    ],
}

NBSP = "\u00a0"
# (step column, behavior column, node) of each row, in order.
EXPECTED = [
    ("settle", "WAIT", "steps/0"),
    ("hop", "call hop", "steps/1"),
    ("↳ step 0", "GO_TO", "steps/1/attempt/1/call/steps/0"),
    ("hop", "call hop", "steps/1"),
    ("↳ call, attempt 2 · step 0", "GO_TO", "steps/1/attempt/2/call/steps/0"),
    ("twice", "repeat 2 times", "steps/2"),
    ("↳ iteration 0 · step 0", "WAIT", LOOP + "0/steps/0"),
    ("↳ iteration 1 · step 0", "WAIT", LOOP + "1/steps/0"),
    ("both", "parallel, all of 2 branches", "steps/3"),
    ("↳ branch 0 (drone1) · up", "TAKE_OFF", B0 + "0"),
    ("↳ branch 0 (drone1) · sub", "call hop", B0 + "1"),
    (NBSP * 4 + "↳ step 0", "GO_TO", B0 + "1/attempt/1/call/steps/0"),
    ("↳ branch 1 (drone2) · up2", "TAKE_OFF", B1 + "0"),
    ("↳ branch 1 (drone2) · meet", "wait for step 'up' achieved", B1 + "1"),
    ("↳ branch 1 (drone2) · nap", "WAIT", B1 + "2"),
    ("land", "LAND", "steps/4"),
    ("↳ fallback · hover", "WAIT", "steps/4/fallback/0"),
]


def table_rows(lines):
    """The cells of the rows of the first markdown table in `lines`."""
    rows = [line for line in lines if line.startswith("| ")]
    return [[c.strip(" ") for c in row[2:-2].split(" | ")] for row in rows[1:]]


class ReportTreeTest(unittest.TestCase):
    def test_node_order(self):
        nodes = ["steps/10", "steps/2/fallback/0", "steps/2/attempt/1/branch/10/steps/0",
                 "steps/2", "steps/2/attempt/1/branch/2/steps/0", "steps/0",
                 "steps/2/attempt/1/branch/2/steps/0/attempt/1/iteration/0/steps/0",
                 "steps/0/attempt/1/branch/1/steps/0", "steps/1",
                 "steps/0/attempt/1/branch/0/steps/0"]
        ordered = sorted(nodes, key=lambda n: report._node_key({"node": n, "attempt": 1}))
        self.assertEqual(ordered, [
            "steps/0", "steps/0/attempt/1/branch/0/steps/0",
            "steps/0/attempt/1/branch/1/steps/0", "steps/1", "steps/2",
            "steps/2/attempt/1/branch/2/steps/0",
            "steps/2/attempt/1/branch/2/steps/0/attempt/1/iteration/0/steps/0",
            "steps/2/attempt/1/branch/10/steps/0", "steps/2/fallback/0", "steps/10"])

    def test_tree_depths(self):
        tree = report.mission_tree(STATUS)
        self.assertEqual([(r["node"], depth) for r, depth, _ in tree],
                         [(node, node.count("/steps/") + node.count("/fallback/"))
                          for _, _, node in EXPECTED])

    def test_steps_table(self):
        lines = report._steps_md(STATUS, "##")
        header = next(line for line in lines if line.startswith("| step"))
        self.assertEqual(header, "| step | behavior | node | robot | attempt | state | cause | "
                                 "message |")
        rows = table_rows(lines)
        self.assertEqual([tuple(row[:3]) for row in rows], EXPECTED, "\n".join(lines))
        # The robot of each record, its attempt, state and cause.
        by_node = {(row[2], row[4]): row for row in rows}
        self.assertEqual(by_node[(B1 + "1", "1")][3:7], ["drone2", "1", "FINISHED",
                                                         "GOAL_ACHIEVED"])
        self.assertEqual(by_node[("steps/1", "2")][3:7], ["drone1", "2", "FINISHED",
                                                          "GOAL_ACHIEVED"])
        self.assertEqual(by_node[("steps/3", "1")][5:7], ["RUNNING", ""])
        self.assertEqual(by_node[("steps/4", "1")][5], "REFUSED")
        self.assertEqual(by_node[("steps/1/attempt/1/call/steps/0", "1")][7],
                         "too slow \\| twice")

    def test_one_robot_no_robot_column(self):
        status = dict(STATUS, robot_ids=["drone1"],
                      steps=[r for r in STATUS["steps"] if r["robot_id"] == "drone1"])
        lines = report._steps_md(status, "##")
        self.assertIn("| step | behavior | node | attempt | state | cause | message |", lines)
        rows = table_rows(lines)
        self.assertEqual([tuple(row[:3]) for row in rows],
                         [e for e in EXPECTED if "drone2" not in e[0]])

    def test_records_without_node(self):
        # A status journaled before nodes: the path says where.
        status = {"steps": [{"path": [1], "name": "b", "behavior": "LAND"},
                            {"path": [0, 0], "name": "f", "behavior": "WAIT"},
                            {"path": [0], "name": "a", "behavior": "GO_TO"}]}
        self.assertEqual([(label, depth) for _, depth, label in report.mission_tree(status)],
                         [("a", 0), ("fallback · f", 1), ("b", 0)])
        rows = table_rows(report._steps_md(status, "##"))
        self.assertEqual([row[2] for row in rows], ["steps/0", "steps/0/fallback/0", "steps/1"])

    def test_report_md(self):
        run_dir = tempfile.mkdtemp(prefix="report-test-")
        self.addCleanup(shutil.rmtree, run_dir, ignore_errors=True)
        robots = [{"robot_id": robot, "mission_file": "tree.yaml", "mission": STATUS,
                   "behavior_events": [], "samples": []} for robot in ("drone1", "drone2")]
        report.write(run_dir, {"mission": "tree.yaml", "time_scale": "max", "seed": 1}, robots,
                     [], [], True)
        with open(os.path.join(run_dir, "report.md")) as f:
            markdown = f.read()
        for robot in ("drone1", "drone2"):
            section = markdown.split(f"## {robot}: tree (RUNNING)")[1].split("### Timeline")[0]
            rows = table_rows(section.split("\n"))
            self.assertEqual([tuple(row[:3]) for row in rows], EXPECTED, section)


if __name__ == "__main__":
    unittest.main()
