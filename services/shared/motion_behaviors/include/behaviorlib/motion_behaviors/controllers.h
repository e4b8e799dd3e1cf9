#pragma once

// The motion controllers of QUADROTOR_PID_MOTION_CONTROL,
// QUADROTOR_PID_THRUST_CONTROL and QUADROTOR_MPC_MOTION_CONTROL behind one
// interface that turns the estimate and a reference into a platform
// setpoint (services/motion_control holds the control laws):
//
//   auto controller = makePidAttitudeController(model, gains);
//   v1::SetpointRequest setpoint = controller->step(state, reference, 0.01, &diagnostics);
//
// Deterministic; not thread-safe.

#include <yaml-cpp/yaml.h>

#include <memory>
#include <string>

#include "absl/status/status.h"
#include "behaviorlib/config/v1/motion.pb.h"
#include "behaviorlib/motion_control/motion_types.h"
#include "behaviorlib/motion_control/mpc_controller.h"
#include "behaviorlib/motion_control/pid_controller.h"
#include "behaviorlib/v1/platform.pb.h"

namespace behaviorlib::motion_behaviors {

class ControllerAdapter {
 public:
  virtual ~ControllerAdapter() = default;
  /// One control step of `dt_s` seconds; the setpoint to send. Sets
  /// `thrust_ratio` to the commanded collective thrust.
  virtual v1::SetpointRequest step(const motion::StateEstimate& state,
                                   const motion::MotionReference& reference, double dt_s,
                                   motion::ControllerDiagnostics* diagnostics,
                                   double* thrust_ratio) = 0;
};

/// PID cascade -> attitude + thrust setpoints.
std::unique_ptr<ControllerAdapter> makePidAttitudeController(const motion::VehicleModel& model,
                                                             const motion::PidGains& gains);
/// PID cascade and an attitude loop -> thrust + body rates setpoints.
std::unique_ptr<ControllerAdapter> makePidThrustRatesController(const motion::VehicleModel& model,
                                                                const motion::PidGains& gains,
                                                                const Eigen::Vector3d& attitude_p,
                                                                double max_rate_rad_s);
/// MPC -> attitude + thrust setpoints.
std::unique_ptr<ControllerAdapter> makeMpcController(const motion::VehicleModel& model,
                                                     const motion::MpcParams& params);

/// The controllers' settings from a system's --config section (defaults in
/// brackets): mass_kg [1.5], max_thrust_n [48] (the airframe), and
///   PID: position_p_xy [1.2], position_p_z [1.5], velocity_p_xy [3],
///        velocity_p_z [4], velocity_i_xy [0.6], velocity_i_z [1.5],
///        attitude_p_xy [6], attitude_p_z [3], max_rate_rad_s [3]
///   MPC: horizon_steps [20], step_s [0.1], acceleration_lag_s [0.12],
///        position_weight [10], velocity_weight [2], input_weight [0.2],
///        input_rate_weight [0.5], max_iterations [200], disturbance_gain [0.03]
struct ControllerConfig {
  motion::VehicleModel model;
  motion::PidGains pid;
  Eigen::Vector3d attitude_p{6.0, 6.0, 3.0};
  double max_rate_rad_s = 3.0;
  motion::MpcParams mpc;

  /// Takes the decoded keys: the PID gains, or the MPC's parameters, and
  /// the airframe's (the mass is the flight keys' mass_kg).
  void configure(const config::v1::PidMotionControlConfig& config);
  void configure(const config::v1::MpcMotionControlConfig& config);
};

}  // namespace behaviorlib::motion_behaviors
