// Fuzzes the simulator's sensor configuration (simulator/sensors/
// sensor_config.h): parseSensorConfig on the raw bytes, then what the
// simulator derives from an accepted configuration: the lidar's ray-casting
// configuration and the lidar itself (its beam directions), scanning an
// empty world when the beam count is small, and the camera's configuration.
// An accepted configuration that the lidar or the camera then refuses would
// stop the simulator at start: the target aborts on it.

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cstdint>
#include <string_view>

#include "formats/world/world.h"
#include "fuzz_support.h"
#include "simulator/sensors/sensor_config.h"
#include "simulator/world/camera.h"
#include "simulator/world/lidar.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  namespace fuzz = behaviorlib::fuzz;
  using behaviorlib::sim::SensorConfig;
  const std::string_view text(reinterpret_cast<const char*>(data), size);
  const absl::StatusOr<SensorConfig> config =
      behaviorlib::sim::parseSensorConfig(text, fuzz::kFileName);
  if (!config.ok()) {
    fuzz::checkParseError(config.status(), "parseSensorConfig");
    return 0;
  }
  // Accepted means valid.
  if (const absl::Status s = config->validate(); !s.ok()) {
    fuzz::broken("parseSensorConfig accepted an invalid configuration", s.ToString());
  }
  static const behaviorlib::world::World* const world = new behaviorlib::world::World("empty");
  const behaviorlib::sim::LidarConfig lidar_config = config->lidar.lidarConfig();
  auto lidar = behaviorlib::sim::Lidar::create(*world, lidar_config);
  if (!lidar.ok()) {
    fuzz::broken("an accepted lidar configuration makes no lidar", lidar.status().ToString());
  }
  (void)lidar->beamNearestAzimuth(0.5);
  // The camera's own checks (Camera::create is left out: its pixel grids
  // take up to 8192 x 8192 floats).
  if (const absl::Status s = config->camera.cameraConfig().validate(); !s.ok()) {
    fuzz::broken("an accepted camera configuration is invalid", s.ToString());
  }
  if (static_cast<long>(lidar_config.beams) * lidar_config.channels <= 4096) {
    const Eigen::Vector3d at(0.0, 0.0, 1.0);
    (void)lidar->scan(at, Eigen::Quaterniond::Identity()).ranges_m.size();
  }
  return 0;
}
