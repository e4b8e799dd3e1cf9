#pragma once

// How much of a world's free space a saved map knows: the figure the room
// exploration application reports ("the mapped fraction of the building's
// free space").
//
//   absl::StatusOr<world::World> world = world::loadWorld("simulator/worlds/rooms.yaml");
//   octomap::OcTree map("building.bt");
//   MapCoverage c = measureCoverage(*world, map, {.height_m = 1.3});
//   double fraction = c.mappedFraction();
//
// The vehicles carry a plane (2-D) lidar, so the measure is a plan view at
// the scanning height: the building is the box around its walls (the
// world's `walls:`), cut into square cells of `cell_m`; a cell is free space
// when the world has no surface at its centre at `height_m`, and mapped when
// the map holds a free voxel within `band_m` above or below that point
// (the lidar's plane tilts with the vehicle). Cells inside walls and
// furniture are not free space and are not counted. The wall error is the
// mean distance from the map's occupied voxels in that band to the world's
// surfaces.

#include <octomap/OcTree.h>

#include <Eigen/Core>
#include <cstddef>
#include <vector>

#include "formats/world/world.h"

namespace behaviorlib::nav {

struct CoverageOptions {
  double height_m = 1.3;  ///< height of the plan view (world frame): flight altitude + lidar mount
  double band_m = 0.3;    ///< a free voxel this far above or below counts
  double cell_m = 0.1;    ///< plan-view cell edge
};

struct MapCoverage {
  size_t free_cells = 0;        ///< cells of the building that are free space at height_m
  size_t known_free_cells = 0;  ///< of those, the ones the map knows as free
  size_t occupied_cells = 0;    ///< of those, the ones the map marks occupied (wrongly)
  /// Occupied voxels of the map within band_m of height_m, inside the
  /// building's box, and their distance (centre to the world's nearest
  /// surface, 0 inside one; found to 5 mm, at most 64 m): how far the mapped walls are
  /// from the real ones.
  size_t occupied_voxels = 0;
  double wall_error_mean_m = 0.0;
  double wall_error_max_m = 0.0;
  /// Those voxels in plan view: one centre per cell_m cell (for plots).
  std::vector<Eigen::Vector2d> occupied_xy_m;
  Eigen::Vector2d building_min_m = Eigen::Vector2d::Zero();
  Eigen::Vector2d building_max_m = Eigen::Vector2d::Zero();
  double cell_m = 0.1;

  double mappedFraction() const {
    return free_cells == 0 ? 0.0 : static_cast<double>(known_free_cells) / free_cells;
  }
  double freeAreaM2() const { return free_cells * cell_m * cell_m; }
  double mappedAreaM2() const { return known_free_cells * cell_m * cell_m; }
};

/// The building's extent: the axis-aligned box around every wall of `world`
/// (each wall box's corners). Empty (min = max = 0) without walls.
void buildingExtent(const world::World& world, Eigen::Vector2d* min_m, Eigen::Vector2d* max_m);

/// Plan-view coverage of `world`'s building by `map` (see the file comment).
/// A world without walls covers nothing: free_cells is 0.
MapCoverage measureCoverage(const world::World& world, const octomap::OcTree& map,
                            const CoverageOptions& options = {});

}  // namespace behaviorlib::nav
