#pragma once

// KEEP_MOVING_WITH_PID_CONTROL (recurrent): keeps the vehicle moving at a
// constant velocity (world frame) and yaw rate by publishing a velocity
// reference on robots/{id}/motion_reference, until deactivated.
//
//   checkSituation  before: flight controller answers, FLYING/HOVERING, fresh
//                   pose estimate, battery; while active: still flying, battery
//   checkGoal       none (recurrent)
//   checkProgress   the estimated velocity more than max_speed_error_m_s from
//                   the request for a whole progress window (after the first
//                   window, while it accelerates); a descent below
//                   min_altitude_m: WRONG_PROGRESS
//   checkProcesses  stale estimate, flight controller gone, no motion
//                   controller following: PROCESS_FAILURE
//
// Config: the ReferenceSupport keys.

#include <string>

#include "behaviorlib/behavior_execution_manager.h"
#include "behaviorlib/flight_common/flight_monitoring.h"
#include "behaviorlib/flight_common/vehicle.h"
#include "behaviorlib/motion_behaviors/motion_link.h"
#include "behaviorlib/motion_behaviors/reference_support.h"
#include "behaviorlib/v1/behaviors/quadrotor_motion_with_pid_control.pb.h"

namespace behaviorlib::motion_behaviors {

class KeepMovingWithPidControlBehavior final
    : public ReferenceBehavior<v1::KeepMovingWithPidControlParameters, config::v1::MotionConfig> {
 public:
  KeepMovingWithPidControlBehavior(flight::Vehicle& vehicle, MotionLink& link);

 protected:
  absl::Status onConfigure(const config::v1::MotionConfig& config) override;
  absl::Status onActivate() override;
  void onExecute() override;
  void onResume() override;
  absl::Status onModify(const v1::KeepMovingWithPidControlParameters& new_parameters) override;

  Verdict checkProgress() override;

 private:
  Eigen::Vector3d requested() const;

  flight::DwellTracker off_speed_{std::chrono::seconds(3)};
  TimePoint changed_at_{};
};

}  // namespace behaviorlib::motion_behaviors
