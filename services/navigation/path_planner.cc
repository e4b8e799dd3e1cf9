#include "navigation/path_planner.h"

#include <ompl/base/spaces/RealVectorStateSpace.h>
#include <ompl/geometric/PathSimplifier.h>
#include <ompl/geometric/SimpleSetup.h>
#include <ompl/geometric/planners/rrt/RRTConnect.h>
#include <ompl/util/Console.h>
#include <ompl/util/RandomNumbers.h>

#include <chrono>
#include <cmath>
#include <mutex>
#include <sstream>

namespace behaviorlib::nav {
namespace {

namespace ob = ompl::base;
namespace og = ompl::geometric;

std::string text(const Eigen::Vector3d& p) {
  std::ostringstream out;
  out.precision(3);
  out << "(" << p.x() << ", " << p.y() << ", " << p.z() << ")";
  return out.str();
}

bool inside(const Eigen::Vector3d& p, const PlanOptions& o) {
  return (p.array() >= o.bounds_min_m.array()).all() && (p.array() <= o.bounds_max_m.array()).all();
}

void quietOmpl() {
  static std::once_flag once;
  std::call_once(once, [] { ompl::msg::setLogLevel(ompl::msg::LOG_WARN); });
}

}  // namespace

void seedPlanner(std::uint32_t seed) {
  quietOmpl();
  ompl::RNG::setSeed(seed);
}

absl::StatusOr<PlannedPath> planPath(const OccupancyMap& map, const Eigen::Vector3d& start_m,
                                     const Eigen::Vector3d& goal_m, const PlanOptions& options) {
  quietOmpl();
  if (!start_m.allFinite() || !goal_m.allFinite()) {
    return absl::InvalidArgumentError("start and goal must be finite coordinates");
  }
  if (!inside(goal_m, options)) {
    return absl::InvalidArgumentError("goal " + text(goal_m) + " is outside the planning volume " +
                                      text(options.bounds_min_m) + " .. " +
                                      text(options.bounds_max_m));
  }
  const auto t0 = std::chrono::steady_clock::now();
  // One dense inflated grid per plan: thousands of checks, one lookup each.
  // Cells are judged by their centre: add half a cell diagonal of margin.
  const double margin = 0.5 * std::sqrt(3.0) * map.resolutionM();
  const InflatedGrid grid(map, options.bounds_min_m, options.bounds_max_m,
                          options.vehicle_radius_m + margin);
  const auto t_grid = std::chrono::steady_clock::now();
  if (grid.blocked(goal_m)) {
    return absl::InvalidArgumentError(
        "goal " + text(goal_m) + " is inside an obstacle: an occupied voxel is within " +
        std::to_string(options.vehicle_radius_m) + " m (the vehicle's radius)");
  }
  if (!inside(start_m, options)) {
    return absl::FailedPreconditionError("the vehicle at " + text(start_m) +
                                         " is outside the planning volume");
  }
  if (grid.blocked(start_m)) {
    return absl::FailedPreconditionError(
        "the vehicle at " + text(start_m) +
        " is closer to an obstacle than its radius: move it away first");
  }

  auto space = std::make_shared<ob::RealVectorStateSpace>(3);
  ob::RealVectorBounds bounds(3);
  for (int i = 0; i < 3; ++i) {
    bounds.setLow(i, options.bounds_min_m[i]);
    bounds.setHigh(i, options.bounds_max_m[i]);
  }
  space->setBounds(bounds);
  og::SimpleSetup setup(space);
  setup.setStateValidityChecker([&grid](const ob::State* state) {
    const double* v = state->as<ob::RealVectorStateSpace::StateType>()->values;
    return !grid.blocked(Eigen::Vector3d(v[0], v[1], v[2]));
  });
  const double extent = space->getMaximumExtent();
  setup.getSpaceInformation()->setStateValidityCheckingResolution(
      std::clamp(options.check_spacing_m / extent, 1e-4, 0.05));
  ob::ScopedState<> start(space), goal(space);
  for (int i = 0; i < 3; ++i) {
    start[i] = start_m[i];
    goal[i] = goal_m[i];
  }
  setup.setStartAndGoalStates(start, goal, 1e-3);
  setup.setPlanner(std::make_shared<og::RRTConnect>(setup.getSpaceInformation()));

  const ob::PlannerStatus solved = setup.solve(options.timeout_s);
  if (solved != ob::PlannerStatus::EXACT_SOLUTION) {
    return absl::NotFoundError("no path from " + text(start_m) + " to " + text(goal_m) +
                               " found within " + std::to_string(options.timeout_s) +
                               " s (the goal may be unreachable)");
  }
  if (options.shortcut_attempts > 0) {
    // Bounded work, not a time budget (simplifySolution(t) may use all of t).
    og::PathSimplifier simplifier(setup.getSpaceInformation());
    og::PathGeometric& raw = setup.getSolutionPath();
    simplifier.reduceVertices(raw);
    simplifier.shortcutPath(raw, options.shortcut_attempts);
  }
  const auto t1 = std::chrono::steady_clock::now();

  PlannedPath path;
  for (const ob::State* s : setup.getSolutionPath().getStates()) {
    const double* v = s->as<ob::RealVectorStateSpace::StateType>()->values;
    path.waypoints_m.emplace_back(v[0], v[1], v[2]);
  }
  for (size_t i = 1; i < path.waypoints_m.size(); ++i) {
    path.length_m += (path.waypoints_m[i] - path.waypoints_m[i - 1]).norm();
  }
  path.planning_time_s = std::chrono::duration<double>(t1 - t0).count();
  path.inflation_time_s = std::chrono::duration<double>(t_grid - t0).count();
  return path;
}

}  // namespace behaviorlib::nav
