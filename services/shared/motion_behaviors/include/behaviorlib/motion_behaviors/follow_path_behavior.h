#pragma once

// FOLLOW_PATH (quadrotor_motion_with_pid_control) and
// FOLLOW_PATH_WITH_MPC_CONTROL (quadrotor_motion_with_mpc_control), goal-based:
// a PathTracker turns the path into a trajectory reference (trapezoidal speed
// per segment, stopping at each waypoint; position, velocity and acceleration
// feed-forward; a horizon for the MPC) that waits for a lagging vehicle, and
// the behavior publishes it on robots/{id}/motion_reference at its frequency.
// The two differ only in their parameter message (same fields).
//
//   checkSituation  before: flight controller answers, FLYING/HOVERING, fresh
//                   pose estimate, battery; while active: still flying, battery
//   checkGoal       the reference at the last waypoint and the estimate within
//                   tolerance_m of it for goal_dwell_s
//   checkProgress   cross-track error beyond max_cross_track_m; the vehicle
//                   lagging the reference by at least 0.8 max_lag_m for a whole
//                   progress window; the reference advancing less than
//                   min_progress_m along the path over a window: WRONG_PROGRESS
//   checkProcesses  stale pose/velocity estimate, flight controller gone, no
//                   motion controller following: PROCESS_FAILURE
//
// Path checks in onActivate (INVALID_ARGUMENT naming path_m, before anything
// is published): a point below min_altitude_m, more than max_path_points
// points, longer than max_path_length_m; empty paths and NaN are refused by
// the parameter layer.
//
// Config (besides the ReferenceSupport keys): max_path_length_m [1000],
// max_path_points [1000], max_lag_m [0.6], max_cross_track_m [1.0],
// min_progress_m [0.1], horizon_steps [20], horizon_step_s [0.1].
// With maximum_execution_time_s 0 the time-out is 3 times the path's
// nominal duration plus 10 s.

#include <memory>
#include <optional>
#include <string>

#include "behaviorlib/behavior_execution_manager.h"
#include "behaviorlib/flight_common/flight_monitoring.h"
#include "behaviorlib/flight_common/vehicle.h"
#include "behaviorlib/motion_behaviors/motion_link.h"
#include "behaviorlib/motion_behaviors/reference_support.h"
#include "behaviorlib/motion_control/path_tracker.h"

namespace behaviorlib::motion_behaviors {

/// Path limits and tracker settings of the FOLLOW_PATH behaviors' config.
struct PathSettings {
  double max_path_length_m = 1000.0;
  int max_path_points = 1000;
  double max_lag_m = 0.6;
  double max_cross_track_m = 1.0;
  double min_progress_m = 0.1;
  int horizon_steps = 20;
  double horizon_step_s = 0.1;

  /// Takes the decoded keys.
  void configure(const config::v1::PathConfig& config);
};

/// Validates a path (INVALID_ARGUMENT naming path_m and the point) and makes
/// its tracker: finite points, at least min_altitude_m high, at most
/// max_path_points, at most max_path_length_m long (from the first point).
absl::StatusOr<motion::PathTracker> makePathTracker(
    const google::protobuf::RepeatedPtrField<v1::Vector3>& path, double speed_m_s,
    double acceleration_m_s2, const PathSettings& settings, double min_altitude_m);

template <class Params>
class FollowPathBehavior final : public ReferenceBehavior<Params, config::v1::FollowPathConfig> {
 public:
  FollowPathBehavior(flight::Vehicle& vehicle, MotionLink& link);

 protected:
  absl::Status onConfigure(const config::v1::FollowPathConfig& config) override;
  absl::Status onActivate() override;
  void onExecute() override;
  void onDeactivate() override;
  void onResume() override;
  absl::Status onModify(const Params& new_parameters) override;

  Verdict checkGoal() override;
  Verdict checkProgress() override;

 private:
  using ReferenceBehavior<Params, config::v1::FollowPathConfig>::support;

  void restartWindows();

  PathSettings path_settings_;
  std::optional<motion::PathTracker> tracker_;
  flight::DwellTracker goal_{std::chrono::seconds(1)};
  flight::DwellTracker lagging_{std::chrono::seconds(3)};
  flight::ProgressWindow progress_{std::chrono::seconds(3)};
  TimePoint last_update_{};
  double tolerance_m_ = 0.1;
  // Cross-track statistics of the activation (for the goal's message).
  double cross_track_sum_sq_ = 0.0;
  double cross_track_max_ = 0.0;
  uint64_t cross_track_samples_ = 0;
};

}  // namespace behaviorlib::motion_behaviors
