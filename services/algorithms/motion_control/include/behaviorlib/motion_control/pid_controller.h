#pragma once

// PidMotionController: the cascade of QUADROTOR_PID_MOTION_CONTROL.
//
//   position ──P + I──▶ velocity (+ feed-forward, limited) ──P + I + D──▶
//   acceleration (+ feed-forward) ──▶ attitude + collective thrust
//
// The platform's autopilot runs the attitude and rate loops below it at its
// physics rate. The integrators do not wind up while the output is
// saturated (conditional integration). Deterministic; not thread-safe.
//
//   PidMotionController pid(model, PidGains{});
//   AttitudeThrustCommand cmd = pid.update(estimate, reference, 0.01, &diag);

#include "behaviorlib/motion_control/motion_types.h"

namespace behaviorlib::motion {

struct PidGains {
  /// Position loop, per world axis (1/s, 1/s^2).
  Eigen::Vector3d position_p{1.2, 1.2, 1.5};
  Eigen::Vector3d position_i{0.05, 0.05, 0.1};
  /// Velocity loop, per world axis (1/s, 1/s^2, dimensionless).
  Eigen::Vector3d velocity_p{3.0, 3.0, 4.0};
  Eigen::Vector3d velocity_i{0.6, 0.6, 1.5};
  Eigen::Vector3d velocity_d{0.05, 0.05, 0.0};
  /// Bounds of the integral terms (m/s for position, m/s^2 for velocity).
  double position_integral_limit_m_s = 0.5;
  double velocity_integral_limit_m_s2 = 3.0;
  /// Yaw: yaw rate = P * error is left to the autopilot's attitude loop; the
  /// controller only passes the reference yaw (or integrates a yaw rate).
};

class PidMotionController {
 public:
  PidMotionController(VehicleModel model, PidGains gains);

  /// One control step of `dt_s` seconds.
  AttitudeThrustCommand update(const StateEstimate& state, const MotionReference& reference,
                               double dt_s, ControllerDiagnostics* diagnostics = nullptr);
  /// Forgets integrators and the yaw being integrated (on activation).
  void reset();

  const VehicleModel& model() const { return model_; }
  PidGains& gains() { return gains_; }

 private:
  VehicleModel model_;
  PidGains gains_;
  Eigen::Vector3d position_integral_ = Eigen::Vector3d::Zero();
  Eigen::Vector3d velocity_integral_ = Eigen::Vector3d::Zero();
  Eigen::Vector3d last_velocity_error_ = Eigen::Vector3d::Zero();
  bool have_last_ = false;
  bool saturated_ = false;
  double yaw_hold_rad_ = 0.0;
  bool yaw_hold_set_ = false;
};

/// For QUADROTOR_PID_THRUST_CONTROL: the attitude loop on the controller's
/// side, turning an attitude command into body rates (thrust + body rates is
/// the platform's innermost level): rates = P * attitude error (rad/s).
Eigen::Vector3d attitudeToBodyRates(const Eigen::Quaterniond& current,
                                    const Eigen::Quaterniond& desired,
                                    const Eigen::Vector3d& p = Eigen::Vector3d(6.0, 6.0, 3.0),
                                    double max_rate_rad_s = 3.0);

}  // namespace behaviorlib::motion
