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
// The map is inflated by the vehicle's radius plus half a voxel diagonal
// (cells are judged by their centres), and by uncertainty_margin_m (the
// pose estimate's uncertainty) where the space allows: when no passage
// joins start and goal with the margin but one does without it, the plan
// keeps the bare inflation (PlannedPath::margin_kept is false) and the
// shortened path still keeps the margin's clearance wherever it can.
//
// Errors: INVALID_ARGUMENT for a goal outside the planning volume or inside
// an obstacle (too close to an occupied voxel for the vehicle's radius);
// FAILED_PRECONDITION for a start in collision; NOT_FOUND when no path was
// found within the time limit (the goal may be unreachable).

#include <Eigen/Core>
#include <cstdint>
#include <vector>

#include "absl/status/statusor.h"
#include "behaviorlib/navigation/occupancy_map.h"

namespace behaviorlib::nav {

struct PlanOptions {
  double vehicle_radius_m = 0.3;
  double timeout_s = 0.5;
  Eigen::Vector3d bounds_min_m{-50, -50, 0.3};
  Eigen::Vector3d bounds_max_m{50, 50, 5.0};
  /// Spacing of the collision checks along a motion (m).
  double check_spacing_m = 0.05;
  /// Shorten the planner's raw path: from each waypoint, straight to the
  /// farthest point of the raw path that can be reached without passing
  /// closer to an obstacle than the preferred clearance (or than the raw
  /// path itself passed there, in a passage narrower than that). false keeps
  /// the raw path.
  bool shorten = true;
  /// Distance beyond the vehicle's radius that the shortened path keeps from
  /// occupied voxels where the space allows it (m). A shortcut that hugs a
  /// wall or a corner at the bare radius leaves no room for the controller's
  /// tracking error, nor for the unseen part of an obstacle seen from one
  /// side (unknown space counts as free).
  double preferred_clearance_m = 0.2;
  /// Inflation beyond the radius for the pose estimate's uncertainty, where
  /// a passage is wide enough for it (m).
  double uncertainty_margin_m = 0.0;
  /// A start closer to an obstacle than the vehicle's radius (a vehicle
  /// that ended a leg near a wall the map had not shown when it was
  /// planned): 0 refuses it (FAILED_PRECONDITION, "move it away first").
  /// Otherwise the path begins with a straight move to the nearest point
  /// within this distance (m) that is clear at the radius, along which the
  /// vehicle never comes closer to an obstacle than it already is.
  double escape_m = 0.0;
};

struct PlannedPath {
  std::vector<Eigen::Vector3d> waypoints_m;  ///< start first, goal last
  double length_m = 0.0;
  double planning_time_s = 0.0;   ///< all of it, wall time
  double inflation_time_s = 0.0;  ///< of which building the inflated grid
  /// Smallest distance beyond the vehicle's radius between the path and an
  /// occupied voxel, sampled along it (m; infinity with none in reach).
  double min_clearance_m = 0.0;
  /// The radius the map was inflated by for the plan (m): the vehicle's,
  /// half a voxel diagonal, and the uncertainty margin if kept.
  double inflation_radius_m = 0.0;
  /// Whether the uncertainty margin was kept everywhere (false: a passage
  /// on the way is too narrow for it).
  bool margin_kept = true;
  /// Length of the first move away from an obstacle too near the start
  /// (PlanOptions::escape_m; m, 0 when the start was clear).
  double escape_length_m = 0.0;
};

/// Half a voxel diagonal: a point is judged by its cell's centre.
double cellMarginM(double resolution_m);

absl::StatusOr<PlannedPath> planPath(const OccupancyMap& map, const Eigen::Vector3d& start_m,
                                     const Eigen::Vector3d& goal_m, const PlanOptions& options);
/// The same on a grid already built over options' bounds with a radius of
/// at least vehicle_radius_m + cellMarginM + uncertainty_margin_m.
absl::StatusOr<PlannedPath> planPath(const InflatedGrid& grid, const Eigen::Vector3d& start_m,
                                     const Eigen::Vector3d& goal_m, const PlanOptions& options);

/// Seeds OMPL's random generator (once, before the first plan) so that plans
/// are reproducible in tests.
void seedPlanner(std::uint32_t seed);

}  // namespace behaviorlib::nav
