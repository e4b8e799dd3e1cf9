// Fuzzes world files (formats/world/world.h): parseWorld on the raw bytes,
// then what the simulator does with a world it loaded: ray casts and a lidar
// scan from the start poses, collision tests, marker geometry.

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cmath>
#include <cstdint>
#include <string_view>

#include "formats/world/world.h"
#include "fuzz_support.h"
#include "simulator/world/lidar.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  using behaviorlib::world::World;
  const std::string_view text(reinterpret_cast<const char*>(data), size);
  const absl::StatusOr<World> world =
      behaviorlib::world::parseWorld(text, behaviorlib::fuzz::kFileName);
  if (!world.ok()) {
    behaviorlib::fuzz::checkParseError(world.status(), "parseWorld");
    return 0;
  }
  for (const auto& box : world->boxes()) (void)world->findBox(box.name);
  for (const auto& marker : world->markers()) {
    (void)world->findMarker(marker.name);
    for (const Eigen::Vector3d& corner : marker.corners()) (void)corner.norm();
    (void)marker.right();
  }
  // A coarse 2-D lidar (the shipped one has 360 beams; fewer keep a fuzzed
  // world of thousands of boxes fast).
  behaviorlib::sim::LidarConfig lidar_config;
  lidar_config.beams = 45;
  auto lidar = behaviorlib::sim::Lidar::create(*world, lidar_config);
  int poses = 0;
  for (const auto& start : world->startPoses()) {
    if (++poses > 4) break;
    (void)world->findStartPose(start.robot_id);
    const Eigen::Vector3d at = start.position_m + Eigen::Vector3d(0.0, 0.0, 1.0);
    const Eigen::Vector3d directions[] = {
        Eigen::Vector3d(1.0, 0.0, 0.0),  Eigen::Vector3d(-1.0, 0.0, 0.0),
        Eigen::Vector3d(0.0, 1.0, 0.0),  Eigen::Vector3d(0.0, -1.0, 0.0),
        Eigen::Vector3d(0.0, 0.0, -1.0), Eigen::Vector3d(1.0, 1.0, 1.0).normalized()};
    for (const Eigen::Vector3d& direction : directions) {
      (void)world->castRay(at, direction, 50.0);
    }
    (void)world->collides(start.position_m, 0.3);
    (void)world->collidingSurface(at, 0.3);
    if (lidar.ok()) {
      const Eigen::Quaterniond yaw(Eigen::AngleAxisd(start.yaw_rad, Eigen::Vector3d::UnitZ()));
      (void)lidar->scan(at, yaw).ranges_m.size();
    }
  }
  return 0;
}
