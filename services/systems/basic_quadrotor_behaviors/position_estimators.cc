#include "behaviorlib/basic_quadrotor_behaviors/position_estimators.h"

#include <limits>

namespace behaviorlib::basic {

void AxisFilter::reset(double position_m, double position_stddev_m,
                       const SensorFilterNoise& noise) {
  x_ = Vector4(position_m, 0.0, 0.0, 0.0);
  P_ = Vector4(position_stddev_m * position_stddev_m,
               noise.initial_velocity_stddev_m_s * noise.initial_velocity_stddev_m_s,
               noise.initial_accel_bias_stddev_m_s2 * noise.initial_accel_bias_stddev_m_s2,
               noise.initial_baro_offset_stddev_m * noise.initial_baro_offset_stddev_m)
           .asDiagonal();
}

void AxisFilter::predict(double accel_m_s2, double dt, const SensorFilterNoise& noise) {
  const double dt2 = dt * dt;
  Matrix4 F = Matrix4::Identity();
  F(0, 1) = dt;
  F(0, 2) = -0.5 * dt2;
  F(1, 2) = -dt;
  x_ = F * x_;
  x_(0) += 0.5 * dt2 * accel_m_s2;
  x_(1) += dt * accel_m_s2;
  // White acceleration noise integrated over the step, plus the random walks.
  const double q = noise.accel_noise_m_s2 * noise.accel_noise_m_s2;
  Matrix4 Q = Matrix4::Zero();
  Q(0, 0) = q * dt2 * dt / 3.0;
  Q(0, 1) = Q(1, 0) = q * dt2 / 2.0;
  Q(1, 1) = q * dt;
  Q(2, 2) = noise.accel_bias_walk_m_s2 * noise.accel_bias_walk_m_s2 * dt;
  Q(3, 3) = noise.baro_drift_m * noise.baro_drift_m * dt;
  P_ = F * P_ * F.transpose() + Q;
}

double AxisFilter::innovation(double z, bool with_offset) const {
  return z - (x_(0) + (with_offset ? x_(3) : 0.0));
}

double AxisFilter::innovationStddev(double stddev, bool with_offset) const {
  const Vector4 H(1.0, 0.0, 0.0, with_offset ? 1.0 : 0.0);
  return std::sqrt(std::max(H.dot(P_ * H) + stddev * stddev, 0.0));
}

void AxisFilter::update(double z, double stddev, bool with_offset) {
  const Vector4 H(1.0, 0.0, 0.0, with_offset ? 1.0 : 0.0);
  const Vector4 PH = P_ * H;
  const double S = H.dot(PH) + stddev * stddev;
  if (!(S > 0.0)) return;
  const Vector4 K = PH / S;
  x_ += K * innovation(z, with_offset);
  // Joseph form: stays symmetric and positive semi-definite.
  const Matrix4 I_KH = Matrix4::Identity() - K * H.transpose();
  P_ = I_KH * P_ * I_KH.transpose() + (stddev * stddev) * K * K.transpose();
  P_ = 0.5 * (P_ + P_.transpose());
}

void SensorPositionFilter::predict(const Eigen::Quaterniond& orientation,
                                   const Eigen::Vector3d& specific_force_m_s2, double dt) {
  if (!initialized_ || !(dt > 0.0 && dt <= 1.0)) return;
  const Eigen::Vector3d a =
      orientation.normalized() * specific_force_m_s2 - Eigen::Vector3d(0.0, 0.0, kGravityM_S2);
  if (!a.allFinite()) return;
  for (int i = 0; i < 3; ++i) axes_[i].predict(a(i), dt, noise_);
}

SensorPositionFilter::Update SensorPositionFilter::updateFix(const Eigen::Vector3d& position_m,
                                                             double horizontal_stddev_m,
                                                             double vertical_stddev_m,
                                                             double fix_time_s,
                                                             double filter_time_s, double gate_m) {
  const double stddev[3] = {std::max(horizontal_stddev_m, 0.01),
                            std::max(horizontal_stddev_m, 0.01), std::max(vertical_stddev_m, 0.01)};
  if (!position_m.allFinite()) return {false, std::numeric_limits<double>::infinity()};
  if (!initialized_) {
    for (int i = 0; i < 3; ++i) axes_[i].reset(position_m(i), stddev[i], noise_);
    initialized_ = true;
    return {true, 0.0};
  }
  // The fix describes the vehicle at its stamp; the state is at the last IMU
  // sample's. Samples of different topics arrive a few milliseconds apart:
  // carry the fix along the velocity estimate over that offset.
  double shift = filter_time_s - fix_time_s;
  if (!(std::abs(shift) <= 0.5)) shift = 0.0;
  Eigen::Vector3d z;
  Eigen::Vector3d innovation;
  for (int i = 0; i < 3; ++i) {
    z(i) = position_m(i) + axes_[i].velocity() * shift;
    innovation(i) = axes_[i].innovation(z(i), false);
  }
  const Update result{innovation.norm() <= gate_m, innovation.norm()};
  if (!result.accepted) return result;
  for (int i = 0; i < 3; ++i) axes_[i].update(z(i), stddev[i], false);
  return result;
}

SensorPositionFilter::Update SensorPositionFilter::updateAltitude(double altitude_m,
                                                                  double stddev_m, double gate_m) {
  if (!initialized_) return {false, 0.0};
  if (!std::isfinite(altitude_m)) return {false, std::numeric_limits<double>::infinity()};
  const double innovation = axes_[2].innovation(altitude_m, true);
  const Update result{std::abs(innovation) <= gate_m, std::abs(innovation)};
  if (result.accepted) axes_[2].update(altitude_m, std::max(stddev_m, 0.01), true);
  return result;
}

Eigen::Vector3d SensorPositionFilter::position() const {
  return {axes_[0].position(), axes_[1].position(), axes_[2].position()};
}

Eigen::Vector3d SensorPositionFilter::velocity() const {
  return {axes_[0].velocity(), axes_[1].velocity(), axes_[2].velocity()};
}

double SensorPositionFilter::positionStddevM() const {
  return std::max(
      {axes_[0].positionStddev(), axes_[1].positionStddev(), axes_[2].positionStddev()});
}

bool SensorPositionFilter::finite() const {
  return axes_[0].finite() && axes_[1].finite() && axes_[2].finite();
}

bool LinearSpeedDeadReckoning::add(double time_s, const Eigen::Vector3d& body_velocity_m_s,
                                   const Eigen::Quaterniond& orientation, double max_gap_s) {
  if (!(time_s > last_time_s_) || !body_velocity_m_s.allFinite()) return false;
  const double dt = std::min(time_s - last_time_s_, max_gap_s);
  const Eigen::Vector3d v = orientation.normalized() * body_velocity_m_s;
  const Eigen::Vector3d step = previous_velocity_
                                   ? Eigen::Vector3d(0.5 * (*previous_velocity_ + v) * dt)
                                   : Eigen::Vector3d(v * dt);
  position_ += step;
  distance_m_ += step.norm();
  previous_velocity_ = v;
  velocity_ = v;
  last_time_s_ = time_s;
  return true;
}

void FrozenDetector::add(double time_s, const Eigen::VectorXd& value) {
  if (value_ && value_->size() == value.size() && *value_ == value) {
    last_s_ = time_s;
    return;
  }
  value_ = value;
  since_s_ = last_s_ = time_s;
}

}  // namespace behaviorlib::basic
