#include "behaviorlib/motion_control/wind_estimator.h"

#include <algorithm>
#include <cmath>

namespace behaviorlib::motion {

double WindEstimator::airSpeedForDrag(double drag_n, double c1, double c2) {
  const double force = std::abs(drag_n);
  double speed = 0.0;
  if (c2 > 1e-12) {
    speed = (-c1 + std::sqrt(c1 * c1 + 4.0 * c2 * force)) / (2.0 * c2);
  } else if (c1 > 1e-12) {
    speed = force / c1;
  }
  // Drag opposes the motion through the air.
  return drag_n > 0.0 ? -speed : speed;
}

void WindEstimator::reset() {
  have_ = false;
  steady_only_ = false;
  drag_m_s2_.setZero();
  velocity_m_s_.setZero();
  last_velocity_.setZero();
  orientation_ = Eigen::Quaterniond::Identity();
}

void WindEstimator::add(double t_s, const Eigen::Quaterniond& orientation,
                        const Eigen::Vector3d& velocity_m_s) {
  if (!std::isfinite(t_s) || !orientation.coeffs().allFinite() || !velocity_m_s.allFinite() ||
      orientation.norm() < 1e-6) {
    return;
  }
  const Eigen::Quaterniond q = orientation.normalized();
  const bool restart = !have_ || t_s - last_t_s_ > params_.max_gap_s;
  if (!restart && t_s <= last_t_s_) return;  // the same sample again, or an older one
  const double dt = restart ? 0.0 : t_s - last_t_s_;
  // Steady flight assumed when there is nothing to differentiate against.
  const Eigen::Vector3d acceleration =
      restart ? Eigen::Vector3d::Zero() : Eigen::Vector3d((velocity_m_s - last_velocity_) / dt);
  const Eigen::Matrix3d rotation = q.toRotationMatrix();  // world <- body
  Eigen::Vector3d specific_body =
      rotation.transpose() * (acceleration + Eigen::Vector3d(0.0, 0.0, params_.gravity_m_s2));
  specific_body.z() = 0.0;  // the thrust's axis: not drag
  const Eigen::Vector3d drag_world = rotation * specific_body;

  if (restart || steady_only_) {
    // The first sample (acceleration assumed zero) is replaced by the first
    // one with a measured acceleration.
    drag_m_s2_ = drag_world;
    velocity_m_s_ = velocity_m_s;
    steady_only_ = restart;
  } else {
    const double alpha = 1.0 - std::exp(-dt / std::max(params_.time_constant_s, 1e-6));
    drag_m_s2_ += alpha * (drag_world - drag_m_s2_);
    velocity_m_s_ += alpha * (velocity_m_s - velocity_m_s_);
  }
  orientation_ = q;
  last_t_s_ = t_s;
  last_velocity_ = velocity_m_s;
  have_ = true;
}

Eigen::Vector2d WindEstimator::windMS() const {
  if (!have_) return Eigen::Vector2d::Zero();
  const Eigen::Matrix3d rotation = orientation_.toRotationMatrix();
  const Eigen::Vector3d drag_body = rotation.transpose() * drag_m_s2_ * params_.mass_kg;
  Eigen::Vector3d air_body(
      airSpeedForDrag(drag_body.x(), params_.linear_drag_n_s_m, params_.quadratic_drag_n_s2_m2),
      airSpeedForDrag(drag_body.y(), params_.linear_drag_n_s_m, params_.quadratic_drag_n_s2_m2),
      0.0);
  // The body-z air speed is hidden in the thrust: take the wind horizontal,
  // (v - R u)_z = 0, which fixes u_z (the body is far from on its side).
  const double r_zz = rotation(2, 2);
  if (r_zz > 0.1) {
    air_body.z() =
        (velocity_m_s_.z() - rotation(2, 0) * air_body.x() - rotation(2, 1) * air_body.y()) / r_zz;
  } else {
    air_body.z() = (rotation.transpose() * velocity_m_s_).z();
  }
  const Eigen::Vector3d wind = velocity_m_s_ - rotation * air_body;
  return wind.head<2>();
}

double windPerformance(double speed_m_s, double calm_m_s, double max_m_s) {
  constexpr double kFloor = 0.2;
  if (!std::isfinite(speed_m_s) || speed_m_s <= calm_m_s) return 1.0;
  if (max_m_s <= calm_m_s || speed_m_s >= max_m_s) return kFloor;
  return 1.0 - (1.0 - kFloor) * (speed_m_s - calm_m_s) / (max_m_s - calm_m_s);
}

}  // namespace behaviorlib::motion
