#pragma once

// WallColumns: what a plane (2-D) lidar's hits say about the space above and
// below its plane. The buildings it maps have vertical walls, so each hit
// raises its voxel's whole column (column_min_z_m .. column_max_z_m) in the
// map, once; the planner, which checks a sphere of the vehicle's radius, then
// sees the wall at every height the vehicle may fly. A hit above the planning
// heights (a door's lintel seen by a tilted vehicle) stays a voxel.
//
// A column falls when the voxel whose hit raised it has become certainly
// free (OctoMap's clamping bound: about seven rays crossed it for every hit):
// the plane saw through it many times, so the hit was wrong (a scan placed
// with a poor pose, noise on a door jamb's face) and the rest of the column,
// which no ray of a plane lidar crosses, never was there. Such a column in a
// doorway closed the door for good. Falling as soon as the voxel was merely
// not occupied was tried: rays grazing a wall made holes in it.
//
//   WallColumns columns({.resolution_m = 0.1, .min_z_m = 0.0, .max_z_m = 3.0,
//                        .max_hit_z_m = 1.8});
//   map.insertScan(origin, hits, misses);
//   columns.afterScan(map, hits);
//
// Not thread-safe: the caller serializes it with the map.

#include <Eigen/Core>
#include <cstdint>
#include <unordered_map>
#include <vector>

#include "behaviorlib/navigation/occupancy_map.h"

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
  /// whose column is not raised yet, then fells every column whose raising
  /// voxel is certainly free.
  void afterScan(OccupancyMap& map, const std::vector<Eigen::Vector3d>& hits_m);
  void clear() { columns_.clear(); }
  size_t standing() const { return columns_.size(); }

 private:
  WallColumnSettings settings_;
  // xy cell -> the centre of the voxel whose hit raised the column.
  std::unordered_map<uint64_t, Eigen::Vector3d> columns_;
};

}  // namespace behaviorlib::nav
