#pragma once

// planThroughUnknown(): NAVIGATE_TO's planner (decision 48). It plans in the
// horizontal plane of the flight altitude, over the cells of an area (the
// activation's bounds), with unknown space counted as free but dearer than
// known free space: a plan may lead into space the map has not seen, and it
// prefers the space it has (Nav2's planner with allow_unknown does the same).
//
//   UnknownSpacePlanOptions options;
//   options.bounds_min_m = {0, 0, 0.5};
//   options.bounds_max_m = {18, 10, 1.6};
//   options.altitude_m = 1.2;
//   options.slice_z_min_m = 1.25;  // the lidar's plane, where it sees
//   options.slice_z_max_m = 1.55;
//   absl::StatusOr<UnknownSpacePlan> plan = planThroughUnknown(map, start, goal, options);
//
// The search is A* over the area's cells, 8-connected, on the map inflated
// by the vehicle's radius (InflatedGrid: obstacles at every height of the
// vehicle's sphere count). A step costs its length, times unknown_cost when
// it enters a cell the map has not seen (MapSlice: unknown in the plane),
// plus a penalty that grows as the cell comes nearer the obstacles than the
// preferred clearance. The cells' path is then shortened: from each point,
// straight to the farthest point of the path the vehicle can reach without
// passing nearer the obstacles than the preferred clearance (or than the
// path itself passed there).
//
// Unlike planPath (OMPL's RRT-Connect in 3-D), the result is the least-cost
// path of the grid: the same map gives the same path, a goal that no chain
// of cells reaches is unreachable for certain (on that map, with unknown
// space free), and a plan takes milliseconds, so the behavior can plan again
// whenever the map changes.
//
// Errors: INVALID_ARGUMENT for bounds not ordered, an area above max_cells,
// or a goal outside the area; NOT_FOUND when the goal is unreachable (no
// chain of cells joins it to the start: blocked on every side seen so far,
// or within the vehicle's radius of an obstacle) or when every path needs
// more than max_unknown_m of unknown space.

#include <Eigen/Core>
#include <cstddef>
#include <vector>

#include "absl/status/statusor.h"
#include "behaviorlib/navigation/occupancy_map.h"

namespace behaviorlib::nav {

struct UnknownSpacePlanOptions {
  double vehicle_radius_m = 0.35;
  /// The area (x, y) and the heights whose obstacles count (z).
  Eigen::Vector3d bounds_min_m{0, 0, 0.5};
  Eigen::Vector3d bounds_max_m{0, 0, 1.6};
  /// The path's height (m), inside the bounds' heights.
  double altitude_m = 1.2;
  /// The slice that tells unknown from known: the plane the lidar sees.
  double slice_z_min_m = 1.25;
  double slice_z_max_m = 1.55;
  /// Cost of a metre through unknown space, in metres of known free space.
  double unknown_cost = 1.5;
  /// Plans that need more unknown space than this (m) are refused.
  double max_unknown_m = 50.0;
  /// Distance beyond the radius the path keeps from obstacles where it can (m).
  double preferred_clearance_m = 0.2;
  /// Extra cost per metre of a cell right at the radius (falling to 0 at the
  /// preferred clearance).
  double clearance_cost = 2.0;
  /// A start nearer an obstacle than the radius (a wall seen late): the path
  /// may first move away from it through cells within this distance (m) of
  /// the start, never nearer the obstacle than the start is.
  double escape_m = 0.7;
  /// Largest area, in cells of the map's resolution (the memory a request
  /// can take).
  size_t max_cells = 1'000'000;
};

struct UnknownSpacePlan {
  std::vector<Eigen::Vector3d> waypoints_m;  ///< start first, goal last
  double length_m = 0.0;
  /// Length of the path through cells the map has not seen (m).
  double unknown_m = 0.0;
  /// The search's cost of the path (m of known free space).
  double cost = 0.0;
  double planning_time_s = 0.0;  ///< wall time
  /// Smallest distance beyond the radius between the path and an obstacle,
  /// sampled along it (m; infinity with none in reach).
  double min_clearance_m = 0.0;
  size_t expanded_cells = 0;
};

absl::StatusOr<UnknownSpacePlan> planThroughUnknown(const OccupancyMap& map,
                                                    const Eigen::Vector3d& start_m,
                                                    const Eigen::Vector3d& goal_m,
                                                    const UnknownSpacePlanOptions& options);

}  // namespace behaviorlib::nav
