"""contract_behaviors in Python: the twin of contract_behaviors.cc for the lifecycle contract
suite (behavior_system_test, run against both). It hosts WAIT, with the C++ WAIT's parameters
(WaitParameters), and CONTRACT_PROBE, whose parameters are declared here in Python to be the
message contract_probe.proto declares; the suite compares the two systems' descriptions.

    build/venv/bin/python tests/integration/contract/contract_behaviors.py --robot-id r1 \\
        --listen 127.0.0.1:0 --port-file p.ports
"""

import sys
import time

import grpc

from behaviorlib.system import Behavior, Situation, StatusError, Verdict, run_system, seconds
from behaviorlib.system.declare import Field, declare_parameters
from behaviorlib.v1 import errors_pb2
from behaviorlib.v1.behaviors.basic_quadrotor_behaviors_pb2 import WaitParameters

ContractProbeParameters = declare_parameters(
    "ContractProbeParameters", package="behaviorlib.tests.v1", behavior="CONTRACT_PROBE",
    doc="CONTRACT_PROBE: does nothing until after_s of active time has passed, then\n"
        "ends through the functions its parameters name. When several do, the\n"
        "library's monitoring order decides which one ends it.",
    fields=[
        Field("after_s", "double", range=(0, 60), default=0,
              doc="Active time in seconds before the named functions act."),
        Field("fail_processes", "bool",
              doc="checkProcesses reports a failed process: PROCESS_FAILURE."),
        Field("change_situation", "bool",
              doc="checkSituation reports the situation infeasible: SITUATION_CHANGE."),
        Field("achieve_goal", "bool", doc="checkGoal finishes: GOAL_ACHIEVED."),
        Field("wrong_progress", "bool", doc="checkProgress finishes: WRONG_PROGRESS."),
        Field("throw_in_execute", "bool",
              doc="onExecute throws (C++) or raises (Python): PROCESS_FAILURE naming it."),
        Field("block_s", "double", range=(0, 10), default=0,
              doc="onExecute blocks this long, in seconds, once: past the watchdog's 1 s,\n"
                  "PROCESS_FAILURE from the watchdog."),
        Field("refuse_activation", "string",
              doc="When not empty, onActivate refuses the activation with this reason."),
        Field("time_out_s", "double", range=(0, 3600), default=0,
              doc="The activation's maximum active time in seconds (TIME_OUT); 0: none."),
    ])


class Wait(Behavior):
    """WAIT: finishes GOAL_ACHIEVED once duration_s of active time has passed."""

    Parameters = WaitParameters

    def check_goal(self):
        if self.active_time() >= seconds(self.parameters.duration_s):
            return Verdict.finish(f"waited {self.parameters.duration_s:g} s")
        return Verdict.keep_going()


class ContractProbe(Behavior):
    """CONTRACT_PROBE, as contract_probe_behavior.h."""

    Parameters = ContractProbeParameters

    def __init__(self):
        super().__init__()
        self._active = False
        self._blocked = False

    def on_activate(self):
        if self.parameters.refuse_activation:
            raise StatusError(grpc.StatusCode.FAILED_PRECONDITION,
                              self.parameters.refuse_activation)
        self._active = True
        self._blocked = False
        if self.parameters.time_out_s > 0:
            self.set_maximum_execution_time(seconds(self.parameters.time_out_s),
                                            "the probe's time_out_s of active time passed")

    def on_deactivate(self):
        self._active = False

    def _due(self):
        return self.active_time() >= seconds(self.parameters.after_s)

    def on_execute(self):
        if not self._due():
            return
        if self.parameters.throw_in_execute:
            raise RuntimeError("the probe throws")
        if self.parameters.block_s > 0 and not self._blocked:
            self._blocked = True
            time.sleep(self.parameters.block_s)

    def check_processes(self):
        if self._due() and self.parameters.fail_processes:
            return Verdict.finish("the probe's process failed")
        return Verdict.keep_going()

    def check_situation(self):
        # Also asked before an activation (and by CheckSituation while inactive), when there
        # are no parameters: the situation is then fine.
        if self._active and self._due() and self.parameters.change_situation:
            return Situation.infeasible(errors_pb2.SITUATION_REASON_CONFIGURATION,
                                        "the probe's situation changed")
        return Situation.ok()

    def check_goal(self):
        if self._due() and self.parameters.achieve_goal:
            return Verdict.finish("the probe's goal achieved")
        return Verdict.keep_going()

    def check_progress(self):
        if self._due() and self.parameters.wrong_progress:
            return Verdict.finish("the probe made no progress")
        return Verdict.keep_going()


if __name__ == "__main__":
    sys.exit(run_system([Wait(), ContractProbe()], system="contract_behaviors"))
