#include "simulator/sensors/sensor_faults.h"

#include <cmath>
#include <limits>
#include <opencv2/core.hpp>
#include <type_traits>

#include "behaviorlib/image_codec/image_codec.h"
#include "simulator/world/camera.h"  // encodeImage
#include "simulator/world/lidar.h"   // standardNormal

namespace behaviorlib::sim {
namespace {

// Full scales of the garbage values.
constexpr double kGarbageJumpMinM = 20.0;     // GPS, barometer
constexpr double kGarbageJumpMaxM = 200.0;    //
constexpr double kGyroFullScaleRadS = 35.0;   // ~2000 deg/s
constexpr double kAccelFullScaleMS2 = 160.0;  // ~16 g
constexpr double kSpeedFullScaleMS = 30.0;
constexpr double kGarbageNanRatio = 0.1;  // lidar beams or points

/// Uniform in [0, 1), the same on every platform (53 bits of one draw).
double uniform01(std::mt19937_64& rng) {
  return static_cast<double>(rng() >> 11) * (1.0 / 9007199254740992.0);
}

double uniform(std::mt19937_64& rng, double low, double high) {
  return low + (high - low) * uniform01(rng);
}

Eigen::Vector3d normal3(std::mt19937_64& rng) {
  const double x = standardNormal(rng);
  const double y = standardNormal(rng);
  const double z = standardNormal(rng);
  return {x, y, z};
}

Eigen::Vector3d uniform3(std::mt19937_64& rng, double full_scale) {
  const double x = uniform(rng, -full_scale, full_scale);
  const double y = uniform(rng, -full_scale, full_scale);
  const double z = uniform(rng, -full_scale, full_scale);
  return {x, y, z};
}

/// A direction uniformly distributed on the sphere.
Eigen::Vector3d unitVector(std::mt19937_64& rng) {
  Eigen::Vector3d v = normal3(rng);
  while (v.norm() < 1e-9) v = normal3(rng);
  return v.normalized();
}

Eigen::Quaterniond rotationOf(const Eigen::Vector3d& theta) {
  const double angle = theta.norm();
  if (angle < 1e-12) return Eigen::Quaterniond::Identity();
  return Eigen::Quaterniond(Eigen::AngleAxisd(angle, theta / angle));
}

/// A jump of 20..200 m, either sign.
double jump(std::mt19937_64& rng) {
  const double magnitude = uniform(rng, kGarbageJumpMinM, kGarbageJumpMaxM);
  return uniform01(rng) < 0.5 ? -magnitude : magnitude;
}

/// The image as BGR, or an empty Mat if it does not decode.
cv::Mat decode(const CameraImageData& image) {
  absl::StatusOr<cv::Mat> bgr = image_codec::decodeToBgr(image.data);
  return bgr.ok() ? *std::move(bgr) : cv::Mat();
}

void reencode(CameraImageData& image, const cv::Mat& bgr, int jpeg_quality) {
  absl::StatusOr<std::string> encoded = encodeImage(bgr, image.encoding, jpeg_quality);
  if (encoded.ok()) image.data = std::move(*encoded);
}

template <class>
[[maybe_unused]] inline constexpr bool kAlwaysFalse = false;

}  // namespace

std::string_view sensorFaultName(SensorFaultType type) {
  switch (type) {
    case SensorFaultType::kOk:
      return "ok";
    case SensorFaultType::kOff:
      return "off";
    case SensorFaultType::kStuck:
      return "stuck";
    case SensorFaultType::kNoisy:
      return "noisy";
    case SensorFaultType::kGarbage:
      return "garbage";
    case SensorFaultType::kIntermittent:
      return "intermittent";
    case SensorFaultType::kDelayed:
      return "delayed";
  }
  return "unknown";
}

SensorFaultModel SensorFaultModel::of(SensorKind kind, const SensorConfig& c) {
  SensorFaultModel model;
  model.jpeg_quality = c.camera.jpeg_quality;
  switch (kind) {
    case SensorKind::kImu:
      model.stddev = {c.imu.gyro_noise_stddev_rad_s, c.imu.accel_noise_stddev_m_s2,
                      c.imu.orientation_noise_stddev_rad};
      break;
    case SensorKind::kGps:
      model.stddev = {c.gps.horizontal_stddev_m, c.gps.vertical_stddev_m, 0.0};
      break;
    case SensorKind::kBaro:
      model.stddev = {c.baro.noise_stddev_m, 0.0, 0.0};
      break;
    case SensorKind::kLinearSpeed:
      model.stddev = {c.linear_speed.noise_stddev_m_s, 0.0, 0.0};
      break;
    case SensorKind::kBattery:
      model.stddev = {c.battery.voltage_noise_stddev_v, c.battery.current_noise_stddev_a, 0.0};
      break;
    case SensorKind::kLidar:
      model.stddev = {c.lidar.noise_stddev_m, 0.0, 0.0};
      break;
    case SensorKind::kCamera:
    case SensorKind::kCameraInfo:
      break;
  }
  return model;
}

void addFaultNoise(SampleData& data, const SensorFaultModel& model, double intensity,
                   std::mt19937_64& rng) {
  // Independent Gaussian noise adds in variance: extra = sqrt(s^2 - 1) sigma
  // makes the total s sigma.
  const double s = noisyScale(intensity);
  const double k = std::sqrt(std::max(0.0, s * s - 1.0));
  const auto& sd = model.stddev;
  std::visit(
      [&](auto& d) {
        using T = std::decay_t<decltype(d)>;
        if constexpr (std::is_same_v<T, ImuData>) {
          d.angular_velocity_rad_s += k * sd[0] * normal3(rng);
          d.specific_force_m_s2 += k * sd[1] * normal3(rng);
          d.orientation = (d.orientation * rotationOf(k * sd[2] * normal3(rng))).normalized();
        } else if constexpr (std::is_same_v<T, PositionFixData>) {
          const Eigen::Vector3d n = normal3(rng);
          d.position_m += k * Eigen::Vector3d(sd[0] * n.x(), sd[0] * n.y(), sd[1] * n.z());
        } else if constexpr (std::is_same_v<T, AltitudeData>) {
          d.altitude_m += k * sd[0] * standardNormal(rng);
        } else if constexpr (std::is_same_v<T, LinearSpeedData>) {
          d.velocity_m_s += k * sd[0] * normal3(rng);
        } else if constexpr (std::is_same_v<T, BatteryData>) {
          const double voltage = standardNormal(rng);
          const double current = standardNormal(rng);
          d.voltage_v = std::max(0.0, d.voltage_v + k * sd[0] * voltage);
          d.current_a += k * sd[1] * current;
        } else if constexpr (std::is_same_v<T, LidarData>) {
          const double sigma = k * sd[0];
          for (float& r : d.ranges_m) {
            const double n = standardNormal(rng);
            if (std::isfinite(r)) r = static_cast<float>(std::max(0.0, r + sigma * n));
          }
          for (Eigen::Vector3f& p : d.points_m) {
            const double n = standardNormal(rng);
            const double range = p.norm();
            if (range > 0.0) p *= static_cast<float>(std::max(0.0, range + sigma * n) / range);
          }
        } else if constexpr (std::is_same_v<T, CameraImageData>) {
          cv::Mat image = decode(d);
          if (image.empty()) return;
          cv::Mat noise(image.size(), CV_16SC3);
          cv::RNG cv_rng(rng());
          cv_rng.fill(noise, cv::RNG::NORMAL, 0.0, kCameraNoiseGreyLevels * intensity);
          cv::Mat noisy;
          cv::add(image, noise, noisy, cv::noArray(), CV_8UC3);
          reencode(d, noisy, model.jpeg_quality);
        } else if constexpr (std::is_same_v<T, CameraInfoData>) {
          // Configuration, not a measurement: nothing to perturb.
        } else {
          static_assert(kAlwaysFalse<T>, "every sample type must be handled");
        }
      },
      data);
}

void garble(SampleData& data, const SensorFaultModel& model, std::mt19937_64& rng) {
  std::visit(
      [&](auto& d) {
        using T = std::decay_t<decltype(d)>;
        if constexpr (std::is_same_v<T, ImuData>) {
          d.angular_velocity_rad_s = uniform3(rng, kGyroFullScaleRadS);
          d.specific_force_m_s2 = uniform3(rng, kAccelFullScaleMS2);
          // A uniformly random rotation (named draws: argument order is
          // unspecified).
          const double w = standardNormal(rng);
          const Eigen::Vector3d v = normal3(rng);
          const Eigen::Quaterniond q(w, v.x(), v.y(), v.z());
          d.orientation = q.norm() > 1e-9 ? q.normalized() : Eigen::Quaterniond::Identity();
        } else if constexpr (std::is_same_v<T, PositionFixData>) {
          const Eigen::Vector3d direction = unitVector(rng);
          d.position_m += uniform(rng, kGarbageJumpMinM, kGarbageJumpMaxM) * direction;
        } else if constexpr (std::is_same_v<T, AltitudeData>) {
          d.altitude_m += jump(rng);
        } else if constexpr (std::is_same_v<T, LinearSpeedData>) {
          d.velocity_m_s = uniform3(rng, kSpeedFullScaleMS);
        } else if constexpr (std::is_same_v<T, BatteryData>) {
          d.charge_ratio = uniform01(rng);
          d.voltage_v = uniform(rng, 0.0, 30.0);
          d.current_a = uniform(rng, -50.0, 150.0);
        } else if constexpr (std::is_same_v<T, LidarData>) {
          const float nan = std::numeric_limits<float>::quiet_NaN();
          for (float& r : d.ranges_m) {
            const double u = uniform01(rng);
            const double range = uniform(rng, d.range_min_m, d.range_max_m);
            r = u < kGarbageNanRatio ? nan : static_cast<float>(range);
          }
          for (Eigen::Vector3f& p : d.points_m) {
            const double u = uniform01(rng);
            const Eigen::Vector3d direction = unitVector(rng);
            const double range = uniform(rng, d.range_min_m, d.range_max_m);
            if (u < kGarbageNanRatio) {
              p = Eigen::Vector3f::Constant(nan);
            } else {
              p = (range * direction).cast<float>();
            }
          }
        } else if constexpr (std::is_same_v<T, CameraImageData>) {
          cv::Mat image(d.height_px, d.width_px, CV_8UC3);
          cv::RNG cv_rng(rng());
          cv_rng.fill(image, cv::RNG::UNIFORM, 0, 256);
          reencode(d, image, model.jpeg_quality);
        } else if constexpr (std::is_same_v<T, CameraInfoData>) {
          // Configuration, not a measurement.
        } else {
          static_assert(kAlwaysFalse<T>, "every sample type must be handled");
        }
      },
      data);
}

void SensorChannel::setFault(SimTime since, const SensorFault& fault) {
  std::lock_guard lock(mutex_);
  if (!history_.empty() && history_.back().first >= since) {
    // The same instant (or, defensively, an earlier one): the last word wins.
    history_.back().second = fault;
  } else {
    history_.emplace_back(since, fault);
    if (history_.size() > kHistory) history_.erase(history_.begin());
  }
  any_.store(true, std::memory_order_release);
}

SensorFault SensorChannel::faultAt(SimTime stamp) const {
  if (!any_.load(std::memory_order_acquire)) return {};
  std::lock_guard lock(mutex_);
  for (auto it = history_.rbegin(); it != history_.rend(); ++it) {
    if (it->first < stamp) return it->second;
  }
  return {};
}

SensorFault SensorChannel::current() const {
  std::lock_guard lock(mutex_);
  return history_.empty() ? SensorFault{} : history_.back().second;
}

void SensorChannel::clearFaults() {
  std::lock_guard lock(mutex_);
  history_.clear();
  any_.store(false, std::memory_order_release);
}

}  // namespace behaviorlib::sim
