"""CIRCLE_AROUND: a behavior written in Python that flies circles around a point, facing it (an
inspection pattern). It reads the pose estimate, publishes motion references that a motion
controller (QUADROTOR_PID_MOTION_CONTROL) follows, and manages its own execution with the paper's
functions: the situation (a fresh estimate, the vehicle flying), the goal (the turns flown and
the vehicle at the end), the progress (the vehicle near the reference), the processes (the
estimate and a controller following this activation's references).

Its parameters are declared in Python (behaviorlib.system.declare): the same message, options
and error details as a .proto would give.
"""

import math

import grpc

from behaviorlib.system import (Behavior, BehaviorOptions, Delivery, Situation, StatusError,
                                Verdict, seconds, to_seconds)
from behaviorlib.system.declare import Field, declare_parameters
from behaviorlib.v1 import errors_pb2, motion_pb2, platform_pb2, types_pb2

CircleAroundParameters = declare_parameters(
    "CircleAroundParameters", package="behaviorlib.examples.v1", behavior="CIRCLE_AROUND",
    kind="GOAL_BASED",
    doc="Flies circles around a point at the point's altitude, facing it: from where the "
        "vehicle is, straight to the nearest point of the circle, then around. Ends "
        "GOAL_ACHIEVED once the turns are flown and the vehicle is at their end; "
        "WRONG_PROGRESS when the vehicle stays too far from the reference; PROCESS_FAILURE "
        "when the pose estimate goes stale or no motion controller follows.",
    activate_doc="Activates CIRCLE_AROUND. INVALID_ARGUMENT for bad parameters (naming the "
                 "parameter), FAILED_PRECONDITION when already active or when the vehicle is not "
                 "flying or has no fresh pose estimate.",
    deactivate_doc="Ends the activation with cause INTERRUPTED; the vehicle holds where it is.",
    pause_doc="Pauses CIRCLE_AROUND: the vehicle holds where it is.",
    resume_doc="Resumes the circle from where the vehicle held.",
    fields=[
        Field("center_m", "Vector3", required=True,
              doc="The point to circle, in metres, world frame (ENU); z is the altitude flown, "
                  "at least 0.3 m."),
        Field("radius_m", "double", range=(0.3, 50), default=2.0,
              doc="Radius of the circle in metres."),
        Field("speed_m_s", "double", range=(0.1, 3), default=1.0,
              doc="Speed along the way in m/s."),
        Field("turns", "double", range=(0.1, 20), default=1.0,
              doc="Turns to fly (counter-clockwise)."),
    ])

# The robot's topics (the C++ flight behaviors' names).
POSE_TOPIC = "robots/{}/self_localization/pose"
FLIGHT_TOPIC = "robots/{}/flight_state"
STATUS_TOPIC = "robots/{}/motion_control/status"
REFERENCE_TOPIC = "robots/{}/motion_reference"

# An estimate older than this (behavior clock) is stale.
MAX_POSE_AGE_S = 1.0
# A controller must follow this activation's references within this time, and keep following.
CONTROLLER_GRACE_S = 2.0
CONTROLLER_TIMEOUT_S = 1.0
# The goal: at the end of the turns, within this distance.
GOAL_TOLERANCE_M = 0.3
# The reference's horizon (a controller makes up for the reference's age with it).
HORIZON_POINTS = 10
HORIZON_STEP_S = 0.1
MIN_ALTITUDE_M = 0.3


def _vector(v):
    return (v.x, v.y, v.z)


def _distance(a, b):
    return math.dist(a, b)


def _age_s(header, now_ns):
    return to_seconds(now_ns - (header.stamp.seconds * 1_000_000_000 + header.stamp.nanos))


class Plan:
    """The reference as a function of active time: a straight approach from the vehicle's
    position to the circle's nearest point, then the turns. Positions in metres, times in
    seconds."""

    def __init__(self, start, center, radius, speed, turns):
        self.center, self.radius, self.speed = center, radius, speed
        dx, dy = start[0] - center[0], start[1] - center[1]
        self.theta0 = math.atan2(dy, dx) if math.hypot(dx, dy) > 1e-6 else 0.0
        self.entry = (center[0] + radius * math.cos(self.theta0),
                      center[1] + radius * math.sin(self.theta0), center[2])
        self.start = start
        self.approach_s = _distance(start, self.entry) / speed
        self.omega = speed / radius
        self.circle_s = 2.0 * math.pi * turns / self.omega
        self.end_s = self.approach_s + self.circle_s
        self.end = self.at(self.end_s)[0]

    def at(self, t):
        """(position, velocity, acceleration) of the reference at active time t."""
        t = min(max(t, 0.0), self.end_s)
        if t < self.approach_s:
            f = t / self.approach_s
            velocity = tuple((e - s) / self.approach_s for s, e in zip(self.start, self.entry))
            position = tuple(s + (e - s) * f for s, e in zip(self.start, self.entry))
            return position, velocity, (0.0, 0.0, 0.0)
        theta = self.theta0 + self.omega * (t - self.approach_s)
        c, s = math.cos(theta), math.sin(theta)
        moving = 1.0 if t < self.end_s else 0.0
        position = (self.center[0] + self.radius * c, self.center[1] + self.radius * s,
                    self.center[2])
        velocity = (-self.speed * s * moving, self.speed * c * moving, 0.0)
        acceleration = (-self.speed * self.omega * c * moving,
                        -self.speed * self.omega * s * moving, 0.0)
        return position, velocity, acceleration

    def yaw_at(self, position):
        """Facing the centre."""
        return math.atan2(self.center[1] - position[1], self.center[0] - position[0])


class CircleAround(Behavior):
    Parameters = CircleAroundParameters

    def __init__(self, channel):
        """`channel`: the system's behaviorlib.system.channel.DataChannel."""
        super().__init__(options=BehaviorOptions(frequency_hz=20.0, watchdog_timeout=seconds(2)))
        self._channel = channel
        self._pose = self._flight = self._status = None
        self._plan = None

    # ---- Activation management ----

    def on_configure(self, config):
        robot = self.robot_id
        follow = [(POSE_TOPIC, types_pb2.PoseStamped, "_pose"),
                  (FLIGHT_TOPIC, platform_pb2.FlightStatus, "_flight"),
                  (STATUS_TOPIC, motion_pb2.MotionControlStatus, "_status")]
        for topic, message_type, attribute in follow:
            # Samples reach the worker between ticks: no lock on behavior state.
            deliver = self.on_worker(lambda m, a=attribute: setattr(self, a, m), Delivery.LATEST)
            self._channel.subscribe(topic.format(robot), message_type, deliver,
                                    latest_first=True)

    def on_activate(self):
        p = self.parameters
        if p.center_m.z < MIN_ALTITUDE_M:
            raise StatusError(grpc.StatusCode.INVALID_ARGUMENT,
                              f"parameter 'center_m.z' is out of range: {p.center_m.z} is below "
                              f"the minimum altitude {MIN_ALTITUDE_M} m",
                              reason=errors_pb2.PARAMETER_OUT_OF_RANGE,
                              field_violations=[("center_m.z", f"at least {MIN_ALTITUDE_M} m")])
        self._plan = Plan(_vector(self._pose.pose.position_m), _vector(p.center_m), p.radius_m,
                          p.speed_m_s, p.turns)
        self._began_ns = self.now()
        self._last_followed_ns = self._began_ns
        self._max_error_m = 0.0
        # The plan's time, twice over, and 10 s: a vehicle that needs more is not flying it.
        self.set_maximum_execution_time(
            seconds(2.0 * self._plan.end_s + 10.0),
            f"the circle should have taken {self._plan.end_s:.1f} s")

    def on_execute(self):
        t = to_seconds(self.active_time())
        reference = motion_pb2.MotionReference(
            source=self.activation_id, mode=motion_pb2.MOTION_REFERENCE_MODE_TRAJECTORY,
            horizon_step_s=HORIZON_STEP_S)
        self._stamp(reference)
        self._fill(reference.point, t)
        for i in range(HORIZON_POINTS):
            self._fill(reference.horizon.add(), t + (i + 1) * HORIZON_STEP_S)
        self._channel.publish(REFERENCE_TOPIC.format(self.robot_id), reference)

    def on_deactivate(self):
        self._hold()

    def on_pause(self):
        self._hold()

    # ---- Execution monitoring ----

    def check_situation(self):
        if self._pose is None:
            return Situation.infeasible(errors_pb2.SITUATION_REASON_INPUT_MISSING,
                                        "no pose estimate: activate a localization behavior such "
                                        "as SELF_LOCALIZE_WITH_GROUND_TRUTH")
        age = _age_s(self._pose.header, self.now())
        if age > MAX_POSE_AGE_S:
            return Situation.infeasible(errors_pb2.SITUATION_REASON_INPUT_STALE,
                                        f"the pose estimate is {age:.2f} s old")
        flying = (platform_pb2.FLIGHT_STATE_FLYING, platform_pb2.FLIGHT_STATE_HOVERING)
        if self._flight is None or self._flight.state not in flying:
            state = ("unknown" if self._flight is None
                     else platform_pb2.FlightState.Name(self._flight.state))
            return Situation.infeasible(errors_pb2.SITUATION_REASON_FLIGHT_STATE,
                                        f"CIRCLE_AROUND needs {self.robot_id} flying; it is {state}")
        return Situation.ok()

    def check_goal(self):
        t = to_seconds(self.active_time())
        position = _vector(self._pose.pose.position_m)
        if t < self._plan.end_s or _distance(position, self._plan.end) > GOAL_TOLERANCE_M:
            return Verdict.keep_going()
        p = self.parameters
        return Verdict.finish(f"flew {p.turns:g} turns of {p.radius_m:g} m around "
                              f"({p.center_m.x:g}, {p.center_m.y:g}, {p.center_m.z:g}) in "
                              f"{t:.1f} s; max distance from the reference "
                              f"{self._max_error_m:.2f} m")

    def check_progress(self):
        t = to_seconds(self.active_time())
        position = _vector(self._pose.pose.position_m)
        error = _distance(position, self._plan.at(t)[0])
        self._max_error_m = max(self._max_error_m, error)
        limit = max(1.0, 0.5 * self.parameters.radius_m)
        if error > limit:
            return Verdict.finish(f"the vehicle is {error:.2f} m from the reference (limit "
                                  f"{limit:.2f} m)")
        return Verdict.keep_going()

    def check_processes(self):
        now = self.now()
        age = _age_s(self._pose.header, now)
        if age > MAX_POSE_AGE_S:
            return Verdict.finish(f"the pose estimate is {age:.2f} s old")
        status = self._status
        if (status is not None and status.reference_source == self.activation_id and
                status.state == motion_pb2.MOTION_CONTROLLER_STATE_TRACKING):
            self._last_followed_ns = now
        if (to_seconds(now - self._began_ns) > CONTROLLER_GRACE_S and
                to_seconds(now - self._last_followed_ns) > CONTROLLER_TIMEOUT_S):
            return Verdict.finish("no motion controller follows CIRCLE_AROUND's references: "
                                  "activate QUADROTOR_PID_MOTION_CONTROL")
        return Verdict.keep_going()

    # ---- Helpers ----

    def _stamp(self, message):
        now = self.now()
        message.header.stamp.seconds, message.header.stamp.nanos = divmod(now, 1_000_000_000)
        message.header.frame_id = "world"
        message.header.robot_id = self.robot_id

    def _fill(self, point, t):
        position, velocity, acceleration = self._plan.at(t)
        point.position_m.x, point.position_m.y, point.position_m.z = position
        point.velocity_m_s.x, point.velocity_m_s.y, point.velocity_m_s.z = velocity
        point.acceleration_m_s2.x, point.acceleration_m_s2.y, point.acceleration_m_s2.z = \
            acceleration
        point.yaw_rad = self._plan.yaw_at(position)

    def _hold(self):
        """A position reference where the vehicle is, facing as the circle did."""
        if self._pose is None or self._plan is None:
            return
        reference = motion_pb2.MotionReference(source=self.activation_id,
                                               mode=motion_pb2.MOTION_REFERENCE_MODE_POSITION)
        self._stamp(reference)
        reference.point.position_m.CopyFrom(self._pose.pose.position_m)
        reference.point.yaw_rad = self._plan.yaw_at(_vector(self._pose.pose.position_m))
        self._channel.publish(REFERENCE_TOPIC.format(self.robot_id), reference)
