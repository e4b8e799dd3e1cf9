#include "behaviorlib/navigation/unknown_space_planner.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <limits>
#include <queue>
#include <string>
#include <utility>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "behaviorlib/navigation/frontiers.h"
#include "behaviorlib/navigation/path_planner.h"

namespace behaviorlib::nav {
namespace {

constexpr double kLongestSegmentM = 15.0;  // of the shortened path

std::string point(const Eigen::Vector3d& p) {
  return absl::StrFormat("(%.2f, %.2f, %.2f)", p.x(), p.y(), p.z());
}

// The area's cells with what the search needs of each.
class Cells {
 public:
  Cells(const OccupancyMap& map, const UnknownSpacePlanOptions& o)
      : slice_(map,
               {.min_m = o.bounds_min_m.head<2>(),
                .max_m = o.bounds_max_m.head<2>(),
                .z_min_m = o.slice_z_min_m,
                .z_max_m = o.slice_z_max_m},
               o.max_cells),
        altitude_m_(o.altitude_m),
        bare_m_(o.vehicle_radius_m + cellMarginM(map.resolutionM())),
        grid_(map, {o.bounds_min_m.x(), o.bounds_min_m.y(), o.altitude_m - map.resolutionM()},
              {o.bounds_max_m.x(), o.bounds_max_m.y(), o.altitude_m + map.resolutionM()},
              bare_m_ + o.preferred_clearance_m) {
    const size_t n = static_cast<size_t>(slice_.width()) * slice_.height();
    clearance_.resize(n);
    unknown_.resize(n);
    for (int iy = 0; iy < slice_.height(); ++iy) {
      for (int ix = 0; ix < slice_.width(); ++ix) {
        const size_t i = index(ix, iy);
        clearance_[i] = grid_.clearanceM(at(ix, iy));
        unknown_[i] = slice_.at(ix, iy) == MapSlice::Cell::kUnknown;
      }
    }
  }

  int width() const { return slice_.width(); }
  int height() const { return slice_.height(); }
  size_t index(int ix, int iy) const { return static_cast<size_t>(iy) * slice_.width() + ix; }
  Eigen::Vector3d at(int ix, int iy) const {
    const Eigen::Vector2d q = slice_.centre(ix, iy);
    return {q.x(), q.y(), altitude_m_};
  }
  bool cellOf(const Eigen::Vector3d& p, int* ix, int* iy) const {
    return slice_.cellOf(p.head<2>(), ix, iy);
  }
  /// Distance from the cell's centre to the nearest obstacle (m).
  double clearance(size_t i) const { return clearance_[i]; }
  bool blocked(size_t i) const { return clearance_[i] <= bare_m_; }
  bool unknown(size_t i) const { return unknown_[i]; }
  double bareM() const { return bare_m_; }
  /// Clearance at any point (its cell's), through the inflated grid.
  double clearanceAt(const Eigen::Vector3d& p) const { return grid_.clearanceM(p); }
  bool unknownAt(const Eigen::Vector3d& p) const {
    int ix = 0, iy = 0;
    return cellOf(p, &ix, &iy) && unknown_[index(ix, iy)];
  }

 private:
  MapSlice slice_;
  double altitude_m_;
  double bare_m_;
  InflatedGrid grid_;
  std::vector<double> clearance_;
  std::vector<bool> unknown_;
};

}  // namespace

absl::StatusOr<UnknownSpacePlan> planThroughUnknown(const OccupancyMap& map,
                                                    const Eigen::Vector3d& start_m,
                                                    const Eigen::Vector3d& goal_m,
                                                    const UnknownSpacePlanOptions& o) {
  const auto t0 = std::chrono::steady_clock::now();
  const Eigen::Vector3d& lo = o.bounds_min_m;
  const Eigen::Vector3d& hi = o.bounds_max_m;
  if (!lo.allFinite() || !hi.allFinite() || (lo.array() >= hi.array()).any()) {
    return absl::InvalidArgumentError("the bounds " + point(lo) + " .. " + point(hi) +
                                      " are not ordered");
  }
  const double res = map.resolutionM();
  const double cells = std::ceil((hi.x() - lo.x()) / res) * std::ceil((hi.y() - lo.y()) / res);
  if (cells > static_cast<double>(o.max_cells)) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "the area %s .. %s holds %.0f cells of %.2f m, more than the %d a plan may search",
        point(lo), point(hi), cells, res, o.max_cells));
  }
  const auto inside = [&](const Eigen::Vector3d& p) {
    return p.x() >= lo.x() && p.x() <= hi.x() && p.y() >= lo.y() && p.y() <= hi.y();
  };
  if (!goal_m.allFinite() || !inside(goal_m)) {
    return absl::InvalidArgumentError("the goal " + point(goal_m) + " lies outside the area " +
                                      point(lo) + " .. " + point(hi));
  }
  if (!start_m.allFinite() || !inside(start_m)) {
    return absl::InvalidArgumentError("the start " + point(start_m) + " lies outside the area " +
                                      point(lo) + " .. " + point(hi));
  }
  const Cells c(map, o);
  int sx = 0, sy = 0, gx = 0, gy = 0;
  if (!c.cellOf(start_m, &sx, &sy) || !c.cellOf(goal_m, &gx, &gy)) {
    return absl::InvalidArgumentError("the start or the goal lies outside the area's cells");
  }
  const size_t start = c.index(sx, sy), goal = c.index(gx, gy);
  if (c.blocked(goal)) {
    return absl::NotFoundError(absl::StrFormat(
        "the goal %s is unreachable: it lies within %.2f m of an obstacle seen (the vehicle's "
        "radius)",
        point(goal_m), o.vehicle_radius_m));
  }
  const Eigen::Vector3d start_cell = c.at(sx, sy);
  const double start_clearance = c.clearance(start);
  // A blocked cell may be entered only while escaping from a start that is
  // too near an obstacle: near the start, never nearer the obstacle.
  const auto enterable = [&](size_t from, size_t to, int tx, int ty) {
    if (!c.blocked(to)) return true;
    return c.blocked(from) && (c.at(tx, ty) - start_cell).norm() <= o.escape_m &&
           c.clearance(to) >= std::min(c.clearance(from), start_clearance) - 1e-9;
  };
  const auto step_cost = [&](size_t to, double length) {
    double factor = c.unknown(to) ? o.unknown_cost : 1.0;
    const double beyond = c.clearance(to) - c.bareM();
    if (beyond < o.preferred_clearance_m) {
      factor += o.clearance_cost * (1.0 - std::max(0.0, beyond) / o.preferred_clearance_m);
    }
    return length * factor;
  };

  // A* over the cells, 8-connected; the straight-line distance is the
  // heuristic (every step costs at least its length).
  const int w = c.width(), h = c.height();
  const size_t n = static_cast<size_t>(w) * h;
  constexpr double kInf = std::numeric_limits<double>::infinity();
  std::vector<double> g(n, kInf);
  std::vector<uint32_t> parent(n, UINT32_MAX);
  std::vector<bool> closed(n, false);
  using Entry = std::pair<double, size_t>;
  std::priority_queue<Entry, std::vector<Entry>, std::greater<>> open;
  const Eigen::Vector3d goal_cell = c.at(gx, gy);
  const auto heuristic = [&](int ix, int iy) { return (c.at(ix, iy) - goal_cell).norm(); };
  g[start] = 0;
  open.emplace(heuristic(sx, sy), start);
  size_t expanded = 0;
  while (!open.empty()) {
    const size_t i = open.top().second;
    open.pop();
    if (closed[i]) continue;
    closed[i] = true;
    ++expanded;
    if (i == goal) break;
    const int x = static_cast<int>(i % w), y = static_cast<int>(i / w);
    for (int dy = -1; dy <= 1; ++dy) {
      for (int dx = -1; dx <= 1; ++dx) {
        if (dx == 0 && dy == 0) continue;
        const int nx = x + dx, ny = y + dy;
        if (nx < 0 || ny < 0 || nx >= w || ny >= h) continue;
        const size_t j = c.index(nx, ny);
        if (closed[j] || !enterable(i, j, nx, ny)) continue;
        const double cost = g[i] + step_cost(j, res * ((dx != 0 && dy != 0) ? M_SQRT2 : 1.0));
        if (cost < g[j]) {
          g[j] = cost;
          parent[j] = static_cast<uint32_t>(i);
          open.emplace(cost + heuristic(nx, ny), j);
        }
      }
    }
  }
  if (!closed[goal]) {
    return absl::NotFoundError(absl::StrFormat(
        "the goal %s is unreachable: no way within the area %s .. %s for a vehicle of radius "
        "%.2f m, with unknown space counted as free (blocked on every side seen so far; %d of "
        "%d cells reached)",
        point(goal_m), point(lo), point(hi), o.vehicle_radius_m, expanded, n));
  }

  // The cells' path, start to goal.
  std::vector<size_t> chain;
  for (size_t i = goal; i != start; i = parent[i]) chain.push_back(i);
  chain.push_back(start);
  std::reverse(chain.begin(), chain.end());
  std::vector<Eigen::Vector3d> raw;
  raw.reserve(chain.size());
  for (size_t i : chain) raw.push_back(c.at(static_cast<int>(i % w), static_cast<int>(i / w)));
  raw.front() = Eigen::Vector3d(start_m.x(), start_m.y(), o.altitude_m);
  raw.back() = Eigen::Vector3d(goal_m.x(), goal_m.y(), o.altitude_m);

  // Shortened: from each kept point, straight to the farthest point of the
  // raw path reachable without passing nearer an obstacle than the preferred
  // clearance, or than the raw path itself passed between the two.
  const double step = 0.5 * res;
  const double preferred = c.bareM() + o.preferred_clearance_m;
  const auto clear = [&](const Eigen::Vector3d& a, const Eigen::Vector3d& b, double needed) {
    const double length = (b - a).norm();
    for (double s = 0; s <= length; s += step) {
      const Eigen::Vector3d p = a + (b - a) * (length > 0 ? s / length : 0.0);
      const double cl = c.clearanceAt(p);
      if (cl < needed && !((p - start_cell).norm() <= o.escape_m && cl >= start_clearance)) {
        return false;
      }
    }
    return true;
  };
  std::vector<Eigen::Vector3d> path{raw.front()};
  size_t from = 0;
  while (from + 1 < raw.size()) {
    size_t best = from + 1;
    double passed = kInf;  // the raw path's least clearance from `from` on
    for (size_t to = from + 1; to < raw.size(); ++to) {
      // Bounded (the work is quadratic in a segment's cells): the tracker
      // stops at every waypoint, so the cap is long.
      if ((raw[to] - raw[from]).norm() > kLongestSegmentM) break;
      passed = std::min(passed, c.clearanceAt(raw[to]));
      if (clear(raw[from], raw[to], std::min(preferred, passed))) best = to;
    }
    path.push_back(raw[best]);
    from = best;
  }

  UnknownSpacePlan plan;
  plan.expanded_cells = expanded;
  plan.cost = g[goal];
  plan.min_clearance_m = kInf;
  for (size_t i = 1; i < path.size(); ++i) {
    const double length = (path[i] - path[i - 1]).norm();
    plan.length_m += length;
    for (double s = 0; s < length; s += step) {
      const Eigen::Vector3d p = path[i - 1] + (path[i] - path[i - 1]) * (s / length);
      if (c.unknownAt(p)) plan.unknown_m += std::min(step, length - s);
      plan.min_clearance_m = std::min(plan.min_clearance_m, c.clearanceAt(p) - o.vehicle_radius_m);
    }
  }
  if (plan.unknown_m > o.max_unknown_m) {
    return absl::NotFoundError(absl::StrFormat(
        "the goal %s is unreachable within max_unknown_m: the best path crosses %.1f m of "
        "unknown space (max_unknown_m %.1f)",
        point(goal_m), plan.unknown_m, o.max_unknown_m));
  }
  plan.waypoints_m = std::move(path);
  plan.planning_time_s =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  return plan;
}

}  // namespace behaviorlib::nav
