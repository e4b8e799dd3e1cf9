#include "behaviorlib/navigation_with_lidar/explore_behavior.h"

#include <algorithm>
#include <cmath>
#include <deque>
#include <limits>
#include <sstream>

#include "behaviorlib/flight_common/flight_support.h"
#include "behaviorlib/motion_behaviors/motion_messages.h"
#include "behaviorlib/navigation/frontiers.h"
#include "behaviorlib/navigation/path_planner.h"
#include "behaviorlib/navigation_with_lidar/lidar_flight.h"

namespace behaviorlib::nav {
namespace {

using flight::fixed2;

using motion_behaviors::pointText;
using motion_behaviors::toEigen;
using motion_behaviors::toProto;

std::string percent(double fraction) {
  std::ostringstream out;
  out.setf(std::ios::fixed);
  out.precision(1);
  out << 100.0 * fraction << " %";
  return out.str();
}

constexpr double kArrivedM = 0.3;        // a leg ends this close to its target
constexpr double kGivenUpM = 0.5;        // a target given up rules out those this close
constexpr int kCandidatesPerChoice = 4;  // plans tried per choice
constexpr uint32_t kChoiceRetries = 3;   // choices again when every plan failed

}  // namespace

ExploreBehavior::ExploreBehavior(LidarMapper& mapper, flight::Vehicle& vehicle,
                                 motion_behaviors::MotionLink& link)
    : ReferenceBehavior(vehicle, link, Duration::zero()), mapper_(mapper) {}

absl::Status ExploreBehavior::onConfigure(const config::v1::ExploreWithFrontiersConfig& config) {
  if (auto s = support().configure(config.motion()); !s.ok()) return s;
  path_settings_.configure(config.path());
  lagging_.setDwell(support().settings().flight.progress_window);
  min_frontier_cells_ = static_cast<size_t>(config.min_frontier_cells());
  look_ahead_m_ = config.look_ahead_m();
  slice_half_height_m_ = config.slice_half_height_m();
  return absl::OkStatus();
}

Situation ExploreBehavior::checkSituation() {
  return lidarFlightSituation(
      mapper_, [this] { return ReferenceBehavior::checkSituation(); }, support().active());
}

absl::Status ExploreBehavior::onActivate() {
  const auto& p = parameters();
  const Eigen::Vector3d lo = toEigen(p.bounds_min_m()), hi = toEigen(p.bounds_max_m());
  if (!lo.allFinite() || !hi.allFinite() || (lo.array() >= hi.array()).any()) {
    return absl::InvalidArgumentError("bounds_min_m " + pointText(lo) +
                                      " must be below bounds_max_m " + pointText(hi) +
                                      " in every coordinate (finite, metres)");
  }
  const MapperSettings& m = mapper_.settings();
  const double z_lo = std::max(lo.z(), m.planning_min_z_m),
               z_hi = std::min(hi.z(), m.planning_max_z_m);
  if (p.altitude_m() < z_lo || p.altitude_m() > z_hi) {
    return absl::InvalidArgumentError("altitude_m " + fixed2(p.altitude_m()) +
                                      " is out of bounds: paths keep between z " + fixed2(z_lo) +
                                      " and " + fixed2(z_hi) + " m");
  }
  if (auto s = support().begin(now(), activationId()); !s.ok()) return s;
  setMaximumExecutionTime(
      std::chrono::duration_cast<Duration>(std::chrono::duration<double>(p.time_limit_s())),
      "the exploration took its time_limit_s (" + fixed2(p.time_limit_s()) + " s)");
  phase_ = Phase::kChoosing;
  paused_ = false;
  stops_ = 0;
  failed_choices_ = 0;
  choice_ = Choice();
  tracker_.reset();
  hold_m_ = support().state().position_m;
  given_up_.clear();
  known_fraction_ = 0;
  last_growth_value_ = 0;
  last_growth_time_ = now();
  legs_ = 0;
  flown_m_ = 0;
  done_message_.clear();
  last_update_ = now();
  startChoice();
  return absl::OkStatus();
}

void ExploreBehavior::startChoice() {
  const auto& p = parameters();
  const MapperSettings& m = mapper_.settings();
  Request r;
  r.start_m = support().state().position_m;
  r.lo_m = toEigen(p.bounds_min_m());
  r.hi_m = toEigen(p.bounds_max_m());
  r.lo_m.z() = std::max(r.lo_m.z(), m.planning_min_z_m);
  r.hi_m.z() = std::min(r.hi_m.z(), m.planning_max_z_m);
  r.altitude_m = p.altitude_m();
  r.radius_m = p.vehicle_radius_m();
  r.given_up = given_up_;
  choice_ = Choice();
  // A newer choice supersedes the running one: called off, its result never
  // reaches choice_.
  choosing_.request_stop();
  choosing_ = inBackground<Choice>([this, r](std::stop_token stop) { return choose(r, stop); },
                                   [this](const Choice& c) { choice_ = c; });
}

ExploreBehavior::Choice ExploreBehavior::choose(const Request& request,
                                                std::stop_token stop) const {
  Choice c;
  c.done = true;
  if (stop.stop_requested()) return c;  // superseded
  mapper_.withMap([&](const OccupancyMap& map) {
    const double plane = request.altitude_m + mapper_.settings().lidar_mount_m.z();
    const MapSlice slice(map, {.min_m = request.lo_m.head<2>(),
                               .max_m = request.hi_m.head<2>(),
                               .z_min_m = plane - slice_half_height_m_,
                               .z_max_m = plane + slice_half_height_m_});
    c.known_fraction = slice.census().knownFraction();
    const std::vector<Frontier> frontiers = slice.frontiers(min_frontier_cells_);
    c.frontiers = frontiers.size();
    if (frontiers.empty()) {
      c.message = "no frontier left";
      return;
    }
    const double bare = request.radius_m + cellMarginM(map.resolutionM());
    const InflatedGrid grid(map, request.lo_m, request.hi_m, bare);
    // Breadth-first over the slice's cells at the flight altitude, from the
    // vehicle: which cells it can reach, and how far (in cells).
    const int w = slice.width(), h = slice.height();
    int sx = 0, sy = 0;
    if (!slice.cellOf(request.start_m.head<2>(), &sx, &sy)) {
      c.message = "the vehicle at " + pointText(request.start_m) + " is outside the area";
      return;
    }
    const auto at_altitude = [&](int ix, int iy) {
      const Eigen::Vector2d q = slice.centre(ix, iy);
      return Eigen::Vector3d(q.x(), q.y(), request.altitude_m);
    };
    constexpr int kUnreached = std::numeric_limits<int>::max();
    std::vector<int> steps(static_cast<size_t>(w) * h, kUnreached);
    std::deque<std::pair<int, int>> queue{{sx, sy}};
    steps[static_cast<size_t>(sy) * w + sx] = 0;
    while (!queue.empty()) {
      const auto [x, y] = queue.front();
      queue.pop_front();
      const int next = steps[static_cast<size_t>(y) * w + x] + 1;
      for (int dy = -1; dy <= 1; ++dy) {
        for (int dx = -1; dx <= 1; ++dx) {
          const int nx = x + dx, ny = y + dy;
          if (nx < 0 || ny < 0 || nx >= w || ny >= h) continue;
          int& s = steps[static_cast<size_t>(ny) * w + nx];
          if (s != kUnreached || grid.blocked(at_altitude(nx, ny), bare)) continue;
          s = next;
          queue.emplace_back(nx, ny);
        }
      }
    }
    // Each frontier's reachable cell nearest its centre.
    std::vector<std::pair<int, Eigen::Vector3d>> candidates;
    for (const Frontier& f : frontiers) {
      std::optional<Eigen::Vector3d> best;
      int best_steps = 0;
      double best_d = std::numeric_limits<double>::infinity();
      for (const Eigen::Vector2d& cell : f.cells_m) {
        int ix = 0, iy = 0;
        if (!slice.cellOf(cell, &ix, &iy)) continue;
        const int s = steps[static_cast<size_t>(iy) * w + ix];
        if (s == kUnreached) continue;
        const double d = (cell - f.centroid_m).norm();
        if (d < best_d) {
          best_d = d;
          best = at_altitude(ix, iy);
          best_steps = s;
        }
      }
      if (!best) {
        ++c.unreachable;
        continue;
      }
      const bool gave_up =
          std::any_of(request.given_up.begin(), request.given_up.end(),
                      [&](const Eigen::Vector3d& g) { return (g - *best).norm() < kGivenUpM; });
      if (gave_up) {
        ++c.unreachable;
        continue;
      }
      candidates.emplace_back(best_steps, *best);
    }
    std::stable_sort(candidates.begin(), candidates.end(),
                     [](const auto& a, const auto& b) { return a.first < b.first; });
    PlanOptions options;
    options.vehicle_radius_m = request.radius_m;
    options.bounds_min_m = request.lo_m;
    options.bounds_max_m = request.hi_m;
    options.timeout_s = 0.5;
    // A leg may end nearer a wall than the radius (the wall was not in the
    // map when the leg was planned): the next leg first moves away from it.
    options.escape_m = 2.0 * request.radius_m;
    int tried = 0;
    for (const auto& [steps_to, target] : candidates) {
      if (tried++ == kCandidatesPerChoice) break;
      auto planned = planPath(grid, request.start_m, target, options);
      if (planned.ok()) {
        c.target_m = target;
        c.path_m = std::move(planned->waypoints_m);
        return;
      }
      c.given_up.push_back(target);
      if (c.plan_failure.empty()) c.plan_failure = std::string(planned.status().message());
    }
    std::ostringstream out;
    out << "no reachable frontier left: " << c.frontiers << " frontiers, " << c.unreachable
        << " out of reach for a vehicle of radius " << fixed2(request.radius_m)
        << " m (or given up)";
    if (!c.given_up.empty()) {
      out << ", " << c.given_up.size() << " whose plan failed (the first: " << c.plan_failure
          << ")";
    }
    c.message = out.str();
  });
  return c;
}

void ExploreBehavior::startLeg(const std::vector<Eigen::Vector3d>& path) {
  auto tracker = trackerFromVehicle(path, parameters().speed_m_s(), path_settings_, support());
  if (!tracker.ok()) {
    given_up_.push_back(path.back());
    startChoice();
    return;
  }
  tracker_ = std::move(*tracker);
  leg_path_ = path;
  last_check_ = now();
  hold_m_.reset();
  lagging_.reset();
  failed_choices_ = 0;
  flown_m_ += tracker_->lengthM();
  ++legs_;
  phase_ = Phase::kFlying;
}

bool ExploreBehavior::legBlocked() const {
  return pathAheadBlocked(mapper_, leg_path_, tracker_->lengthM() - tracker_->remainingM(),
                          look_ahead_m_, parameters().vehicle_radius_m());
}

void ExploreBehavior::onExecute() {
  followOrHold(support(), !paused_ && phase_ == Phase::kFlying && tracker_ ? &*tracker_ : nullptr,
               hold_m_, last_update_, now());
}

void ExploreBehavior::onDeactivate() {
  choosing_.request_stop();  // the running choice is dropped
  support().end();
  tracker_.reset();
}

void ExploreBehavior::onPause() {
  paused_ = true;
  hold_m_ = support().state().position_m;
}

void ExploreBehavior::onResume() {
  paused_ = false;
  tracker_.reset();
  hold_m_ = support().state().position_m;
  phase_ = Phase::kChoosing;
  startChoice();
}

absl::Status ExploreBehavior::onModify(const v1::ExploreWithFrontiersParameters& n) {
  const auto& p = parameters();
  if (toEigen(n.bounds_min_m()) != toEigen(p.bounds_min_m()) ||
      toEigen(n.bounds_max_m()) != toEigen(p.bounds_max_m()) || n.altitude_m() != p.altitude_m() ||
      n.vehicle_radius_m() != p.vehicle_radius_m() || n.time_limit_s() != p.time_limit_s()) {
    return absl::InvalidArgumentError(
        "only speed_m_s, coverage and stall_s can change while exploring: deactivate and "
        "activate again for other bounds, altitude, radius or time limit");
  }
  return absl::OkStatus();
}

Verdict ExploreBehavior::checkGoal() {
  if (phase_ == Phase::kDone) return Verdict::finish(done_message_);
  return Verdict::keepGoing();
}

Verdict ExploreBehavior::checkProgress() {
  const auto& p = parameters();
  const TimePoint t = now();
  if (phase_ == Phase::kChoosing && choice_.done && !paused_) {
    known_fraction_ = choice_.known_fraction;
    // Frontiers there but every plan failed (a random planner's time-out, a
    // vehicle just too near a wall): choose again, on a newer map, before
    // giving those targets up.
    if (!choice_.target_m && !choice_.given_up.empty() && failed_choices_ < kChoiceRetries &&
        known_fraction_ < p.coverage()) {
      ++failed_choices_;
      startChoice();
      return Verdict::keepGoing();
    }
    given_up_.insert(given_up_.end(), choice_.given_up.begin(), choice_.given_up.end());
    const std::string summary = percent(known_fraction_) + " of the area known after " +
                                std::to_string(legs_) + " legs (" + std::to_string(stops_) +
                                " stopped by a wall seen on the way), " + fixed2(flown_m_) +
                                " m of paths";
    if (known_fraction_ >= p.coverage()) {
      phase_ = Phase::kDone;
      done_message_ = "explored: " + summary + " (coverage " + fixed2(p.coverage()) + " reached)";
    } else if (!choice_.target_m) {
      phase_ = Phase::kDone;
      done_message_ = "explored: " + summary + "; " + choice_.message;
    } else {
      startLeg(choice_.path_m);
    }
  }
  if (phase_ == Phase::kFlying && tracker_ && !paused_) {
    const Eigen::Vector3d position = support().state().position_m;
    const Eigen::Vector3d end = tracker_->points().back();
    const bool arrived = tracker_->referenceAtEnd() && (position - end).norm() <= kArrivedM;
    bool blocked = false;
    if (!arrived && t - last_check_ >= check_interval_) {
      last_check_ = t;
      blocked = legBlocked();
    }
    const bool astray =
        tracker_->crossTrackErrorM(position) > path_settings_.max_cross_track_m ||
        lagging_.update(t, tracker_->lagM(position) >= 0.8 * path_settings_.max_lag_m);
    if (arrived || astray || blocked) {
      if (astray) given_up_.push_back(end);
      if (blocked) ++stops_;
      hold_m_ = arrived ? end : position;
      tracker_.reset();
      phase_ = Phase::kChoosing;
      startChoice();
    }
  }
  if (known_fraction_ >= last_growth_value_ + 0.01) {
    last_growth_value_ = known_fraction_;
    last_growth_time_ = t;
  }
  const double stalled = std::chrono::duration<double>(t - last_growth_time_).count();
  if (phase_ != Phase::kDone && stalled > p.stall_s()) {
    return Verdict::finish("the known fraction of the area has grown by less than 0.01 in " +
                           fixed2(stalled) + " s (stall_s " + fixed2(p.stall_s()) +
                           "): " + percent(known_fraction_) + " known after " +
                           std::to_string(legs_) + " legs");
  }
  return Verdict::keepGoing();
}

}  // namespace behaviorlib::nav
