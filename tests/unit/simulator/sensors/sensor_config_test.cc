#include "simulator/sensors/sensor_config.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <fstream>
#include <string>

namespace behaviorlib::sim {
namespace {

using ::testing::HasSubstr;
using ::testing::StartsWith;

/// Every setting, in order, for comparisons.
std::vector<double> flatten(const SensorConfig& c) {
  return {c.imu.rate_hz,
          c.imu.gyro_noise_stddev_rad_s,
          c.imu.gyro_bias_stddev_rad_s,
          c.imu.gyro_bias_walk_rad_s_sqrt_s,
          c.imu.accel_noise_stddev_m_s2,
          c.imu.accel_bias_stddev_m_s2,
          c.imu.accel_bias_walk_m_s2_sqrt_s,
          c.imu.orientation_noise_stddev_rad,
          c.gps.rate_hz,
          c.gps.horizontal_stddev_m,
          c.gps.vertical_stddev_m,
          c.baro.rate_hz,
          c.baro.noise_stddev_m,
          c.baro.drift_walk_m_sqrt_s,
          c.linear_speed.rate_hz,
          c.linear_speed.noise_stddev_m_s,
          c.battery.rate_hz,
          c.battery.voltage_noise_stddev_v,
          c.battery.current_noise_stddev_a,
          c.lidar.rate_hz,
          static_cast<double>(c.lidar.beams),
          c.lidar.field_of_view_rad,
          static_cast<double>(c.lidar.channels),
          c.lidar.elevation_min_rad,
          c.lidar.elevation_max_rad,
          c.lidar.range_min_m,
          c.lidar.range_max_m,
          c.lidar.noise_stddev_m,
          c.lidar.mount_position_m.x(),
          c.lidar.mount_position_m.y(),
          c.lidar.mount_position_m.z(),
          c.camera.rate_hz,
          c.camera.info_rate_hz,
          static_cast<double>(c.camera.width_px),
          static_cast<double>(c.camera.height_px),
          c.camera.horizontal_fov_rad,
          c.camera.mount_position_m.x(),
          c.camera.mount_position_m.y(),
          c.camera.mount_position_m.z(),
          c.camera.mount_pitch_rad,
          static_cast<double>(c.camera.jpeg_quality),
          static_cast<double>(c.worker_threads)};
}

TEST(SensorConfig, TheDefaultsAreValid) { EXPECT_TRUE(SensorConfig{}.validate().ok()); }

TEST(SensorConfig, TheDocumentedExampleFileStatesTheDefaults) {
  absl::StatusOr<SensorConfig> config = loadSensorConfig(BEHAVIORLIB_SENSOR_CONFIG_EXAMPLE);
  ASSERT_TRUE(config.ok()) << config.status();
  EXPECT_EQ(flatten(*config), flatten(SensorConfig{}));
  EXPECT_EQ(config->camera.format, "jpeg");
}

TEST(SensorConfig, AnEmptyFileKeepsTheDefaultsAndKeysOverrideThem) {
  absl::StatusOr<SensorConfig> empty = parseSensorConfig("# nothing\n", "empty.yaml");
  ASSERT_TRUE(empty.ok()) << empty.status();
  EXPECT_EQ(flatten(*empty), flatten(SensorConfig{}));

  absl::StatusOr<SensorConfig> config = parseSensorConfig(
      "gps:\n  rate_hz: 0\nlidar:\n  channels: 16\n  mount_position_m: [0.1, 0, 0.2]\n"
      "camera:\n  format: png\n  width_px: 320\nimu:\n",
      "mine.yaml");
  ASSERT_TRUE(config.ok()) << config.status();
  EXPECT_EQ(config->gps.rate_hz, 0.0);
  EXPECT_EQ(config->gps.horizontal_stddev_m, SensorConfig{}.gps.horizontal_stddev_m);
  EXPECT_TRUE(config->lidar.threeD());
  EXPECT_EQ(config->lidar.mount_position_m, Eigen::Vector3d(0.1, 0, 0.2));
  EXPECT_EQ(config->camera.format, "png");
  EXPECT_EQ(config->camera.width_px, 320);
  EXPECT_EQ(config->imu.rate_hz, 200.0);
  // The lidar's field of view is centred on body +x.
  const LidarConfig lidar = config->lidar.lidarConfig();
  EXPECT_EQ(lidar.channels, 16);
  EXPECT_DOUBLE_EQ(lidar.angle_min_rad, -lidar.angle_max_rad);
}

struct BadFile {
  const char* text;
  const char* expected;  ///< the whole message after "bad.yaml:"
};

class SensorConfigErrors : public ::testing::TestWithParam<BadFile> {};

TEST_P(SensorConfigErrors, NameTheFileTheLineAndTheProblem) {
  absl::StatusOr<SensorConfig> config = parseSensorConfig(GetParam().text, "bad.yaml");
  ASSERT_FALSE(config.ok());
  EXPECT_EQ(config.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(std::string(config.status().message()), std::string("bad.yaml:") + GetParam().expected);
}

INSTANTIATE_TEST_SUITE_P(
    Files, SensorConfigErrors,
    ::testing::Values(
        BadFile{"imu:\n  rate_hz: fast\n", "2: imu: rate_hz must be a number"},
        BadFile{"imu:\n  rate_hz: 200\n  rat_hz: 3\n",
                "3: imu: unknown key 'rat_hz' (allowed: rate_hz, gyro_noise_stddev_rad_s, "
                "gyro_bias_stddev_rad_s, gyro_bias_walk_rad_s_sqrt_s, accel_noise_stddev_m_s2, "
                "accel_bias_stddev_m_s2, accel_bias_walk_m_s2_sqrt_s, "
                "orientation_noise_stddev_rad)"},
        BadFile{"gps:\n  rate_hz: -1\n",
                "2: gps: rate_hz must be within [0, 1000] (0 disables it), got -1"},
        BadFile{"baro:\n  rate_hz: 2000\n",
                "2: baro: rate_hz must be within [0, 1000] (0 disables it), got 2000"},
        BadFile{"baro:\n  noise_stddev_m: -0.1\n",
                "2: baro: noise_stddev_m must be a non-negative number, got -0.1"},
        BadFile{"lidar:\n  range_min_m: 1\n\n  range_max_m: 0.5\n",
                "4: lidar: range_max_m must be a number > range_min_m"},
        BadFile{"lidar:\n  beams: 1.5\n", "2: lidar: beams must be an integer"},
        BadFile{"lidar:\n  mount_position_m: [0, 0]\n",
                "2: lidar: mount_position_m must be a list of 3 numbers [x, y, z]"},
        BadFile{"camera:\n  format: bmp\n", "2: camera: format must be jpeg or png, got 'bmp'"},
        BadFile{"camera:\n  width_px: 4\n", "2: camera: width_px must be within 8..8192"},
        BadFile{"camera:\n  rate_hz: 15\n  rate_hz: 10\n", "3: camera: duplicate key 'rate_hz'"},
        BadFile{"camera: 15\n", "1: camera: must be a mapping of keys to values"},
        BadFile{"sonar:\n  rate_hz: 1\n",
                "1: unknown key 'sonar' (allowed: worker_threads, imu, gps, baro, linear_speed, "
                "battery, lidar, camera)"},
        BadFile{"worker_threads: 0\n", "1: worker_threads must be within 1..16"},
        BadFile{"imu: [1\n", "2: not valid YAML: end of sequence flow not found"}));

TEST(SensorConfig, AMissingFileIsNotFound) {
  absl::StatusOr<SensorConfig> config = loadSensorConfig("/nonexistent/sensors.yaml");
  ASSERT_FALSE(config.ok());
  EXPECT_EQ(config.status().code(), absl::StatusCode::kNotFound);
  EXPECT_THAT(std::string(config.status().message()), StartsWith("/nonexistent/sensors.yaml: "));
}

TEST(SensorConfig, ValidateNamesTheSectionAndTheSetting) {
  SensorConfig config;
  config.lidar.elevation_max_rad = -1.0;
  EXPECT_TRUE(config.validate().ok()) << "elevations matter for 3-D lidars only";
  config.lidar.channels = 8;
  EXPECT_THAT(std::string(config.validate().message()),
              HasSubstr("lidar: elevation_max_rad must be >= elevation_min_rad"));
}

}  // namespace
}  // namespace behaviorlib::sim
