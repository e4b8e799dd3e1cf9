#include "behaviorlib/navigation/wall_columns.h"

#include <cmath>

namespace behaviorlib::nav {

void WallColumns::afterScan(OccupancyMap& map, const std::vector<Eigen::Vector3d>& hits_m) {
  const double res = settings_.resolution_m;
  auto columnVoxels = [&](const Eigen::Vector3d& raiser, auto&& fn) {
    for (double z = settings_.min_z_m + 0.5 * res; z < settings_.max_z_m; z += res) {
      fn(Eigen::Vector3d(raiser.x(), raiser.y(), z));
    }
  };
  for (const Eigen::Vector3d& h : hits_m) {
    if (!h.allFinite() || h.z() > settings_.max_hit_z_m) continue;
    const double cx = std::floor(h.x() / res);
    const double cy = std::floor(h.y() / res);
    const uint64_t key = (static_cast<uint64_t>(static_cast<int64_t>(cx) & 0xffffffff) << 32) |
                         static_cast<uint64_t>(static_cast<int64_t>(cy) & 0xffffffff);
    const Eigen::Vector3d raiser((cx + 0.5) * res, (cy + 0.5) * res,
                                 (std::floor(h.z() / res) + 0.5) * res);
    if (!columns_.emplace(key, raiser).second) continue;
    // One zero-length ray per voxel: occupied, and nothing else cleared.
    columnVoxels(raiser, [&](const Eigen::Vector3d& p) {
      if (std::abs(p.z() - raiser.z()) > 0.25 * res) map.insertScan(p, {p});
    });
  }
  for (auto it = columns_.begin(); it != columns_.end();) {
    if (!map.certainlyFree(it->second)) {
      ++it;
      continue;
    }
    columnVoxels(it->second, [&](const Eigen::Vector3d& p) { map.forgetVoxel(p); });
    it = columns_.erase(it);
  }
}

}  // namespace behaviorlib::nav
