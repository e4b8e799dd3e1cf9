#pragma once

// ROTATE_WITH_PID_CONTROL (quadrotor_motion_with_pid_control) and
// ROTATE_WITH_MPC_CONTROL (quadrotor_motion_with_mpc_control), goal-based:
// turns the vehicle in place. The behavior publishes a position reference at
// the position where it was activated whose yaw turns towards the target at
// yaw_rate_rad_s (the shorter way) on robots/{id}/motion_reference.
//
//   checkSituation  before: flight controller answers, FLYING/HOVERING, fresh
//                   pose estimate, battery; while active: still flying, battery
//   checkGoal       estimated yaw within tolerance_rad of the target for
//                   goal_dwell_s
//   checkProgress   the vehicle drifting beyond max_drift_m from where it
//                   turns; the yaw more than max_yaw_lag_rad behind the
//                   reference for a whole progress window: WRONG_PROGRESS
//   checkProcesses  stale estimate, flight controller gone, no motion
//                   controller following: PROCESS_FAILURE
//
// Config (besides the ReferenceSupport keys): max_drift_m [0.5],
// max_yaw_lag_rad [0.5].

#include <string>

#include "behaviorlib/behavior_execution_manager.h"
#include "behaviorlib/flight_common/flight_monitoring.h"
#include "behaviorlib/flight_common/vehicle.h"
#include "behaviorlib/motion_behaviors/motion_link.h"
#include "behaviorlib/motion_behaviors/reference_support.h"

namespace behaviorlib::motion_behaviors {

template <class Params>
class RotateBehavior final : public ReferenceBehavior<Params, config::v1::RotateConfig> {
 public:
  RotateBehavior(flight::Vehicle& vehicle, MotionLink& link);

 protected:
  absl::Status onConfigure(const config::v1::RotateConfig& config) override;
  absl::Status onActivate() override;
  void onExecute() override;
  void onResume() override;
  absl::Status onModify(const Params& new_parameters) override;

  Verdict checkGoal() override;
  Verdict checkProgress() override;

 private:
  using ReferenceBehavior<Params, config::v1::RotateConfig>::support;

  void setTarget(const Params& p);

  double max_drift_m_ = 0.5;
  double max_yaw_lag_rad_ = 0.5;
  flight::DwellTracker goal_{std::chrono::seconds(1)};
  flight::DwellTracker lagging_{std::chrono::seconds(3)};
  Eigen::Vector3d hold_m_ = Eigen::Vector3d::Zero();
  double start_yaw_rad_ = 0.0;
  double target_yaw_rad_ = 0.0;
  double reference_yaw_rad_ = 0.0;
  TimePoint last_update_{};
};

/// Moves `current` towards `target` by at most `step` radians the shorter
/// way; the result is wrapped to (-pi, pi].
double turnTowards(double current, double target, double step);

}  // namespace behaviorlib::motion_behaviors
