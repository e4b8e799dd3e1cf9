#include "simulator/sensors/sensor_suite.h"

#include <cmath>
#include <stdexcept>

namespace behaviorlib::sim {
namespace {

/// Standard gravity (m/s^2): what an accelerometer at rest reads upwards.
constexpr double kGravity_m_s2 = 9.80665;

uint64_t splitMix64(uint64_t x) {
  x += 0x9e3779b97f4a7c15ULL;
  x = (x ^ (x >> 30)) * 0xbf58476d1ce4e5b9ULL;
  x = (x ^ (x >> 27)) * 0x94d049bb133111ebULL;
  return x ^ (x >> 31);
}

uint64_t fnv1a64(std::string_view text, uint64_t hash = 0xcbf29ce484222325ULL) {
  for (unsigned char ch : text) {
    hash ^= ch;
    hash *= 0x100000001b3ULL;
  }
  return hash;
}

Eigen::Vector3d normal3(std::mt19937_64& rng) {
  // Named draws: the order of evaluation of function arguments is unspecified.
  const double x = standardNormal(rng);
  const double y = standardNormal(rng);
  const double z = standardNormal(rng);
  return {x, y, z};
}

/// The rotation by the rotation vector `theta` (rad).
Eigen::Quaterniond rotationOf(const Eigen::Vector3d& theta) {
  const double angle = theta.norm();
  if (angle < 1e-12) return Eigen::Quaterniond::Identity();
  return Eigen::Quaterniond(Eigen::AngleAxisd(angle, theta / angle));
}

}  // namespace

std::string_view sensorName(SensorKind kind) {
  switch (kind) {
    case SensorKind::kImu:
      return "imu";
    case SensorKind::kGps:
      return "gps";
    case SensorKind::kBaro:
      return "baro";
    case SensorKind::kLinearSpeed:
      return "linear_speed";
    case SensorKind::kBattery:
      return "battery";
    case SensorKind::kLidar:
      return "lidar";
    case SensorKind::kCamera:
      return "camera";
    case SensorKind::kCameraInfo:
      return "camera_info";
  }
  return "unknown";
}

uint64_t sensorSeed(uint64_t seed, std::string_view robot_id, std::string_view sensor_name) {
  // The length (little-endian, whatever the platform) keeps ("a/", "b") and
  // ("a", "/b") apart.
  char length[8];
  for (int i = 0; i < 8; ++i) {
    length[i] = static_cast<char>((static_cast<uint64_t>(robot_id.size()) >> (8 * i)) & 0xff);
  }
  uint64_t name_hash = fnv1a64(robot_id);
  name_hash = fnv1a64(std::string_view(length, sizeof length), name_hash);
  name_hash = fnv1a64(sensor_name, name_hash);
  return splitMix64(splitMix64(seed) ^ name_hash);
}

SensorScene::SensorScene(std::shared_ptr<const world::World> scene_world,
                         const SensorConfig& config)
    : world(scene_world ? std::move(scene_world) : std::make_shared<const world::World>()) {
  if (config.lidar.rate_hz > 0.0) {
    absl::StatusOr<Lidar> made = Lidar::create(*world, config.lidar.lidarConfig());
    if (!made.ok()) throw std::invalid_argument(std::string(made.status().message()));
    lidar.emplace(std::move(*made));
  }
  if (config.camera.rate_hz > 0.0 || config.camera.info_rate_hz > 0.0) {
    absl::StatusOr<Camera> made = Camera::create(*world, config.camera.cameraConfig());
    if (!made.ok()) throw std::invalid_argument(std::string(made.status().message()));
    camera.emplace(std::move(*made));
  }
}

RateSchedule::RateSchedule(double rate_hz) {
  if (rate_hz > 0.0 && std::isfinite(rate_hz)) {
    period_ns_ = std::max<int64_t>(1, std::llround(1e9 / rate_hz));
    next_ns_ = period_ns_;
  }
}

bool RateSchedule::due(SimTime now) {
  if (period_ns_ <= 0 || now.count() < next_ns_) return false;
  // The next due time after `now` (a vehicle added late skips the past).
  next_ns_ += period_ns_;
  if (next_ns_ <= now.count()) {
    next_ns_ += ((now.count() - next_ns_) / period_ns_ + 1) * period_ns_;
  }
  return true;
}

uint64_t SensorSuite::faultSeed(uint64_t seed, SensorKind kind) const {
  // A generator of its own, so that faults never shift the sensor's noise.
  return sensorSeed(seed, robot_id_, std::string(sensorName(kind)) + "/faults");
}

SensorSuite::Simple SensorSuite::simple(SensorKind kind, double rate_hz, uint64_t seed,
                                        const SensorOutput::Sink* sink,
                                        const SensorChannels& channels) const {
  return Simple{RateSchedule(rate_hz),
                std::mt19937_64(sensorSeed(seed, robot_id_, sensorName(kind))),
                SensorOutput(robot_id_, kind, sink, channels[static_cast<std::size_t>(kind)],
                             SensorFaultModel::of(kind, config_), faultSeed(seed, kind))};
}

std::shared_ptr<FrameSensor> SensorSuite::frameSensor(SensorKind kind, uint64_t seed,
                                                      const SensorOutput::Sink* sink,
                                                      const SensorChannels& channels) const {
  return std::make_shared<FrameSensor>(robot_id_, kind, sink,
                                       channels[static_cast<std::size_t>(kind)],
                                       SensorFaultModel::of(kind, config_), faultSeed(seed, kind));
}

SensorSuite::SensorSuite(std::string robot_id, const SensorConfig& config, uint64_t seed,
                         std::shared_ptr<const SensorScene> scene, const SensorOutput::Sink* sink,
                         const SensorChannels& channels)
    : robot_id_(std::move(robot_id)),
      config_(config),
      scene_(std::move(scene)),
      imu_{RateSchedule(config.imu.rate_hz),
           std::mt19937_64(sensorSeed(seed, robot_id_, sensorName(SensorKind::kImu))),
           SensorOutput(robot_id_, SensorKind::kImu, sink,
                        channels[static_cast<std::size_t>(SensorKind::kImu)],
                        SensorFaultModel::of(SensorKind::kImu, config_),
                        faultSeed(seed, SensorKind::kImu))},
      gps_(simple(SensorKind::kGps, config.gps.rate_hz, seed, sink, channels)),
      baro_(simple(SensorKind::kBaro, config.baro.rate_hz, seed, sink, channels)),
      linear_speed_(
          simple(SensorKind::kLinearSpeed, config.linear_speed.rate_hz, seed, sink, channels)),
      battery_(simple(SensorKind::kBattery, config.battery.rate_hz, seed, sink, channels)),
      camera_info_(simple(SensorKind::kCameraInfo,
                          config.camera.rate_hz > 0.0 ? config.camera.info_rate_hz : 0.0, seed,
                          sink, channels)),
      lidar_{RateSchedule(scene_->lidar ? config.lidar.rate_hz : 0.0),
             std::mt19937_64(sensorSeed(seed, robot_id_, sensorName(SensorKind::kLidar))),
             frameSensor(SensorKind::kLidar, seed, sink, channels)},
      camera_{RateSchedule(scene_->camera ? config.camera.rate_hz : 0.0),
              std::mt19937_64(sensorSeed(seed, robot_id_, sensorName(SensorKind::kCamera))),
              frameSensor(SensorKind::kCamera, seed, sink, channels)} {
  // The biases a unit starts with (after every reset).
  imu_.gyro_bias = config_.imu.gyro_bias_stddev_rad_s * normal3(imu_.rng);
  imu_.accel_bias = config_.imu.accel_bias_stddev_m_s2 * normal3(imu_.rng);
}

void SensorSuite::sampleImu(SimTime now, const VehicleSnapshot& state) {
  const ImuConfig& c = config_.imu;
  const double sqrt_dt = std::sqrt(imu_.schedule.periodS());
  // Fixed draw order: bias walks, then noises, then the orientation error.
  imu_.gyro_bias += c.gyro_bias_walk_rad_s_sqrt_s * sqrt_dt * normal3(imu_.rng);
  imu_.accel_bias += c.accel_bias_walk_m_s2_sqrt_s * sqrt_dt * normal3(imu_.rng);
  const Eigen::Vector3d gyro_noise = c.gyro_noise_stddev_rad_s * normal3(imu_.rng);
  const Eigen::Vector3d accel_noise = c.accel_noise_stddev_m_s2 * normal3(imu_.rng);
  const Eigen::Vector3d attitude_error = c.orientation_noise_stddev_rad * normal3(imu_.rng);

  const Eigen::Quaterniond q = state.orientation.normalized();
  ImuData data;
  data.angular_velocity_rad_s = state.angular_velocity_rad_s + imu_.gyro_bias + gyro_noise;
  const Eigen::Vector3d specific_force_world =
      state.acceleration_m_s2 + Eigen::Vector3d(0.0, 0.0, kGravity_m_s2);
  data.specific_force_m_s2 = q.conjugate() * specific_force_world + imu_.accel_bias + accel_noise;
  data.orientation = (q * rotationOf(attitude_error)).normalized();
  imu_.output.publish(now, std::move(data));
}

void SensorSuite::step(SimTime now, const VehicleSnapshot& state,
                       std::vector<FrameRequest>* frames) {
  // Delayed samples (faults) due now go out before the new ones.
  imu_.output.release(now);
  gps_.output.release(now);
  baro_.output.release(now);
  linear_speed_.output.release(now);
  battery_.output.release(now);
  camera_info_.output.release(now);
  lidar_.sensor->output.release(now);
  camera_.sensor->output.release(now);

  if (imu_.schedule.due(now)) sampleImu(now, state);
  if (gps_.schedule.due(now)) {
    const GpsConfig& c = config_.gps;
    const double nx = standardNormal(gps_.rng);
    const double ny = standardNormal(gps_.rng);
    const double nz = standardNormal(gps_.rng);
    PositionFixData data;
    data.position_m =
        state.position_m + Eigen::Vector3d(c.horizontal_stddev_m * nx, c.horizontal_stddev_m * ny,
                                           c.vertical_stddev_m * nz);
    data.horizontal_stddev_m = c.horizontal_stddev_m;
    data.vertical_stddev_m = c.vertical_stddev_m;
    gps_.output.publish(now, std::move(data));
  }
  if (baro_.schedule.due(now)) {
    const BaroConfig& c = config_.baro;
    baro_.drift +=
        c.drift_walk_m_sqrt_s * std::sqrt(baro_.schedule.periodS()) * standardNormal(baro_.rng);
    const double noise = c.noise_stddev_m * standardNormal(baro_.rng);
    AltitudeData data;
    data.altitude_m = state.position_m.z() + baro_.drift + noise;
    data.stddev_m = c.noise_stddev_m;
    baro_.output.publish(now, std::move(data));
  }
  if (linear_speed_.schedule.due(now)) {
    const Eigen::Vector3d noise =
        config_.linear_speed.noise_stddev_m_s * normal3(linear_speed_.rng);
    LinearSpeedData data;
    data.velocity_m_s = state.orientation.normalized().conjugate() * state.velocity_m_s + noise;
    linear_speed_.output.publish(now, std::move(data));
  }
  if (battery_.schedule.due(now)) {
    const BatteryConfig& c = config_.battery;
    const double voltage_noise = c.voltage_noise_stddev_v * standardNormal(battery_.rng);
    const double current_noise = c.current_noise_stddev_a * standardNormal(battery_.rng);
    BatteryData data;
    data.charge_ratio = state.battery_ratio;
    data.voltage_v = std::max(0.0, state.battery_voltage_v + voltage_noise);
    data.current_a = state.battery_current_a + current_noise;
    battery_.output.publish(now, std::move(data));
  }
  if (camera_info_.schedule.due(now) && scene_->camera) {
    const Camera& camera = *scene_->camera;
    const Eigen::Isometry3d body_from_optical =
        camera.worldFromOptical(Eigen::Vector3d::Zero(), Eigen::Quaterniond::Identity());
    CameraInfoData data;
    data.width_px = camera.config().width_px;
    data.height_px = camera.config().height_px;
    data.fx_px = camera.focalLengthPx();
    data.fy_px = camera.focalLengthPx();
    data.cx_px = camera.cx();
    data.cy_px = camera.cy();
    data.position_in_body_m = body_from_optical.translation();
    data.body_from_camera = Eigen::Quaterniond(body_from_optical.rotation()).normalized();
    camera_info_.output.publish(now, std::move(data));
  }
  if (lidar_.schedule.due(now)) {
    // Drawn whether or not the frame gets made: see the file comment.
    const uint64_t noise_seed = lidar_.rng();
    frames->push_back({lidar_.sensor, now, state.position_m, state.orientation, noise_seed});
  }
  if (camera_.schedule.due(now)) {
    frames->push_back({camera_.sensor, now, state.position_m, state.orientation, 0});
  }
}

}  // namespace behaviorlib::sim
