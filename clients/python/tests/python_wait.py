"""WAIT in Python, for the tests that run a Python behavior system as a program
(test_system_service.py, test_system_security.py): the C++ WAIT's parameters (WaitParameters)
and options, GOAL_ACHIEVED once duration_s of active time has passed."""

from behaviorlib.system import Behavior, Verdict, seconds
from behaviorlib.v1.behaviors.basic_quadrotor_behaviors_pb2 import WaitParameters


class Wait(Behavior):
    """WAIT in Python: finishes GOAL_ACHIEVED once duration_s of active time has passed."""

    Parameters = WaitParameters

    def check_goal(self):
        if self.active_time() >= seconds(self.parameters.duration_s):
            return Verdict.finish("waited")
        return Verdict.keep_going()
