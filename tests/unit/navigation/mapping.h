#pragma once

// Builds an occupancy map of a world from simulated 3-D lidar scans taken
// at given poses (what navigation_with_lidar does while the vehicle flies).

#include <cmath>
#include <vector>

#include "behaviorlib/navigation/occupancy_map.h"
#include "formats/world/world.h"
#include "simulator/world/lidar.h"

namespace behaviorlib::nav::testing {

inline sim::LidarConfig mappingLidar() {
  sim::LidarConfig c;
  c.beams = 360;
  c.channels = 16;
  c.elevation_min_rad = -0.26;
  c.elevation_max_rad = 0.26;
  c.range_max_m = 12.0;
  c.noise_stddev_m = 0.02;
  return c;
}

// The hits and the ends of the rays that hit nothing (at the lidar's range)
// of one scan from `position`, in world coordinates.
inline void scanPoints(sim::Lidar& lidar, const Eigen::Vector3d& position,
                       const Eigen::Quaterniond& attitude, std::vector<Eigen::Vector3d>& hits,
                       std::vector<Eigen::Vector3d>& misses) {
  const sim::LidarScan scan = lidar.scan(position, attitude);
  for (int ch = 0; ch < scan.channels; ++ch) {
    const double el = lidar.elevationRad(ch);
    for (int b = 0; b < scan.beams; ++b) {
      const double az = lidar.azimuthRad(b);
      const Eigen::Vector3d dir =
          attitude *
          Eigen::Vector3d(std::cos(el) * std::cos(az), std::cos(el) * std::sin(az), std::sin(el));
      const float r = scan.at(ch, b);
      if (std::isinf(r) && r > 0) {
        misses.push_back(position + dir * lidar.config().range_max_m);
      } else if (std::isfinite(r)) {
        hits.push_back(position + dir * static_cast<double>(r));
      }
    }
  }
}

inline void scanInto(OccupancyMap& map, sim::Lidar& lidar, const Eigen::Vector3d& position) {
  std::vector<Eigen::Vector3d> hits, misses;
  scanPoints(lidar, position, Eigen::Quaterniond::Identity(), hits, misses);
  map.insertScan(position, hits, misses);
}

}  // namespace behaviorlib::nav::testing
