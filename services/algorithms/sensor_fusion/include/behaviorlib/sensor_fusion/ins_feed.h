#pragma once

// InsFeed: the inertial navigation that SELF_LOCALIZE_WITH_EKF_SENSOR_FUSION
// and SELF_LOCALIZE_AND_MAP_WITH_LIDAR share. It feeds an InsEkf:
// - every IMU sample predicts over the time since the previous one (once the
//   filter has started), and every `yaw_every`-th corrects the yaw with the
//   IMU's own orientation (when `use_imu_yaw`);
// - a barometer altitude and a body linear speed (optical flow) correct it,
//   each no tighter than its configured standard deviation.
// The behaviors start the filter (the EKF at the first GPS fix, SLAM at the
// first IMU sample) and add their own corrections (GPS, scan matches).
//
//   InsFeed ins(noise, {.use_imu_yaw = true, .yaw_stddev_rad = 0.05});
//   ins.imu(stamp.time_since_epoch(), orientation, gyro_rad_s, specific_force_m_s2);
//   ins.altitude(altitude_m, stated_stddev_m);
//   ins.ekf().position();
//
// Deterministic; not thread-safe.

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <chrono>
#include <cstdint>
#include <optional>

#include "behaviorlib/sensor_fusion/ekf.h"

namespace behaviorlib::fusion {

struct InsFeedSettings {
  bool use_imu_yaw = true;
  double yaw_stddev_rad = 0.05;  ///< of the IMU's yaw
  uint32_t yaw_every = 20;       ///< one yaw correction per this many IMU samples
  double baro_stddev_m = 0.5;    ///< the barometer is trusted no more than this
  double linear_speed_stddev_m_s = 0.1;
};

/// The heading of `q`: the angle of its forward (x) axis in the world's
/// horizontal plane (rad).
double yawOf(const Eigen::Quaterniond& q);

class InsFeed {
 public:
  explicit InsFeed(EkfNoise noise = {}, InsFeedSettings settings = {});

  /// A new filter, not started, and no sample seen.
  void reset();
  void setUseImuYaw(bool use) { settings_.use_imu_yaw = use; }

  /// One IMU sample stamped `stamp` (since the clock's epoch): its orientation (world <- body),
  /// body rates and specific force (body FLU, +9.81 up at rest). Returns
  /// whether the filter predicted (it has started, and a sample came
  /// before this one).
  bool imu(std::chrono::nanoseconds stamp, const Eigen::Quaterniond& orientation,
           const Eigen::Vector3d& gyro_rad_s, const Eigen::Vector3d& specific_force_m_s2);
  /// A barometer altitude with its stated standard deviation (m); nothing
  /// before the filter starts.
  UpdateResult altitude(double altitude_m, double stated_stddev_m);
  /// A linear speed measured in the body frame; nothing before the filter
  /// starts.
  UpdateResult bodyVelocity(const Eigen::Vector3d& velocity_body_m_s);

  InsEkf& ekf() { return ekf_; }
  const InsEkf& ekf() const { return ekf_; }
  /// IMU samples seen since reset().
  uint64_t imuCount() const { return imu_count_; }
  /// The latest IMU sample's orientation, or nullopt before the first.
  const std::optional<Eigen::Quaterniond>& imuOrientation() const { return orientation_; }
  /// The body rates of the latest IMU sample less the filter's gyro bias.
  Eigen::Vector3d bodyRates() const { return gyro_ - ekf_.gyroBias(); }

 private:
  EkfNoise noise_;
  InsFeedSettings settings_;
  InsEkf ekf_;
  std::optional<std::chrono::nanoseconds> last_imu_;
  std::optional<Eigen::Quaterniond> orientation_;
  Eigen::Vector3d gyro_ = Eigen::Vector3d::Zero();
  uint64_t imu_count_ = 0;
};

}  // namespace behaviorlib::fusion
