#pragma once

// WallColumns: what a plane (2-D) lidar's hits say about the space above and
// below its plane. The buildings it maps have vertical walls, so each hit
// raises its voxel's whole column (column_min_z_m .. column_max_z_m) in the
// map, once; the planner, which checks a sphere of the vehicle's radius, then
// sees the wall at every height the vehicle may fly. A hit above the planning
// heights (a door's lintel seen by a tilted vehicle) stays a voxel.
//
// A column never falls. Letting it fall once later rays cleared the voxel
// that raised it was tried (a noisy hit on a door jamb's face can raise a
// column in the doorway): rays that graze a wall clear its face voxels too,
// and the fallen columns left holes in walls that a plan went through.
//
//   WallColumns columns({.resolution_m = 0.1, .min_z_m = 0.0, .max_z_m = 3.0,
//                        .max_hit_z_m = 1.8});
//   map.insertScan(origin, hits, misses);
//   columns.afterScan(map, hits);
//
// Not thread-safe: the caller serializes it with the map.

#include <Eigen/Core>
#include <cstdint>
#include <unordered_set>
#include <vector>

#include "navigation/occupancy_map.h"

namespace behaviorlib::nav {

struct WallColumnSettings {
  double resolution_m = 0.1;  ///< the map's
  double min_z_m = 0.0;       ///< a column runs from here ...
  double max_z_m = 3.0;       ///< ... to here
  /// A hit above this height (a door's lintel, a ceiling, seen by a tilted
  /// vehicle) stays a voxel: a column would close the door below it.
  double max_hit_z_m = 1.8;
};

class WallColumns {
 public:
  explicit WallColumns(WallColumnSettings settings) : settings_(settings) {}

  /// After a scan was inserted into `map`: raises the column of each hit
  /// whose column is not raised yet.
  void afterScan(OccupancyMap& map, const std::vector<Eigen::Vector3d>& hits_m);
  void clear() { columns_.clear(); }
  size_t standing() const { return columns_.size(); }

 private:
  WallColumnSettings settings_;
  std::unordered_set<uint64_t> columns_;  // xy cells raised
};

}  // namespace behaviorlib::nav
