#include "simulator/tools/map_coverage.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <unordered_set>

namespace behaviorlib::nav {

void buildingExtent(const world::World& world, Eigen::Vector2d* min_m, Eigen::Vector2d* max_m) {
  constexpr double kInf = std::numeric_limits<double>::infinity();
  Eigen::Vector2d lo(kInf, kInf), hi(-kInf, -kInf);
  for (const world::Box& box : world.boxes()) {
    if (box.kind != world::Box::Kind::kWall) continue;
    const double c = std::cos(box.yaw_rad), s = std::sin(box.yaw_rad);
    for (const double sx : {-0.5, 0.5}) {
      for (const double sy : {-0.5, 0.5}) {
        const double dx = sx * box.size_m.x(), dy = sy * box.size_m.y();
        const Eigen::Vector2d corner(box.center_m.x() + c * dx - s * dy,
                                     box.center_m.y() + s * dx + c * dy);
        lo = lo.cwiseMin(corner);
        hi = hi.cwiseMax(corner);
      }
    }
  }
  if (!std::isfinite(lo.x())) lo = hi = Eigen::Vector2d::Zero();
  *min_m = lo;
  *max_m = hi;
}

namespace {

/// True when the map has a free leaf within the column segment
/// [z_min, z_max] above (x, y): a search per voxel height.
bool knownFree(const octomap::OcTree& map, double x, double y, double z_min, double z_max) {
  const double step = map.getResolution();
  for (double z = z_min; z <= z_max + 1e-9; z += step) {
    const octomap::OcTreeNode* node = map.search(x, y, z);
    if (node != nullptr && !map.isNodeOccupied(node)) return true;
  }
  return false;
}

bool knownOccupied(const octomap::OcTree& map, double x, double y, double z) {
  const octomap::OcTreeNode* node = map.search(x, y, z);
  return node != nullptr && map.isNodeOccupied(node);
}

}  // namespace

MapCoverage measureCoverage(const world::World& world, const octomap::OcTree& map,
                            const CoverageOptions& options) {
  MapCoverage result;
  result.cell_m = options.cell_m;
  buildingExtent(world, &result.building_min_m, &result.building_max_m);
  const Eigen::Vector2d size = result.building_max_m - result.building_min_m;
  const long nx = static_cast<long>(std::floor(size.x() / options.cell_m));
  const long ny = static_cast<long>(std::floor(size.y() / options.cell_m));
  for (long i = 0; i < nx; ++i) {
    for (long j = 0; j < ny; ++j) {
      const double x = result.building_min_m.x() + (i + 0.5) * options.cell_m;
      const double y = result.building_min_m.y() + (j + 0.5) * options.cell_m;
      if (world.collides({x, y, options.height_m}, 0.0)) continue;
      ++result.free_cells;
      if (knownFree(map, x, y, options.height_m - options.band_m,
                    options.height_m + options.band_m)) {
        ++result.known_free_cells;
      } else if (knownOccupied(map, x, y, options.height_m)) {
        ++result.occupied_cells;
      }
    }
  }
  // The wall error: each occupied voxel in the band, inside the building.
  double sum = 0.0;
  std::unordered_set<int64_t> cells;
  for (auto it = map.begin_leafs(), end = map.end_leafs(); it != end; ++it) {
    if (!map.isNodeOccupied(*it)) continue;
    const double half = 0.5 * it.getSize();
    const Eigen::Vector3d c(it.getX(), it.getY(), it.getZ());
    if (std::abs(c.z() - options.height_m) > options.band_m + half) continue;
    if ((c.head<2>().array() < result.building_min_m.array()).any() ||
        (c.head<2>().array() > result.building_max_m.array()).any()) {
      continue;
    }
    // The smallest radius (to 5 mm, up to 64 m) at which the centre meets a
    // surface: doubled until it does, then halved.
    double lo = 0.0, hi = 0.0;
    if (!world.collides(c, 0.0)) {
      hi = 0.125;
      while (hi < 64.0 && !world.collides(c, hi)) {
        lo = hi;
        hi *= 2.0;
      }
      while (hi - lo > 0.005) {
        const double mid = 0.5 * (lo + hi);
        (world.collides(c, mid) ? hi : lo) = mid;
      }
    }
    const double error = hi;
    const int64_t ix = static_cast<int64_t>(std::floor(c.x() / options.cell_m));
    const int64_t iy = static_cast<int64_t>(std::floor(c.y() / options.cell_m));
    if (cells.insert(ix * 1'000'003 + iy).second) {
      result.occupied_xy_m.emplace_back((ix + 0.5) * options.cell_m, (iy + 0.5) * options.cell_m);
    }
    sum += error;
    result.wall_error_max_m = std::max(result.wall_error_max_m, error);
    ++result.occupied_voxels;
  }
  if (result.occupied_voxels > 0) result.wall_error_mean_m = sum / result.occupied_voxels;
  return result;
}

}  // namespace behaviorlib::nav
