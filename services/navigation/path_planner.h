#pragma once

// planPath(): GENERATE_PATH_WITH_OCCUPANCY_GRID's planner. OMPL's RRT-Connect
// in the 3-D box of the planning volume, every state and motion checked
// against the occupancy map for a sphere of the vehicle's radius; the path
// is then shortened (OMPL's simplifier) and returned as waypoints.
//
//   PlanOptions options;
//   options.bounds_min_m = {0, 0, 0.5};
//   options.bounds_max_m = {18, 10, 2.5};
//   absl::StatusOr<PlannedPath> path = planPath(map, start, goal, options);
//
// Errors: INVALID_ARGUMENT for a goal outside the planning volume or inside
// an obstacle (too close to an occupied voxel for the vehicle's radius);
// FAILED_PRECONDITION for a start in collision; NOT_FOUND when no path was
// found within the time limit (the goal may be unreachable).

#include <Eigen/Core>
#include <cstdint>
#include <vector>

#include "absl/status/statusor.h"
#include "navigation/occupancy_map.h"

namespace behaviorlib::nav {

struct PlanOptions {
  double vehicle_radius_m = 0.3;
  double timeout_s = 0.5;
  Eigen::Vector3d bounds_min_m{-50, -50, 0.3};
  Eigen::Vector3d bounds_max_m{50, 50, 5.0};
  /// Spacing of the collision checks along a motion (m).
  double check_spacing_m = 0.05;
  /// Shortcutting attempts when shortening the path (OMPL's PathSimplifier:
  /// vertex reduction, then random shortcuts); 0 keeps the raw path.
  unsigned int shortcut_attempts = 100;
};

struct PlannedPath {
  std::vector<Eigen::Vector3d> waypoints_m;  ///< start first, goal last
  double length_m = 0.0;
  double planning_time_s = 0.0;   ///< all of it, wall time
  double inflation_time_s = 0.0;  ///< of which building the inflated grid
};

absl::StatusOr<PlannedPath> planPath(const OccupancyMap& map, const Eigen::Vector3d& start_m,
                                     const Eigen::Vector3d& goal_m, const PlanOptions& options);

/// Seeds OMPL's random generator (once, before the first plan) so that plans
/// are reproducible in tests.
void seedPlanner(std::uint32_t seed);

}  // namespace behaviorlib::nav
