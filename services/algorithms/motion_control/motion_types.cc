#include "behaviorlib/motion_control/motion_types.h"

#include <algorithm>
#include <cmath>
#include <numbers>

namespace behaviorlib::motion {

double StateEstimate::yawRad() const {
  const Eigen::Vector3d forward = orientation * Eigen::Vector3d::UnitX();
  return std::atan2(forward.y(), forward.x());
}

double wrapAngle(double rad) {
  rad = std::fmod(rad + std::numbers::pi, 2.0 * std::numbers::pi);
  if (rad <= 0.0) rad += 2.0 * std::numbers::pi;
  return rad - std::numbers::pi;
}

AttitudeThrustCommand accelerationToAttitude(const Eigen::Vector3d& acceleration_m_s2,
                                             double yaw_rad, const VehicleModel& model,
                                             bool* saturated) {
  bool limited = false;
  Eigen::Vector3d thrust =
      model.mass_kg * (acceleration_m_s2 + Eigen::Vector3d(0, 0, model.gravity_m_s2));
  // Never ask for downward thrust; keep some upward component.
  const double min_up = model.min_thrust_ratio * model.max_thrust_n;
  if (thrust.z() < min_up) {
    thrust.z() = min_up;
    limited = true;
  }
  const double horizontal = thrust.head<2>().norm();
  const double max_horizontal = thrust.z() * std::tan(model.max_tilt_rad);
  if (horizontal > max_horizontal) {
    thrust.head<2>() *= max_horizontal / horizontal;
    limited = true;
  }
  double ratio = thrust.norm() / model.max_thrust_n;
  if (ratio > model.max_thrust_ratio) {
    ratio = model.max_thrust_ratio;
    limited = true;
  }
  ratio = std::max(ratio, model.min_thrust_ratio);

  const Eigen::Vector3d z_body = thrust.normalized();
  const Eigen::Vector3d x_course(std::cos(yaw_rad), std::sin(yaw_rad), 0.0);
  Eigen::Vector3d y_body = z_body.cross(x_course);
  if (y_body.norm() < 1e-6) y_body = Eigen::Vector3d::UnitY();
  y_body.normalize();
  const Eigen::Vector3d x_body = y_body.cross(z_body);
  Eigen::Matrix3d rotation;
  rotation.col(0) = x_body;
  rotation.col(1) = y_body;
  rotation.col(2) = z_body;
  AttitudeThrustCommand command;
  command.orientation = Eigen::Quaterniond(rotation).normalized();
  command.thrust_ratio = ratio;
  if (saturated) *saturated = limited;
  return command;
}

}  // namespace behaviorlib::motion
