#pragma once

// SensorConfig: rates, noise levels, lidar and camera settings of the
// simulated sensors, the same for every vehicle. Read from a YAML file
// (format and defaults in simulator/sensors/README.md; a commented example
// with the defaults is deploy/config/simulator_sensors.yaml).
//
//   absl::StatusOr<SensorConfig> config = loadSensorConfig("sensors.yaml");
//   if (!config.ok()) return config.status();  // "sensors.yaml:7: imu: rate_hz must be ..."
//   config->gps.horizontal_stddev_m = 0.2;
//
// Every rate is in samples per second of simulated time; 0 disables the
// sensor. Noise is Gaussian with the given standard deviation per sample;
// random walks grow by their `*_sqrt_s` value per square root of a second.

#include <Eigen/Core>
#include <numbers>
#include <string>
#include <string_view>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "simulator/world/camera.h"
#include "simulator/world/lidar.h"

namespace behaviorlib::sim {

/// Inertial measurement unit (frame base_link, FLU).
struct ImuConfig {
  double rate_hz = 200.0;
  double gyro_noise_stddev_rad_s = 0.003;
  /// Standard deviation of the gyro bias per axis at start (and after Reset).
  double gyro_bias_stddev_rad_s = 0.002;
  /// Random walk of the gyro bias.
  double gyro_bias_walk_rad_s_sqrt_s = 0.0001;
  double accel_noise_stddev_m_s2 = 0.05;
  double accel_bias_stddev_m_s2 = 0.02;
  double accel_bias_walk_m_s2_sqrt_s = 0.001;
  /// Error of the reported orientation: a random rotation per sample.
  double orientation_noise_stddev_rad = 0.002;
};

/// GPS-like world position.
struct GpsConfig {
  double rate_hz = 10.0;
  /// Per horizontal axis (x and y).
  double horizontal_stddev_m = 0.5;
  double vertical_stddev_m = 1.0;
};

/// Barometric altitude: world z plus noise plus a slow drift.
struct BaroConfig {
  double rate_hz = 25.0;
  double noise_stddev_m = 0.1;
  /// Random walk of the offset (drift); starts at 0.
  double drift_walk_m_sqrt_s = 0.02;
};

/// Body-frame linear velocity, like an optical-flow sensor.
struct LinearSpeedConfig {
  double rate_hz = 30.0;
  double noise_stddev_m_s = 0.05;
};

/// Battery charge, voltage and current.
struct BatteryConfig {
  double rate_hz = 2.0;
  double voltage_noise_stddev_v = 0.01;
  double current_noise_stddev_a = 0.05;
};

/// Scanning lidar: 2-D (one channel, a LaserScan) or 3-D (several channels, a
/// PointCloud), ray cast against the world.
struct LidarSensorConfig {
  double rate_hz = 10.0;
  /// Beams per channel, spread over the field of view centred on body +x.
  int beams = 360;
  /// Horizontal field of view; 2 pi (a full turn) or less.
  double field_of_view_rad = 2.0 * std::numbers::pi;
  /// 1: a 2-D lidar scanning the body's horizontal plane; more: a 3-D lidar
  /// with channels spread from elevation_min_rad to elevation_max_rad.
  int channels = 1;
  double elevation_min_rad = -0.2618;  ///< used when channels > 1 (-15 degrees)
  double elevation_max_rad = 0.2618;   ///< used when channels > 1 (+15 degrees)
  double range_min_m = 0.1;
  double range_max_m = 30.0;
  double noise_stddev_m = 0.01;
  /// Position of the lidar in the body frame (FLU); its axes are the body's.
  Eigen::Vector3d mount_position_m{0.0, 0.0, 0.1};

  bool threeD() const { return channels > 1; }
  /// The ray-casting configuration (seed unused: noise comes per frame).
  LidarConfig lidarConfig() const;
};

/// Pinhole camera rendered with OpenCV.
struct CameraSensorConfig {
  /// Images per second (rendered only while someone subscribes).
  double rate_hz = 15.0;
  /// CameraInfo messages per second.
  double info_rate_hz = 1.0;
  int width_px = 640;
  int height_px = 480;
  double horizontal_fov_rad = std::numbers::pi / 3.0;
  /// Position in the body frame (FLU); the camera looks along body +x.
  Eigen::Vector3d mount_position_m{0.1, 0.0, 0.05};
  /// Tilt below body +x; positive looks down.
  double mount_pitch_rad = 0.0;
  /// "jpeg" or "png".
  std::string format = "jpeg";
  int jpeg_quality = 90;

  CameraConfig cameraConfig() const;
};

struct SensorConfig {
  ImuConfig imu;
  GpsConfig gps;
  BaroConfig baro;
  LinearSpeedConfig linear_speed;
  BatteryConfig battery;
  LidarSensorConfig lidar;
  CameraSensorConfig camera;
  /// Threads that ray-cast lidar scans and render camera frames.
  int worker_threads = 2;

  /// OK, or kInvalidArgument naming the first bad setting ("lidar:
  /// range_max_m must be > range_min_m").
  absl::Status validate() const;
};

/// Reads a sensor configuration file; absent keys keep their defaults.
/// Errors (kNotFound for a missing file, else kInvalidArgument) read
/// "<path>:<line>: <section>: <problem>".
absl::StatusOr<SensorConfig> loadSensorConfig(const std::string& path);

/// Parses sensor configuration YAML; `source_name` stands for the file in
/// errors.
absl::StatusOr<SensorConfig> parseSensorConfig(std::string_view yaml_text,
                                               std::string_view source_name);

}  // namespace behaviorlib::sim
