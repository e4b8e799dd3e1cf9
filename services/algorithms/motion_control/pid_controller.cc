#include "behaviorlib/motion_control/pid_controller.h"

#include <algorithm>
#include <cmath>

namespace behaviorlib::motion {
namespace {

bool finite(const Eigen::Vector3d& v) { return v.allFinite(); }

Eigen::Vector3d clampNorm(const Eigen::Vector3d& v, double limit) {
  const double n = v.norm();
  return n > limit ? Eigen::Vector3d(v * (limit / n)) : v;
}

}  // namespace

PidMotionController::PidMotionController(VehicleModel model, PidGains gains)
    : model_(model), gains_(gains) {}

void PidMotionController::reset() {
  position_integral_.setZero();
  velocity_integral_.setZero();
  last_velocity_error_.setZero();
  have_last_ = false;
  saturated_ = false;
  yaw_hold_set_ = false;
}

AttitudeThrustCommand PidMotionController::update(const StateEstimate& state,
                                                  const MotionReference& reference, double dt_s,
                                                  ControllerDiagnostics* diagnostics) {
  ControllerDiagnostics diag;
  const ReferencePoint& ref = reference.point;
  if (!finite(state.position_m) || !finite(state.velocity_m_s) || !finite(ref.position_m) ||
      !finite(ref.velocity_m_s) || !std::isfinite(ref.yaw_rad) || !(dt_s > 0.0)) {
    diag.finite = false;
    if (diagnostics) *diagnostics = diag;
    // Level hover thrust: the safest command without a usable input.
    AttitudeThrustCommand hover;
    hover.orientation = Eigen::AngleAxisd(state.yawRad(), Eigen::Vector3d::UnitZ());
    hover.thrust_ratio = model_.hoverThrustRatio();
    return hover;
  }

  // Position loop (skipped in velocity mode).
  Eigen::Vector3d velocity_command = ref.velocity_m_s;
  double yaw = ref.yaw_rad;
  if (reference.mode == MotionReference::Mode::kVelocity) {
    if (!yaw_hold_set_) {
      yaw_hold_rad_ = state.yawRad();
      yaw_hold_set_ = true;
    }
    yaw_hold_rad_ = wrapAngle(yaw_hold_rad_ + reference.yaw_rate_rad_s * dt_s);
    yaw = yaw_hold_rad_;
    position_integral_.setZero();
  } else {
    yaw_hold_set_ = false;
    const Eigen::Vector3d error = ref.position_m - state.position_m;
    if (!saturated_) {
      position_integral_ += gains_.position_i.cwiseProduct(error) * dt_s;
      position_integral_ = clampNorm(position_integral_, gains_.position_integral_limit_m_s);
    }
    velocity_command += gains_.position_p.cwiseProduct(error) + position_integral_;
  }
  // Speed limits.
  Eigen::Vector2d horizontal = velocity_command.head<2>();
  if (horizontal.norm() > model_.max_horizontal_speed_m_s) {
    velocity_command.head<2>() = horizontal * (model_.max_horizontal_speed_m_s / horizontal.norm());
  }
  velocity_command.z() = std::clamp(velocity_command.z(), -model_.max_vertical_speed_m_s,
                                    model_.max_vertical_speed_m_s);

  // Velocity loop.
  const Eigen::Vector3d velocity_error = velocity_command - state.velocity_m_s;
  if (!saturated_) {
    velocity_integral_ += gains_.velocity_i.cwiseProduct(velocity_error) * dt_s;
    velocity_integral_ = clampNorm(velocity_integral_, gains_.velocity_integral_limit_m_s2);
  }
  Eigen::Vector3d derivative = Eigen::Vector3d::Zero();
  if (have_last_) derivative = (velocity_error - last_velocity_error_) / dt_s;
  last_velocity_error_ = velocity_error;
  have_last_ = true;
  const Eigen::Vector3d acceleration =
      ref.acceleration_m_s2 + gains_.velocity_p.cwiseProduct(velocity_error) + velocity_integral_ +
      gains_.velocity_d.cwiseProduct(derivative);

  bool saturated = false;
  AttitudeThrustCommand command = accelerationToAttitude(acceleration, yaw, model_, &saturated);
  saturated_ = saturated;
  diag.saturated = saturated;
  diag.acceleration_command_m_s2 = acceleration;
  diag.finite = acceleration.allFinite() && std::isfinite(command.thrust_ratio);
  if (diagnostics) *diagnostics = diag;
  return command;
}

Eigen::Vector3d attitudeToBodyRates(const Eigen::Quaterniond& current,
                                    const Eigen::Quaterniond& desired, const Eigen::Vector3d& p,
                                    double max_rate_rad_s) {
  // Error rotation in the body frame, shortest way.
  Eigen::Quaterniond error = current.conjugate() * desired;
  if (error.w() < 0.0) error.coeffs() = -error.coeffs();
  const Eigen::Vector3d axis_angle = 2.0 * error.vec();  // small-angle rotation vector
  Eigen::Vector3d rates = p.cwiseProduct(axis_angle);
  for (int i = 0; i < 3; ++i) rates[i] = std::clamp(rates[i], -max_rate_rad_s, max_rate_rad_s);
  return rates;
}

}  // namespace behaviorlib::motion
