#include "behaviorlib/sensor_fusion/ins_feed.h"

#include <algorithm>
#include <cmath>

namespace behaviorlib::fusion {

double yawOf(const Eigen::Quaterniond& q) {
  const Eigen::Vector3d forward = q * Eigen::Vector3d::UnitX();
  return std::atan2(forward.y(), forward.x());
}

InsFeed::InsFeed(EkfNoise noise, InsFeedSettings settings)
    : noise_(noise), settings_(settings), ekf_(noise) {}

void InsFeed::reset() {
  ekf_ = InsEkf(noise_);
  last_imu_.reset();
  orientation_.reset();
  gyro_ = Eigen::Vector3d::Zero();
  imu_count_ = 0;
}

bool InsFeed::imu(std::chrono::nanoseconds stamp, const Eigen::Quaterniond& orientation,
                  const Eigen::Vector3d& gyro_rad_s, const Eigen::Vector3d& specific_force_m_s2) {
  orientation_ = orientation;
  gyro_ = gyro_rad_s;
  bool predicted = false;
  if (ekf_.initialized() && last_imu_) {
    ekf_.predict(gyro_, specific_force_m_s2,
                 std::chrono::duration<double>(stamp - *last_imu_).count());
    predicted = true;
    if (settings_.use_imu_yaw && settings_.yaw_every > 0 && imu_count_ % settings_.yaw_every == 0) {
      ekf_.updateYaw(yawOf(orientation), settings_.yaw_stddev_rad);
    }
  }
  last_imu_ = stamp;
  ++imu_count_;
  return predicted;
}

UpdateResult InsFeed::altitude(double altitude_m, double stated_stddev_m) {
  if (!ekf_.initialized()) return {};
  return ekf_.updateBarometer(altitude_m, std::max(stated_stddev_m, settings_.baro_stddev_m));
}

UpdateResult InsFeed::bodyVelocity(const Eigen::Vector3d& velocity_body_m_s) {
  if (!ekf_.initialized()) return {};
  return ekf_.updateBodyVelocity(velocity_body_m_s, settings_.linear_speed_stddev_m_s);
}

}  // namespace behaviorlib::fusion
