"""numpy views of the API's messages, where an array is the natural form.

    from behaviorlib import numpy_helpers as nph

    pose = drone.pose()
    p = nph.position(pose)        # array([x, y, z]) in metres, world frame
    psi = nph.yaw(pose)           # radians, about world z
    v = nph.velocity(drone.twist())

numpy is imported here only: the rest of the client does not need it.
"""

import math

import numpy as np


def _pose_of(message):
    # PoseStamped, or a Pose.
    return message.pose if hasattr(message, "header") else message


def vector(v):
    """A Vector3 as array([x, y, z])."""
    return np.array([v.x, v.y, v.z], dtype=float)


def position(pose):
    """The position of a PoseStamped (or Pose), metres: array([x, y, z])."""
    return vector(_pose_of(pose).position_m)


def quaternion(pose):
    """The orientation of a PoseStamped (or Pose): array([w, x, y, z])."""
    q = _pose_of(pose).orientation
    return np.array([q.w, q.x, q.y, q.z], dtype=float)


def yaw(pose):
    """The heading of a PoseStamped (or Pose) about the world's z axis,
    radians in (-pi, pi]."""
    w, x, y, z = quaternion(pose)
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def velocity(twist):
    """The linear velocity of a TwistStamped (or Twist), m/s."""
    t = twist.twist if hasattr(twist, "header") else twist
    return vector(t.linear_m_s)


def angular_velocity(twist):
    """The angular velocity of a TwistStamped (or Twist), rad/s."""
    t = twist.twist if hasattr(twist, "header") else twist
    return vector(t.angular_rad_s)


def stamp_s(message):
    """The header's stamp of a stamped message, seconds."""
    stamp = message.header.stamp
    return stamp.seconds + stamp.nanos * 1e-9
