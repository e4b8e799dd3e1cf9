#include "simulator/tools/map_coverage.h"

#include <algorithm>
#include <cmath>
#include <limits>

namespace behaviorlib::nav {

void buildingExtent(const sim::World& world, Eigen::Vector2d* min_m, Eigen::Vector2d* max_m) {
  constexpr double kInf = std::numeric_limits<double>::infinity();
  Eigen::Vector2d lo(kInf, kInf), hi(-kInf, -kInf);
  for (const sim::Box& box : world.boxes()) {
    if (box.kind != sim::Box::Kind::kWall) continue;
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

MapCoverage measureCoverage(const sim::World& world, const octomap::OcTree& map,
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
  return result;
}

}  // namespace behaviorlib::nav
