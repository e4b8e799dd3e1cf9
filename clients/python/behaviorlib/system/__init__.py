"""behaviorlib.system: behaviors written in Python, run by a port of the C++ engine's contract
(decision 47, section 2). Its core is transport-free: the injected clock
(clock.py), parameter validation driven by the (behaviorlib.v1.param) options (parameters.py),
and the Behavior base class with its ExecutionManager and the resumable event log (engine.py).
The process around it (main.py: run_system) serves what a C++ behavior system serves: the
BehaviorSystem service and a typed service per behavior (service.py, typed.py), health
(health.py), reflection (reflection.py) and /metrics (metrics.py), and registers with the
coordinator (registration.py). With --follow-time it follows the simulator's time grants
(time_follower.py: the deterministic mode).
"""

from .clock import (NANOS_PER_SECOND, Clock, ClockListener, FakeClock, SteadyClock, seconds,
                    to_seconds)
from .engine import (Behavior, BehaviorContext, BehaviorObserver, BehaviorOptions, Delivery,
                     EventLog, ExecutionManager, Situation, Subscription, Verdict, cause_name,
                     declared_behavior_name, new_incarnation_id, parameter_error)
from .main import BehaviorSystemProcess, SystemContext, run_system
from .parameters import (StatusError, apply_defaults_and_validate, describe, from_struct,
                         leading_comment, load_descriptor_set, merge_update, number_text,
                         range_text, to_struct, unit_of_field_name)
from .time_follower import TimeFollower

__all__ = [
    "NANOS_PER_SECOND", "Clock", "ClockListener", "FakeClock", "SteadyClock", "seconds",
    "to_seconds",
    "Behavior", "BehaviorContext", "BehaviorObserver", "BehaviorOptions", "Delivery", "EventLog",
    "ExecutionManager", "Situation", "Subscription", "Verdict", "cause_name",
    "declared_behavior_name", "new_incarnation_id", "parameter_error",
    "BehaviorSystemProcess", "SystemContext", "run_system",
    "StatusError", "apply_defaults_and_validate", "describe", "from_struct", "leading_comment",
    "load_descriptor_set", "merge_update", "number_text", "range_text", "to_struct",
    "unit_of_field_name",
    "TimeFollower",
]
