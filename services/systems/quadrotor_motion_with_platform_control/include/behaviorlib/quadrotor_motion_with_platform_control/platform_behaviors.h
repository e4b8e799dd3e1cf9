#pragma once

// The behaviors of quadrotor_motion_with_platform_control: motion through the
// platform's own control levels, holding the vehicle's command lease while
// active (PlatformSupport). When one ends, its lease is released and the
// platform hovers where the vehicle is.
//
// MOVE_VERTICAL_WITH_PLATFORM_CONTROL (goal-based): position + yaw setpoints
// at the horizontal position and yaw of activation, the altitude moving
// towards the target at speed_m_s.
//   checkGoal       altitude within tolerance_m, vertical speed below
//                   max_vertical_speed_m_s [0.1], for goal_dwell_s
//   checkProgress   less than min_progress_m towards the target over a
//                   progress window; horizontal drift beyond max_drift_m
//
// MOVE_AT_SPEED_WITH_PLATFORM_CONTROL (goal-based with duration_s, else until
// deactivated): velocity + yaw rate setpoints.
//   checkGoal       duration_s of active time (when > 0)
//   checkProgress   the velocity more than max_speed_error_m_s [0.5] from the
//                   request for a whole window after the first; a descent
//                   below min_altitude_m
//
// ROTATE_WITH_PLATFORM_CONTROL (goal-based): position + yaw setpoints at the
// position of activation, the yaw turning towards the target at
// yaw_rate_rad_s.
//   checkGoal       yaw within tolerance_rad for goal_dwell_s
//   checkProgress   drift beyond max_drift_m; the yaw more than
//                   max_yaw_lag_rad [0.5] behind the setpoint for a window
//
// All: checkSituation (before: flying, fresh estimate, battery, lease free;
// active: still flying, battery) and checkProcesses (stale estimate,
// unreachable flight controller, lease lost, a refused setpoint) from
// motion_behaviors::CommanderSupport.
//
// Config of each behavior's section (defaults in brackets): the
// CommanderSupport keys (pose_timeout_s, lease_ttl_s, preempt_lease,
// min_battery_ratio, full_battery_ratio, progress_window_s), goal_dwell_s [1],
// min_altitude_m [0.2], max_drift_m [0.5], min_progress_m [0.1], and the
// behavior's own keys named above.

#include "behaviorlib/behavior_execution_manager.h"
#include "behaviorlib/config/v1/quadrotor_motion_with_platform_control.pb.h"
#include "behaviorlib/flight_common/flight_monitoring.h"
#include "behaviorlib/flight_common/vehicle.h"
#include "behaviorlib/motion_behaviors/commander_support.h"
#include "behaviorlib/v1/behaviors/quadrotor_motion_with_platform_control.pb.h"

namespace behaviorlib::platform_motion {

/// The platform-control behaviors' own config keys.
struct PlatformMotionSettings {
  Duration goal_dwell = std::chrono::seconds(1);
  double min_altitude_m = 0.2;
  double max_drift_m = 0.5;
  double min_progress_m = 0.1;

  void configure(const config::v1::PlatformMotionConfig& config);
};

class MoveVerticalBehavior final
    : public Behavior<v1::MoveVerticalWithPlatformControlParameters,
                      config::v1::MoveVerticalWithPlatformControlConfig> {
 public:
  explicit MoveVerticalBehavior(flight::Vehicle& vehicle);

 protected:
  absl::Status onConfigure(
      const config::v1::MoveVerticalWithPlatformControlConfig& config) override;
  absl::Status onActivate() override;
  void onExecute() override;
  void onDeactivate() override;
  void onPause() override;
  void onResume() override;
  absl::Status onModify(
      const v1::MoveVerticalWithPlatformControlParameters& new_parameters) override;

  Situation checkSituation() override;
  Verdict checkGoal() override;
  Verdict checkProgress() override;
  Verdict checkProcesses() override;

 private:
  absl::StatusOr<double> targetOf(const v1::MoveVerticalWithPlatformControlParameters& p) const;
  void restart();

  motion_behaviors::CommanderSupport support_;
  PlatformMotionSettings settings_;
  double max_vertical_speed_m_s_ = 0.1;
  flight::DwellTracker goal_{std::chrono::seconds(1)};
  flight::ProgressWindow progress_{std::chrono::seconds(3)};
  Eigen::Vector3d hold_m_ = Eigen::Vector3d::Zero();
  double start_z_m_ = 0.0;
  double yaw_rad_ = 0.0;
  double target_z_m_ = 0.0;
  double reference_z_m_ = 0.0;
  TimePoint last_update_{};
};

class MoveAtSpeedBehavior final
    : public Behavior<v1::MoveAtSpeedWithPlatformControlParameters,
                      config::v1::MoveAtSpeedWithPlatformControlConfig> {
 public:
  explicit MoveAtSpeedBehavior(flight::Vehicle& vehicle);

 protected:
  absl::Status onConfigure(const config::v1::MoveAtSpeedWithPlatformControlConfig& config) override;
  absl::Status onActivate() override;
  void onExecute() override;
  void onDeactivate() override;
  void onPause() override;
  void onResume() override;
  absl::Status onModify(
      const v1::MoveAtSpeedWithPlatformControlParameters& new_parameters) override;

  Situation checkSituation() override;
  Verdict checkGoal() override;
  Verdict checkProgress() override;
  Verdict checkProcesses() override;

 private:
  Eigen::Vector3d requested() const;

  motion_behaviors::CommanderSupport support_;
  PlatformMotionSettings settings_;
  double max_speed_error_m_s_ = 0.5;
  flight::DwellTracker off_speed_{std::chrono::seconds(3)};
  TimePoint changed_at_{};
};

class RotateWithPlatformControlBehavior final
    : public Behavior<v1::RotateWithPlatformControlParameters,
                      config::v1::RotateWithPlatformControlConfig> {
 public:
  explicit RotateWithPlatformControlBehavior(flight::Vehicle& vehicle);

 protected:
  absl::Status onConfigure(const config::v1::RotateWithPlatformControlConfig& config) override;
  absl::Status onActivate() override;
  void onExecute() override;
  void onDeactivate() override;
  void onPause() override;
  void onResume() override;
  absl::Status onModify(const v1::RotateWithPlatformControlParameters& new_parameters) override;

  Situation checkSituation() override;
  Verdict checkGoal() override;
  Verdict checkProgress() override;
  Verdict checkProcesses() override;

 private:
  void setTarget(const v1::RotateWithPlatformControlParameters& p);

  motion_behaviors::CommanderSupport support_;
  PlatformMotionSettings settings_;
  double max_yaw_lag_rad_ = 0.5;
  flight::DwellTracker goal_{std::chrono::seconds(1)};
  flight::DwellTracker lagging_{std::chrono::seconds(3)};
  Eigen::Vector3d hold_m_ = Eigen::Vector3d::Zero();
  double start_yaw_rad_ = 0.0;
  double target_yaw_rad_ = 0.0;
  double reference_yaw_rad_ = 0.0;
  TimePoint last_update_{};
};

}  // namespace behaviorlib::platform_motion
