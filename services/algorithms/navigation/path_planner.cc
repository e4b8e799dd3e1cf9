#include "behaviorlib/navigation/path_planner.h"

#include <ompl/base/spaces/RealVectorStateSpace.h>
#include <ompl/geometric/SimpleSetup.h>
#include <ompl/geometric/planners/rrt/RRTConnect.h>
#include <ompl/util/Console.h>
#include <ompl/util/RandomNumbers.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>
#include <mutex>
#include <optional>
#include <sstream>
#include <utility>
#include <vector>

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

// Points along the polyline, at most `step` apart, every vertex kept.
std::vector<Eigen::Vector3d> densify(const std::vector<Eigen::Vector3d>& path, double step) {
  std::vector<Eigen::Vector3d> out;
  if (path.empty()) return out;
  out.push_back(path.front());
  for (size_t i = 1; i < path.size(); ++i) {
    const Eigen::Vector3d d = path[i] - path[i - 1];
    const int n = std::max(1, static_cast<int>(std::ceil(d.norm() / step)));
    for (int k = 1; k <= n; ++k) out.push_back(path[i - 1] + d * (static_cast<double>(k) / n));
  }
  return out;
}

// Smallest clearance along the straight segment a-b, sampled every
// `spacing`; below `floor_m` (or blocked) it stops early and returns -1.
double segmentClearance(const InflatedGrid& grid, double radius, const Eigen::Vector3d& a,
                        const Eigen::Vector3d& b, double spacing, double floor_m) {
  const int n = std::max(1, static_cast<int>(std::ceil((b - a).norm() / spacing)));
  double least = std::numeric_limits<double>::infinity();
  for (int k = 0; k <= n; ++k) {
    const Eigen::Vector3d p = a + (b - a) * (static_cast<double>(k) / n);
    const double c = grid.clearanceM(p);
    if (grid.blocked(p, radius) || c < floor_m) return -1.0;
    least = std::min(least, c);
  }
  return least;
}

// Moves each interior point up the clearance field, a cell at a time,
// until it has `target_m` of clearance or can gain no more: in open space a
// point near an obstacle moves out to the target, in a passage narrower
// than that it moves to the passage's middle. A move that would leave a
// blocked segment to a neighbour is not made.
void pushAway(const InflatedGrid& grid, double radius, std::vector<Eigen::Vector3d>& points,
              double target_m, double resolution, double spacing) {
  const double h = resolution;
  const double step = resolution;
  for (size_t i = 1; i + 1 < points.size(); ++i) {
    Eigen::Vector3d p = points[i];
    double c = grid.clearanceM(p);
    for (int iteration = 0; iteration < 20 && c < target_m; ++iteration) {
      Eigen::Vector3d gradient;
      for (int axis = 0; axis < 3; ++axis) {
        Eigen::Vector3d d = Eigen::Vector3d::Zero();
        d[axis] = h;
        gradient[axis] = grid.clearanceM(p + d) - grid.clearanceM(p - d);
      }
      if (gradient.norm() < 1e-9) break;
      const Eigen::Vector3d next = p + gradient.normalized() * step;
      const double cn = grid.clearanceM(next);
      if (cn < c || grid.blocked(next, radius)) break;
      p = next;
      c = cn;
    }
    if (p == points[i]) continue;
    if (segmentClearance(grid, radius, points[i - 1], p, spacing, 0.0) >= 0.0 &&
        segmentClearance(grid, radius, p, points[i + 1], spacing, 0.0) >= 0.0) {
      points[i] = p;
    }
  }
}

// From each point, straight to the farthest later point whose segment
// keeps min(target, the least clearance of the points it replaces): the
// path is shortened without being pulled against a wall or a corner where
// the space allows more room.
std::vector<Eigen::Vector3d> pullString(const InflatedGrid& grid, double radius,
                                        const std::vector<Eigen::Vector3d>& points, double target_m,
                                        double spacing) {
  std::vector<Eigen::Vector3d> out;
  if (points.empty()) return out;
  std::vector<double> clearance(points.size());
  for (size_t k = 0; k < points.size(); ++k) clearance[k] = grid.clearanceM(points[k]);
  out.push_back(points.front());
  size_t i = 0;
  std::vector<double> least(points.size());
  while (i + 1 < points.size()) {
    least[i] = clearance[i];
    for (size_t j = i + 1; j < points.size(); ++j) least[j] = std::min(least[j - 1], clearance[j]);
    size_t chosen = i + 1;
    for (size_t j = points.size() - 1; j > i + 1; --j) {
      const double required = std::min(target_m, least[j]);
      if (segmentClearance(grid, radius, points[i], points[j], spacing, required - 1e-6) >= 0.0) {
        chosen = j;
        break;
      }
    }
    out.push_back(points[chosen]);
    i = chosen;
  }
  return out;
}

absl::Status checkEnds(const Eigen::Vector3d& start_m, const Eigen::Vector3d& goal_m,
                       const PlanOptions& options) {
  if (!start_m.allFinite() || !goal_m.allFinite()) {
    return absl::InvalidArgumentError("start and goal must be finite coordinates");
  }
  if (!inside(goal_m, options)) {
    return absl::InvalidArgumentError("goal " + text(goal_m) + " is outside the planning volume " +
                                      text(options.bounds_min_m) + " .. " +
                                      text(options.bounds_max_m));
  }
  return absl::OkStatus();
}

// The nearest point within options.escape_m of `start` that is clear at
// `bare`, inside the volume, reached by a straight move along which the
// clearance never falls below the start's; none when the start is inside an
// obstacle or no such point exists.
std::optional<Eigen::Vector3d> escapeFrom(const InflatedGrid& grid, const Eigen::Vector3d& start,
                                          double bare, const PlanOptions& options) {
  const double clearance = grid.clearanceM(start);
  if (!(clearance > 0.0)) return std::nullopt;
  const double floor = std::min(clearance, bare) - 1e-6;
  const double step = grid.resolutionM();
  const int reach = static_cast<int>(std::ceil(options.escape_m / step));
  std::vector<std::pair<double, Eigen::Vector3d>> candidates;
  for (int dz = -reach; dz <= reach; ++dz) {
    for (int dy = -reach; dy <= reach; ++dy) {
      for (int dx = -reach; dx <= reach; ++dx) {
        const Eigen::Vector3d offset = step * Eigen::Vector3d(dx, dy, dz);
        const double d = offset.norm();
        if (d > 0.0 && d <= options.escape_m) candidates.emplace_back(d, start + offset);
      }
    }
  }
  std::stable_sort(candidates.begin(), candidates.end(),
                   [](const auto& a, const auto& b) { return a.first < b.first; });
  for (const auto& [d, p] : candidates) {
    if (!inside(p, options) || grid.blocked(p, bare)) continue;
    const int n = std::max(1, static_cast<int>(std::ceil(d / (0.5 * step))));
    bool away = true;
    for (int i = 1; i <= n && away; ++i) {
      away = grid.clearanceM(start + (p - start) * (static_cast<double>(i) / n)) >= floor;
    }
    if (away) return p;
  }
  return std::nullopt;
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

double cellMarginM(double resolution_m) { return 0.5 * std::sqrt(3.0) * resolution_m; }

absl::StatusOr<PlannedPath> planPath(const OccupancyMap& map, const Eigen::Vector3d& start_m,
                                     const Eigen::Vector3d& goal_m, const PlanOptions& options) {
  if (absl::Status s = checkEnds(start_m, goal_m, options); !s.ok()) return s;
  const auto t0 = std::chrono::steady_clock::now();
  // One dense inflated grid per plan: thousands of checks, one lookup each.
  const InflatedGrid grid(map, options.bounds_min_m, options.bounds_max_m,
                          options.vehicle_radius_m + cellMarginM(map.resolutionM()) +
                              std::max(0.0, options.uncertainty_margin_m));
  const double inflation_s =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  absl::StatusOr<PlannedPath> path = planPath(grid, start_m, goal_m, options);
  if (path.ok()) {
    path->inflation_time_s = inflation_s;
    path->planning_time_s += inflation_s;
  }
  return path;
}

absl::StatusOr<PlannedPath> planPath(const InflatedGrid& grid, const Eigen::Vector3d& start_m,
                                     const Eigen::Vector3d& goal_m, const PlanOptions& options) {
  quietOmpl();
  if (absl::Status s = checkEnds(start_m, goal_m, options); !s.ok()) return s;
  const auto t0 = std::chrono::steady_clock::now();
  const double resolution = grid.resolutionM();
  const double bare = options.vehicle_radius_m + cellMarginM(resolution);
  if (grid.blocked(goal_m, bare)) {
    return absl::InvalidArgumentError(
        "goal " + text(goal_m) + " is inside an obstacle: an occupied voxel is within " +
        std::to_string(options.vehicle_radius_m) + " m (the vehicle's radius)");
  }
  if (!inside(start_m, options)) {
    return absl::FailedPreconditionError("the vehicle at " + text(start_m) +
                                         " is outside the planning volume");
  }
  if (grid.blocked(start_m, bare)) {
    const std::optional<Eigen::Vector3d> away =
        options.escape_m > 0.0 ? escapeFrom(grid, start_m, bare, options) : std::nullopt;
    if (!away) {
      return absl::FailedPreconditionError(
          "the vehicle at " + text(start_m) +
          " is closer to an obstacle than its radius: move it away first" +
          (options.escape_m > 0.0
               ? " (no point within " + std::to_string(options.escape_m) + " m is clear of it)"
               : std::string()));
    }
    // Away from the obstacle first, then planned from there.
    PlanOptions from_there = options;
    from_there.escape_m = 0.0;
    absl::StatusOr<PlannedPath> path = planPath(grid, *away, goal_m, from_there);
    if (!path.ok()) return path;
    path->waypoints_m.insert(path->waypoints_m.begin(), start_m);
    path->escape_length_m = (*away - start_m).norm();
    path->length_m += path->escape_length_m;
    path->min_clearance_m =
        std::min(path->min_clearance_m, grid.clearanceM(start_m) - options.vehicle_radius_m);
    return path;
  }
  // The uncertainty margin where a passage allows it: kept when the start,
  // the goal and a chain of cells between them are clear with it.
  const double margin = std::max(0.0, options.uncertainty_margin_m);
  double radius = bare + margin;
  if (margin > 0.0 && (grid.blocked(goal_m, radius) || grid.blocked(start_m, radius) ||
                       !grid.connected(start_m, goal_m, radius))) {
    radius = bare;
  }

  auto space = std::make_shared<ob::RealVectorStateSpace>(3);
  ob::RealVectorBounds bounds(3);
  for (int i = 0; i < 3; ++i) {
    bounds.setLow(i, options.bounds_min_m[i]);
    bounds.setHigh(i, options.bounds_max_m[i]);
  }
  space->setBounds(bounds);
  og::SimpleSetup setup(space);
  setup.setStateValidityChecker([&grid, radius](const ob::State* state) {
    const double* v = state->as<ob::RealVectorStateSpace::StateType>()->values;
    return !grid.blocked(Eigen::Vector3d(v[0], v[1], v[2]), radius);
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
  og::PathGeometric& solution = setup.getSolutionPath();
  if (options.shorten) {
    // RRT-Connect's path wanders: it can pass the goal and come back through
    // space the map has not seen (which counts as free). The string pulling
    // below keeps a path's detours, since it only drops points it can see
    // past; OMPL's simplifier first joins vertices that see each other.
    const og::PathSimplifierPtr& simplifier = setup.getPathSimplifier();
    simplifier->reduceVertices(solution);
    simplifier->shortcutPath(solution);
  }
  std::vector<Eigen::Vector3d> raw;
  for (const ob::State* s : solution.getStates()) {
    const double* v = s->as<ob::RealVectorStateSpace::StateType>()->values;
    raw.emplace_back(v[0], v[1], v[2]);
  }
  const double spacing = options.check_spacing_m;
  PlannedPath path;
  if (options.shorten) {
    // The clearance sought includes the margin even where it was dropped:
    // through a narrow passage the path keeps to its middle.
    const double target = bare + margin + std::max(0.0, options.preferred_clearance_m);
    std::vector<Eigen::Vector3d> dense = densify(raw, resolution);
    pushAway(grid, radius, dense, target, resolution, spacing);
    path.waypoints_m = pullString(grid, radius, dense, target, spacing);
  } else {
    path.waypoints_m = std::move(raw);
  }
  const auto t1 = std::chrono::steady_clock::now();

  path.min_clearance_m = std::numeric_limits<double>::infinity();
  for (size_t i = 1; i < path.waypoints_m.size(); ++i) {
    path.length_m += (path.waypoints_m[i] - path.waypoints_m[i - 1]).norm();
    const double c =
        segmentClearance(grid, radius, path.waypoints_m[i - 1], path.waypoints_m[i], spacing, 0.0);
    path.min_clearance_m = std::min(path.min_clearance_m, c - bare);
  }
  path.planning_time_s = std::chrono::duration<double>(t1 - t0).count();
  path.inflation_radius_m = radius;
  path.margin_kept = radius > bare || margin == 0.0;
  return path;
}

}  // namespace behaviorlib::nav
