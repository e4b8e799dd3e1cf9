#pragma once

// PathTracker: FOLLOW_PATH's reference generator. It turns a path (points in
// the world frame) into a time-parameterised trajectory that stops at every
// waypoint (trapezoidal speed profile per segment: accelerate, cruise,
// decelerate) and hands the motion controller, at every step, the reference
// point now plus a horizon of future points (for the MPC), with velocity and
// acceleration feed-forward. A path changed in flight continues from the
// reference of the old one (continueFrom): no jump, no stop.
//
// The reference waits for the vehicle: its time advances at full rate only
// while the vehicle is within `max_lag_m / 2` of the reference point, and
// stops at `max_lag_m`; so wind slows the path down instead of letting the
// reference run away, and "no progress" is visible as a reference that does
// not move.
//
//   auto tracker = PathTracker::create({{0,0,1}, {4,0,1}, {4,4,1}}, params).value();
//   tracker.start(current_position, current_yaw);
//   MotionReference ref = tracker.update(current_position, 0.01);

#include <Eigen/Core>
#include <vector>

#include "absl/status/statusor.h"
#include "behaviorlib/motion_control/motion_types.h"

namespace behaviorlib::motion {

struct PathTrackerParams {
  double speed_m_s = 1.0;
  double acceleration_m_s2 = 1.0;
  double max_lag_m = 0.6;
  /// Horizon handed to the controller (MPC), in points and spacing.
  int horizon_steps = 20;
  double horizon_step_s = 0.1;
  /// Longest path accepted (m).
  double max_length_m = 1000.0;
};

class PathTracker {
 public:
  /// INVALID_ARGUMENT (naming the point) for an empty path, a non-finite
  /// coordinate, a speed or acceleration out of range, or a path longer than
  /// max_length_m.
  static absl::StatusOr<PathTracker> create(std::vector<Eigen::Vector3d> waypoints,
                                            PathTrackerParams params);

  /// Starts from the vehicle's position (the first segment leads from it to
  /// the first waypoint) holding `yaw_rad`.
  void start(const Eigen::Vector3d& position_m, double yaw_rad);
  /// Starts from a reference of another path (the one followed until now,
  /// current()), so that a path changed in flight is taken up without a jump
  /// and without stopping: the first segment leads from its position, entered
  /// at the part of its velocity along that segment (the part across it is
  /// dropped: a turn is not flown at speed), holding `yaw_rad`. The segment
  /// then brakes at the acceleration, or harder when it is too short to stop
  /// in from that speed.
  void continueFrom(const ReferencePoint& from, double yaw_rad);
  /// The reference now (at timeS()).
  ReferencePoint current() const { return sample(time_s_); }
  /// Advances by `dt_s` (less when the vehicle lags) and returns the reference.
  MotionReference update(const Eigen::Vector3d& position_m, double dt_s);

  /// Distance from `position_m` to the path polyline (m).
  double crossTrackErrorM(const Eigen::Vector3d& position_m) const;
  /// Distance from `position_m` to the current reference point (m).
  double lagM(const Eigen::Vector3d& position_m) const;
  /// True once the reference reached the last waypoint.
  bool referenceAtEnd() const { return time_s_ >= total_time_s_; }
  /// Path length still ahead of the reference (m).
  double remainingM() const;
  double lengthM() const { return length_m_; }
  /// Reference time (s) and the time the whole path takes at full speed.
  double timeS() const { return time_s_; }
  double totalTimeS() const { return total_time_s_; }
  const std::vector<Eigen::Vector3d>& points() const { return points_; }
  /// The reference at path time `t_s`.
  ReferencePoint sample(double t_s) const;

 private:
  // A segment's speed profile: from entry_speed to peak_speed at
  // first_accel (negative when it slows), cruise, then down to rest at
  // braking.
  struct Segment {
    Eigen::Vector3d start, direction;
    double length, start_time, duration;
    double entry_speed = 0.0, peak_speed, first_accel, first_time, braking, braking_time;
  };
  PathTracker(std::vector<Eigen::Vector3d> waypoints, PathTrackerParams params);
  void startAt(const Eigen::Vector3d& position_m, double yaw_rad, const Eigen::Vector3d& velocity);
  void plan(double entry_speed);

  std::vector<Eigen::Vector3d> waypoints_;
  PathTrackerParams params_;
  std::vector<Eigen::Vector3d> points_;  // start position + waypoints
  std::vector<Segment> segments_;
  double length_m_ = 0.0;
  double total_time_s_ = 0.0;
  double time_s_ = 0.0;
  double yaw_rad_ = 0.0;
};

}  // namespace behaviorlib::motion
