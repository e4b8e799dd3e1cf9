#pragma once

// Frontiers: where exploration goes next. A horizontal slice of the
// occupancy map over an area is classified cell by cell (free, occupied,
// unknown); a frontier is a cluster of free cells that border unknown ones
// (Yamauchi, "A frontier-based approach for autonomous exploration", 1997).
//
//   MapSlice slice(map, {.min_m = {0, 0}, .max_m = {18, 10},
//                        .z_min_m = 1.1, .z_max_m = 1.4});
//   for (const Frontier& f : slice.frontiers(3)) ... f.centroid_m ...
//   double known = slice.census().knownFraction();
//
// A 2-D lidar sees the plane it scans: the slice should hold that plane.
// Cells outside the area are neither free nor unknown: the area's edge is
// not a frontier, so an exploration bounded by a building's outline ends
// when the building is known.

#include <Eigen/Core>
#include <cstddef>
#include <cstdint>
#include <vector>

#include "behaviorlib/navigation/occupancy_map.h"

namespace behaviorlib::nav {

struct SliceOptions {
  Eigen::Vector2d min_m{0, 0};  ///< lowest corner of the area (x, y)
  Eigen::Vector2d max_m{0, 0};  ///< highest corner
  double z_min_m = 0.0;         ///< the slice: voxels whose centre is between these heights
  double z_max_m = 0.0;
};

struct Frontier {
  std::vector<Eigen::Vector2d> cells_m;  ///< centres of its cells
  Eigen::Vector2d centroid_m{0, 0};
};

/// Cells of the area by state.
struct SliceCensus {
  size_t free = 0, occupied = 0, unknown = 0;
  /// Known (free or occupied) share of the area's cells, 0 .. 1.
  double knownFraction() const;
};

class MapSlice {
 public:
  enum class Cell : uint8_t { kUnknown, kFree, kOccupied };

  /// A column's cell is occupied when any voxel of the slice is occupied,
  /// free when none is and one is known free, unknown otherwise; an unknown
  /// cell with 5/8 of its neighbours known, one of them free, is a gap
  /// between two far rays or beside a wall and counts as free. The area is clipped to at most `max_cells`
  /// cells (the caller bounds the memory).
  MapSlice(const OccupancyMap& map, const SliceOptions& options, size_t max_cells = 4'000'000);

  int width() const { return width_; }
  int height() const { return height_; }
  Cell at(int ix, int iy) const { return cells_[static_cast<size_t>(iy) * width_ + ix]; }
  /// Centre of cell (ix, iy), metres.
  Eigen::Vector2d centre(int ix, int iy) const;
  /// The cell holding `p`, if inside the area.
  bool cellOf(const Eigen::Vector2d& p, int* ix, int* iy) const;

  /// Clusters (8-connected) of free cells with an unknown 4-neighbour, of
  /// at least `min_cells` cells, largest first.
  std::vector<Frontier> frontiers(size_t min_cells) const;
  SliceCensus census() const;

 private:
  Eigen::Vector2d origin_;
  double resolution_;
  int width_ = 0, height_ = 0;
  std::vector<Cell> cells_;
};

}  // namespace behaviorlib::nav
