#include "behaviorlib/sensor_fusion/ekf.h"

#include <cmath>

namespace behaviorlib::fusion {
namespace {

constexpr double kGravity = 9.81;
// Indexes of the error state.
constexpr int kP = 0, kV = 3, kTheta = 6, kBa = 9, kBg = 12, kBaro = 15;

Eigen::Quaterniond deltaRotation(const Eigen::Vector3d& rotation_vector) {
  const double angle = rotation_vector.norm();
  if (angle < 1e-12) return Eigen::Quaterniond::Identity();
  return Eigen::Quaterniond(Eigen::AngleAxisd(angle, rotation_vector / angle));
}

double wrap(double a) { return std::atan2(std::sin(a), std::cos(a)); }

double yawOf(const Eigen::Quaterniond& q) {
  const Eigen::Vector3d forward = q * Eigen::Vector3d::UnitX();
  return std::atan2(forward.y(), forward.x());
}

}  // namespace

Eigen::Matrix3d skew(const Eigen::Vector3d& v) {
  Eigen::Matrix3d m;
  m << 0, -v.z(), v.y(), v.z(), 0, -v.x(), -v.y(), v.x(), 0;
  return m;
}

InsEkf::InsEkf(EkfNoise noise) : noise_(noise) {}

void InsEkf::initialize(const Eigen::Vector3d& position_m, const Eigen::Vector3d& velocity_m_s,
                        const Eigen::Quaterniond& orientation) {
  p_ = position_m;
  v_ = velocity_m_s;
  q_ = orientation.normalized();
  ba_.setZero();
  bg_.setZero();
  baro_offset_m_ = 0.0;
  P_.setZero();
  auto block = [&](int i, double stddev) {
    P_.block<3, 3>(i, i) = Eigen::Matrix3d::Identity() * stddev * stddev;
  };
  block(kP, noise_.initial_position_stddev_m);
  block(kV, noise_.initial_velocity_stddev_m_s);
  block(kTheta, noise_.initial_attitude_stddev_rad);
  block(kBa, noise_.initial_accel_bias_stddev_m_s2);
  block(kBg, noise_.initial_gyro_bias_stddev_rad_s);
  P_(kBaro, kBaro) = noise_.initial_baro_offset_stddev_m * noise_.initial_baro_offset_stddev_m;
  rejected_ = 0;
  initialized_ = true;
}

void InsEkf::predict(const Eigen::Vector3d& gyro_rad_s, const Eigen::Vector3d& specific_force_m_s2,
                     double dt_s) {
  if (!initialized_ || !(dt_s > 0.0) || dt_s > 1.0) return;
  const Eigen::Matrix3d R = q_.toRotationMatrix();
  const Eigen::Vector3d f = specific_force_m_s2 - ba_;
  const Eigen::Vector3d w = gyro_rad_s - bg_;
  const Eigen::Vector3d a = R * f + Eigen::Vector3d(0, 0, -kGravity);

  p_ += v_ * dt_s + 0.5 * a * dt_s * dt_s;
  v_ += a * dt_s;
  q_ = (q_ * deltaRotation(w * dt_s)).normalized();

  ErrorMatrix F = ErrorMatrix::Identity();
  F.block<3, 3>(kP, kV) = Eigen::Matrix3d::Identity() * dt_s;
  F.block<3, 3>(kV, kTheta) = -R * skew(f) * dt_s;
  F.block<3, 3>(kV, kBa) = -R * dt_s;
  F.block<3, 3>(kTheta, kTheta) = deltaRotation(-w * dt_s).toRotationMatrix();
  F.block<3, 3>(kTheta, kBg) = -Eigen::Matrix3d::Identity() * dt_s;

  ErrorMatrix Q = ErrorMatrix::Zero();
  const auto I = Eigen::Matrix3d::Identity();
  Q.block<3, 3>(kV, kV) = I * std::pow(noise_.accel_noise_m_s2, 2) * dt_s;
  Q.block<3, 3>(kTheta, kTheta) = I * std::pow(noise_.gyro_noise_rad_s, 2) * dt_s;
  Q.block<3, 3>(kBa, kBa) = I * std::pow(noise_.accel_bias_walk_m_s3, 2) * dt_s;
  Q.block<3, 3>(kBg, kBg) = I * std::pow(noise_.gyro_bias_walk_rad_s2, 2) * dt_s;
  Q(kBaro, kBaro) = std::pow(noise_.baro_drift_m_sqrt_s, 2) * dt_s;
  P_ = F * P_ * F.transpose() + Q;
  P_ = 0.5 * (P_ + P_.transpose());
}

template <int M>
UpdateResult InsEkf::update(const Eigen::Matrix<double, M, 1>& innovation,
                            const Eigen::Matrix<double, M, kErrorStates>& H,
                            const Eigen::Matrix<double, M, M>& R) {
  UpdateResult result;
  if (!initialized_ || !innovation.allFinite() || !R.allFinite()) {
    ++rejected_;
    return result;
  }
  const Eigen::Matrix<double, M, M> S = H * P_ * H.transpose() + R;
  const Eigen::Matrix<double, M, M> S_inv = S.inverse();
  result.nis = innovation.dot(S_inv * innovation);
  if (!std::isfinite(result.nis) || result.nis > gate(M)) {
    ++rejected_;
    return result;
  }
  const Eigen::Matrix<double, kErrorStates, M> K = P_ * H.transpose() * S_inv;
  inject(K * innovation);
  // Joseph form: stays symmetric positive semi-definite.
  const ErrorMatrix IKH = ErrorMatrix::Identity() - K * H;
  P_ = IKH * P_ * IKH.transpose() + K * R * K.transpose();
  result.accepted = true;
  return result;
}

void InsEkf::inject(const ErrorVector& dx) {
  p_ += dx.segment<3>(kP);
  v_ += dx.segment<3>(kV);
  q_ = (q_ * deltaRotation(dx.segment<3>(kTheta))).normalized();
  ba_ += dx.segment<3>(kBa);
  bg_ += dx.segment<3>(kBg);
  baro_offset_m_ += dx(kBaro);
}

UpdateResult InsEkf::updatePosition(const Eigen::Vector3d& position_m, double stddev_horizontal_m,
                                    double stddev_vertical_m) {
  Eigen::Matrix<double, 3, kErrorStates> H = Eigen::Matrix<double, 3, kErrorStates>::Zero();
  H.block<3, 3>(0, kP) = Eigen::Matrix3d::Identity();
  Eigen::Matrix3d R = Eigen::Vector3d(stddev_horizontal_m * stddev_horizontal_m,
                                      stddev_horizontal_m * stddev_horizontal_m,
                                      stddev_vertical_m * stddev_vertical_m)
                          .asDiagonal();
  return update<3>(position_m - p_, H, R);
}

UpdateResult InsEkf::updateHorizontalPosition(const Eigen::Vector2d& position_m,
                                              const Eigen::Matrix2d& covariance_m2) {
  Eigen::Matrix<double, 2, kErrorStates> H = Eigen::Matrix<double, 2, kErrorStates>::Zero();
  H.block<2, 2>(0, kP) = Eigen::Matrix2d::Identity();
  return update<2>(position_m - p_.head<2>(), H, covariance_m2);
}

UpdateResult InsEkf::updateBarometer(double altitude_m, double stddev_m) {
  // The barometer reads the altitude plus its own slowly drifting offset.
  Eigen::Matrix<double, 1, kErrorStates> H = Eigen::Matrix<double, 1, kErrorStates>::Zero();
  H(0, kP + 2) = 1.0;
  H(0, kBaro) = 1.0;
  Eigen::Matrix<double, 1, 1> z, R;
  z << altitude_m - (p_.z() + baro_offset_m_);
  R << stddev_m * stddev_m;
  return update<1>(z, H, R);
}

UpdateResult InsEkf::updateBodyVelocity(const Eigen::Vector3d& velocity_body_m_s,
                                        double stddev_m_s) {
  const Eigen::Matrix3d Rt = q_.toRotationMatrix().transpose();
  const Eigen::Vector3d predicted = Rt * v_;
  Eigen::Matrix<double, 3, kErrorStates> H = Eigen::Matrix<double, 3, kErrorStates>::Zero();
  H.block<3, 3>(0, kV) = Rt;
  H.block<3, 3>(0, kTheta) = skew(predicted);
  const Eigen::Matrix3d R = Eigen::Matrix3d::Identity() * stddev_m_s * stddev_m_s;
  return update<3>(velocity_body_m_s - predicted, H, R);
}

UpdateResult InsEkf::updateYaw(double yaw_rad, double stddev_rad) {
  // d(yaw)/d(dtheta) for a body-frame rotation error: the world z axis
  // expressed in the body frame.
  const Eigen::Vector3d z_body = q_.conjugate() * Eigen::Vector3d::UnitZ();
  Eigen::Matrix<double, 1, kErrorStates> H = Eigen::Matrix<double, 1, kErrorStates>::Zero();
  H.block<1, 3>(0, kTheta) = z_body.transpose();
  Eigen::Matrix<double, 1, 1> z, R;
  z << wrap(yaw_rad - yawOf(q_));
  R << stddev_rad * stddev_rad;
  return update<1>(z, H, R);
}

double InsEkf::horizontalStddevM() const {
  return std::sqrt(std::max(0.0, P_(kP, kP) + P_(kP + 1, kP + 1)));
}

bool InsEkf::finite() const {
  return p_.allFinite() && v_.allFinite() && q_.coeffs().allFinite() &&
         std::isfinite(baro_offset_m_) && P_.allFinite();
}

double InsEkf::gate(int dimension) {
  switch (dimension) {
    case 1:
      return 10.83;
    case 2:
      return 13.82;
    default:
      return 16.27;
  }
}

}  // namespace behaviorlib::fusion
