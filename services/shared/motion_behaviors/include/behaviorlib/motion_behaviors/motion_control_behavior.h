#pragma once

// QUADROTOR_PID_MOTION_CONTROL, QUADROTOR_PID_THRUST_CONTROL
// (quadrotor_motion_with_pid_control) and QUADROTOR_MPC_MOTION_CONTROL
// (quadrotor_motion_with_mpc_control), recurrent: the active motion
// controller. Holding the vehicle's command lease, every tick (100 Hz of the
// behavior clock by default) it reads the pose estimate and the newest motion
// reference, runs its controller and streams the setpoint to the
// FlightController:
//
//   reference fresh (age <= reference_timeout_s)  follow it, advanced by its
//                                                 age along its horizon
//   otherwise                                     hold: the last reference
//                                                 point, the position where the
//                                                 vehicle was when a velocity
//                                                 reference ended, or where the
//                                                 controller became active
//
// The pose estimate is advanced by its age with its velocity (at most
// max_pose_extrapolation_s). Its status goes to robots/{id}/motion_control/status
// at status_frequency_hz and once more, STOPPED, when it ends.
//
//   checkSituation  before: flight controller answers, FLYING/HOVERING, fresh
//                   pose estimate, battery, the lease free (unless
//                   preempt_lease); while active: no emergency, still flying,
//                   battery (SITUATION_CHANGE)
//   checkGoal       none (recurrent)
//   checkProgress   distance to the reference point beyond max_tracking_error_m
//                   for a whole progress window: WRONG_PROGRESS
//   checkProcesses  stale pose/velocity estimate, flight controller gone, the
//                   lease lost or not renewed, a refused setpoint, an output
//                   that is not finite or stays saturated longer than
//                   saturation_timeout_s: PROCESS_FAILURE
//   onPause         the platform holds the current position (position setpoint)
//   onDeactivate    releases the lease: the platform hovers where the vehicle is
//
// Config (besides the CommanderSupport keys and ControllerConfig's controller
// keys): reference_timeout_s [0.5], status_frequency_hz [20],
// saturation_timeout_s [2], max_tracking_error_m [2],
// max_pose_extrapolation_s [0.1].

#include <functional>
#include <memory>
#include <optional>
#include <string>

#include "behaviorlib/behavior_execution_manager.h"
#include "behaviorlib/flight_common/flight_monitoring.h"
#include "behaviorlib/flight_common/flight_support.h"
#include "behaviorlib/flight_common/vehicle.h"
#include "behaviorlib/motion_behaviors/commander_support.h"
#include "behaviorlib/motion_behaviors/controllers.h"
#include "behaviorlib/motion_behaviors/motion_link.h"

namespace behaviorlib::motion_behaviors {

/// Makes the controller of one activation from the configuration and the
/// vehicle model with the activation's limits.
using ControllerFactory = std::function<std::unique_ptr<ControllerAdapter>(
    const ControllerConfig& config, const motion::VehicleModel& model)>;

/// Execution defaults of the motion controllers: 100 Hz, no time-out, a 2 s
/// watchdog.
BehaviorOptions controllerBehaviorOptions();

/// Config: config::v1::PidMotionControlConfig or MpcMotionControlConfig.
template <class Params, class Config>
class MotionControlBehavior final : public Behavior<Params, Config> {
 public:
  MotionControlBehavior(flight::Vehicle& vehicle, MotionLink& link, ControllerFactory factory);

 protected:
  absl::Status onConfigure(const Config& config) override;
  absl::Status onActivate() override;
  void onExecute() override;
  void onDeactivate() override;
  void onPause() override;
  void onResume() override;
  absl::Status onModify(const Params& new_parameters) override;

  Situation checkSituation() override;
  Verdict checkProgress() override;
  Verdict checkProcesses() override;

 private:
  // The reference to follow now, and whether it is a fresh one.
  motion::MotionReference currentReference(TimePoint now, bool* tracking);
  void publishStatus(TimePoint now, v1::MotionControllerState state);
  void makeController(const Params& p);

  MotionLink& link_;
  ControllerFactory factory_;
  CommanderSupport support_;
  ControllerConfig controller_config_;
  Duration reference_timeout_ = std::chrono::milliseconds(500);
  Duration status_period_ = std::chrono::milliseconds(50);
  Duration saturation_timeout_ = std::chrono::seconds(2);
  double max_tracking_error_m_ = 2.0;
  double max_pose_extrapolation_s_ = 0.1;

  // Activation state (worker thread only).
  std::unique_ptr<ControllerAdapter> controller_;
  motion::MotionReference hold_;
  bool was_tracking_ = false;
  bool hold_where_stopped_ = false;  // a velocity reference ended: hold where the vehicle is
  std::string reference_source_;
  v1::Header reference_header_;
  TimePoint last_step_{};
  TimePoint last_status_{};
  std::optional<TimePoint> saturated_since_;
  flight::DwellTracker off_track_{std::chrono::seconds(3)};
  double position_error_m_ = 0.0;
  double thrust_ratio_ = 0.0;
  bool saturated_ = false;
  uint64_t setpoints_ = 0;
  uint64_t status_seq_ = 0;
};

}  // namespace behaviorlib::motion_behaviors
