#pragma once

// KEEP_HOVERING_WITH_PID_CONTROL (quadrotor_motion_with_pid_control) and
// HOVER_WITH_MPC_CONTROL (quadrotor_motion_with_mpc_control), recurrent: hold
// the vehicle where it was activated by publishing that position and yaw as
// the reference on robots/{id}/motion_reference, until deactivated.
//
//   checkSituation  before: flight controller answers, FLYING/HOVERING, fresh
//                   pose estimate, battery; while active: still flying, battery
//   checkGoal       none (recurrent)
//   checkProgress   drift beyond max_drift_m from the hover point: WRONG_PROGRESS
//   checkProcesses  stale estimate, flight controller gone, no motion
//                   controller following: PROCESS_FAILURE

#include <string>

#include "behaviorlib/behavior_execution_manager.h"
#include "behaviorlib/flight_common/vehicle.h"
#include "behaviorlib/motion_behaviors/motion_link.h"
#include "behaviorlib/motion_behaviors/reference_support.h"

namespace behaviorlib::motion_behaviors {

template <class Params>
class HoverBehavior final : public ReferenceBehavior<Params, config::v1::MotionConfig> {
 public:
  HoverBehavior(flight::Vehicle& vehicle, MotionLink& link);

 protected:
  absl::Status onConfigure(const config::v1::MotionConfig& config) override;
  absl::Status onActivate() override;
  void onExecute() override;

  Verdict checkProgress() override;

 private:
  using ReferenceBehavior<Params, config::v1::MotionConfig>::support;

  Eigen::Vector3d hold_m_ = Eigen::Vector3d::Zero();
  double yaw_rad_ = 0.0;
};

}  // namespace behaviorlib::motion_behaviors
