#include "navigation/wall_columns.h"

#include <cmath>

namespace behaviorlib::nav {

void WallColumns::afterScan(OccupancyMap& map, const std::vector<Eigen::Vector3d>& hits_m) {
  const double res = settings_.resolution_m;
  for (const Eigen::Vector3d& h : hits_m) {
    if (!h.allFinite() || h.z() > settings_.max_hit_z_m) continue;
    const auto cx = static_cast<int64_t>(std::floor(h.x() / res));
    const auto cy = static_cast<int64_t>(std::floor(h.y() / res));
    const uint64_t key =
        (static_cast<uint64_t>(cx & 0xffffffff) << 32) | static_cast<uint64_t>(cy & 0xffffffff);
    if (!columns_.insert(key).second) continue;
    // One zero-length ray per voxel: occupied, and nothing else cleared.
    for (double z = settings_.min_z_m + 0.5 * res; z < settings_.max_z_m; z += res) {
      const Eigen::Vector3d p((static_cast<double>(cx) + 0.5) * res,
                              (static_cast<double>(cy) + 0.5) * res, z);
      map.insertScan(p, {p});
    }
  }
}

}  // namespace behaviorlib::nav
