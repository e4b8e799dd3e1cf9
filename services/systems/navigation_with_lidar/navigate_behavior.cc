#include "behaviorlib/navigation_with_lidar/navigate_behavior.h"

#include <algorithm>
#include <cmath>
#include <functional>
#include <string>
#include <vector>

#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"
#include "behaviorlib/flight_common/flight_support.h"
#include "behaviorlib/motion_behaviors/motion_messages.h"
#include "behaviorlib/navigation_with_lidar/lidar_flight.h"

namespace behaviorlib::nav {
namespace {

using flight::fixed2;

using motion_behaviors::pointText;
using motion_behaviors::toEigen;
using motion_behaviors::toProto;

constexpr uint32_t kPlanAttempts = 3;  // failed plans in a row before giving up
constexpr double kProgressM = 0.5;     // the way left must shrink by this over stall_s
constexpr size_t kMaxAreaCells = 1'000'000;
constexpr size_t kLongestPlansStated = 16;  // in the finished message

Duration secondsOf(double s) {
  return std::chrono::duration_cast<Duration>(std::chrono::duration<double>(s));
}

}  // namespace

NavigateBehavior::NavigateBehavior(LidarMapper& mapper, flight::Vehicle& vehicle,
                                   motion_behaviors::MotionLink& link)
    : ReferenceBehavior(vehicle, link, Duration::zero()), mapper_(mapper) {}

absl::Status NavigateBehavior::onConfigure(const config::v1::NavigateToConfig& config) {
  if (auto s = support().configure(config.motion()); !s.ok()) return s;
  path_settings_.configure(config.path());
  lagging_.setDwell(support().settings().flight.progress_window);
  look_ahead_m_ = config.look_ahead_m();
  slice_half_height_m_ = config.slice_half_height_m();
  unknown_cost_ = config.unknown_cost();
  preferred_clearance_m_ = config.preferred_clearance_m();
  replan_interval_ = secondsOf(config.replan_interval_s());
  replan_gain_ = config.replan_gain();
  return absl::OkStatus();
}

Situation NavigateBehavior::checkSituation() {
  return lidarFlightSituation(
      mapper_, [this] { return ReferenceBehavior::checkSituation(); }, support().active());
}

UnknownSpacePlanOptions NavigateBehavior::planOptions() const {
  const auto& p = parameters();
  const MapperSettings& m = mapper_.settings();
  UnknownSpacePlanOptions o;
  o.vehicle_radius_m = p.vehicle_radius_m();
  o.bounds_min_m = toEigen(p.bounds_min_m());
  o.bounds_max_m = toEigen(p.bounds_max_m());
  o.bounds_min_m.z() = std::max(o.bounds_min_m.z(), m.planning_min_z_m);
  o.bounds_max_m.z() = std::min(o.bounds_max_m.z(), m.planning_max_z_m);
  o.altitude_m = p.goal_m().z();
  const double plane = o.altitude_m + m.lidar_mount_m.z();
  o.slice_z_min_m = plane - slice_half_height_m_;
  o.slice_z_max_m = plane + slice_half_height_m_;
  o.unknown_cost = unknown_cost_;
  o.max_unknown_m = p.max_unknown_m();
  o.preferred_clearance_m = preferred_clearance_m_;
  // A path may end nearer a wall than the radius (the wall was not in the
  // map when it was planned): the next one first moves away from it.
  o.escape_m = 2.0 * p.vehicle_radius_m();
  o.max_cells = kMaxAreaCells;
  return o;
}

absl::Status NavigateBehavior::onActivate() {
  const auto& p = parameters();
  const Eigen::Vector3d lo = toEigen(p.bounds_min_m()), hi = toEigen(p.bounds_max_m());
  if (!lo.allFinite() || !hi.allFinite() || (lo.array() >= hi.array()).any()) {
    return absl::InvalidArgumentError("bounds_min_m " + pointText(lo) +
                                      " must be below bounds_max_m " + pointText(hi) +
                                      " in every coordinate (finite, metres)");
  }
  const double res = mapper_.settings().resolution_m;
  const double cells = std::ceil((hi.x() - lo.x()) / res) * std::ceil((hi.y() - lo.y()) / res);
  if (cells > static_cast<double>(kMaxAreaCells)) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "the bounds hold %.0f cells of the map's %.2f m, more than the %d a plan may search: "
        "give the area the paths may use, not more",
        cells, res, kMaxAreaCells));
  }
  const UnknownSpacePlanOptions o = planOptions();
  const Eigen::Vector3d goal = toEigen(p.goal_m());
  const auto inside = [&](const Eigen::Vector3d& q) {
    return q.x() >= lo.x() && q.x() <= hi.x() && q.y() >= lo.y() && q.y() <= hi.y();
  };
  if (!goal.allFinite() || !inside(goal)) {
    return absl::InvalidArgumentError("goal_m " + pointText(goal) + " lies outside the bounds " +
                                      pointText(lo) + " .. " + pointText(hi));
  }
  if (goal.z() < o.bounds_min_m.z() || goal.z() > o.bounds_max_m.z()) {
    return absl::InvalidArgumentError(
        "goal_m's altitude " + fixed2(goal.z()) + " is out of bounds: paths keep between z " +
        fixed2(o.bounds_min_m.z()) + " and " + fixed2(o.bounds_max_m.z()) + " m");
  }
  if (auto s = support().begin(now(), activationId()); !s.ok()) return s;
  const Eigen::Vector3d position = support().state().position_m;
  if (!inside(position)) {
    support().end();
    return absl::InvalidArgumentError("the vehicle at " + pointText(position) +
                                      " is outside the bounds " + pointText(lo) + " .. " +
                                      pointText(hi));
  }
  setMaximumExecutionTime(secondsOf(p.time_limit_s()), "the navigation took its time_limit_s (" +
                                                           fixed2(p.time_limit_s()) + " s)");
  phase_ = Phase::kPlanning;
  paused_ = false;
  planning_ = false;
  plan_ = Plan();
  tracker_.reset();
  hold_m_ = position;
  failures_ = 0;
  failure_.clear();
  best_way_m_ = std::numeric_limits<double>::infinity();
  best_way_time_ = now();
  last_plan_length_m_ = (goal - position).norm();
  plans_ = followed_ = stops_ = astray_ = 0;
  paths_m_ = unknown_m_ = 0;
  plan_times_s_.clear();
  done_message_.clear();
  last_update_ = last_plan_ = now();
  startPlan(false);
  return absl::OkStatus();
}

void NavigateBehavior::startPlan(bool flying) {
  // While flying, from the reference: a plan followed continues from there.
  const Eigen::Vector3d start =
      flying && tracker_ ? tracker_->current().position_m : support().state().position_m;
  const UnknownSpacePlanOptions options = planOptions();
  planning_ = true;
  last_plan_ = now();
  plan_ = Plan();
  // A newer plan supersedes the running one: called off, its result never
  // reaches plan_.
  planning_stop_.request_stop();
  const Eigen::Vector3d goal = toEigen(parameters().goal_m());
  planning_stop_ =
      inBackground<Plan>([this, start, goal, options](
                             std::stop_token stop) { return plan(start, goal, options, stop); },
                         [this](const Plan& result) {
                           plan_ = result;
                           planning_ = false;
                         });
}

NavigateBehavior::Plan NavigateBehavior::plan(const Eigen::Vector3d& start_m,
                                              const Eigen::Vector3d& goal_m,
                                              const UnknownSpacePlanOptions& options,
                                              std::stop_token stop) const {
  Plan result;
  result.done = true;
  if (stop.stop_requested()) return result;  // superseded
  // Off the worker: only what the request carries (the parameters are the
  // worker's).
  mapper_.withMap([&](const OccupancyMap& map) {
    result.revision = map.revision();
    auto planned = planThroughUnknown(map, start_m, goal_m, options);
    if (planned.ok()) {
      result.path = std::move(*planned);
    } else {
      result.status = planned.status();
    }
  });
  return result;
}

void NavigateBehavior::startPath(const std::vector<Eigen::Vector3d>& path) {
  // A plan made while flying is taken up from the reference (no jump, no
  // stop); one made while holding starts from the vehicle.
  std::optional<motion::ReferencePoint> from;
  if (tracker_ && phase_ == Phase::kFlying) from = tracker_->current();
  auto tracker = trackerFromVehicle(path, parameters().speed_m_s(), path_settings_, support(),
                                    from ? &*from : nullptr);
  if (!tracker.ok()) {
    failure_ = std::string(tracker.status().message());
    ++failures_;
    toPlanning();
    return;
  }
  tracker_ = std::move(*tracker);
  failures_ = 0;
  last_check_ = now();
  hold_m_.reset();
  lagging_.reset();
  phase_ = Phase::kFlying;
}

void NavigateBehavior::toPlanning() {
  if (!hold_m_) hold_m_ = support().state().position_m;
  tracker_.reset();
  phase_ = Phase::kPlanning;
  startPlan(false);
}

bool NavigateBehavior::pathBlocked() const {
  return pathAheadBlocked(mapper_, tracker_->points(), tracker_->lengthM() - tracker_->remainingM(),
                          look_ahead_m_, parameters().vehicle_radius_m());
}

double NavigateBehavior::wayLeftM() const {
  if (!tracker_) return last_plan_length_m_;
  return tracker_->remainingM() + tracker_->lagM(support().state().position_m);
}

void NavigateBehavior::onExecute() {
  followOrHold(support(), !paused_ && phase_ == Phase::kFlying && tracker_ ? &*tracker_ : nullptr,
               hold_m_, last_update_, now());
}

void NavigateBehavior::onDeactivate() {
  planning_stop_.request_stop();  // the running plan is dropped
  planning_ = false;
  support().end();
  tracker_.reset();
}

void NavigateBehavior::onPause() {
  paused_ = true;
  hold_m_ = support().state().position_m;
}

void NavigateBehavior::onResume() {
  paused_ = false;
  hold_m_ = support().state().position_m;
  toPlanning();
}

absl::Status NavigateBehavior::onModify(const v1::NavigateToParameters& n) {
  const auto& p = parameters();
  if (toEigen(n.goal_m()) != toEigen(p.goal_m()) ||
      toEigen(n.bounds_min_m()) != toEigen(p.bounds_min_m()) ||
      toEigen(n.bounds_max_m()) != toEigen(p.bounds_max_m()) ||
      n.arrival_radius_m() != p.arrival_radius_m() ||
      n.vehicle_radius_m() != p.vehicle_radius_m() || n.max_unknown_m() != p.max_unknown_m() ||
      n.time_limit_s() != p.time_limit_s()) {
    return absl::InvalidArgumentError(
        "only speed_m_s and stall_s can change while navigating: deactivate and activate again "
        "for another goal, bounds, radius, unknown distance or time limit");
  }
  return absl::OkStatus();
}

std::string NavigateBehavior::summary() const {
  std::vector<double> times = plan_times_s_;
  std::sort(times.begin(), times.end(), std::greater<>());
  const double median = times.empty() ? 0.0 : times[times.size() / 2];
  const double longest = times.empty() ? 0.0 : times.front();
  // The longest plans one by one: a percentile over many flights (the 99th
  // of a thousand plans is the 11th longest) is exact from each flight's
  // longest, where it is not from each flight's own percentile.
  std::vector<std::string> top;
  for (size_t i = 0; i < std::min(times.size(), kLongestPlansStated); ++i) {
    top.push_back(absl::StrFormat("%.1f", times[i] * 1e3));
  }
  return absl::StrFormat(
      "%d plans (%d followed while flying, %d after a wall seen ahead, %d after straying), "
      "%.2f m of paths of which %.2f m through unknown space; plan time median %.1f ms, "
      "longest %.1f ms; the %d longest: %s ms",
      plans_, followed_, stops_, astray_, paths_m_, unknown_m_, median * 1e3, longest * 1e3,
      top.size(), absl::StrJoin(top, ", "));
}

Verdict NavigateBehavior::checkGoal() {
  if (phase_ == Phase::kDone) return Verdict::finish(done_message_);
  return Verdict::keepGoing();
}

Verdict NavigateBehavior::checkProgress() {
  const auto& p = parameters();
  const TimePoint t = now();
  const Eigen::Vector3d position = support().state().position_m;
  const Eigen::Vector3d goal = toEigen(p.goal_m());
  if (phase_ != Phase::kDone && (position - goal).norm() <= p.arrival_radius_m()) {
    phase_ = Phase::kDone;
    tracker_.reset();
    hold_m_ = position;
    done_message_ = "reached " + pointText(goal) + ": " + summary();
    return Verdict::keepGoing();
  }
  if (paused_ || phase_ == Phase::kDone) return Verdict::keepGoing();

  // A plan's result.
  if (!planning_ && plan_.done) {
    const Plan result = plan_;
    plan_ = Plan();
    ++plans_;
    plan_times_s_.push_back(result.path.planning_time_s);
    if (result.status.ok()) {
      const double length = result.path.length_m;
      const bool better = !tracker_ || length < (1.0 - replan_gain_) * wayLeftM();
      if (phase_ == Phase::kPlanning || better) {
        if (phase_ == Phase::kFlying) ++followed_;
        paths_m_ += length;
        unknown_m_ += result.path.unknown_m;
        last_plan_length_m_ = length;
        path_revision_ = result.revision;
        startPath(result.path.waypoints_m);
      }
    } else if (phase_ == Phase::kPlanning) {
      ++failures_;
      failure_ = std::string(result.status.message());
    }
  }
  // A plan that failed, or a path that could not be followed (startPath).
  if (phase_ == Phase::kPlanning && failures_ >= kPlanAttempts) {
    return Verdict::finish(absl::StrFormat("no way to the goal after %d plans on newer maps: %s",
                                           failures_, failure_));
  }
  // Planning again after a failure, once the map had time to grow.
  if (phase_ == Phase::kPlanning && !planning_ && failures_ > 0 &&
      t - last_plan_ >= retry_interval_) {
    startPlan(false);
  }

  if (phase_ == Phase::kFlying && tracker_) {
    bool blocked = false;
    if (t - last_check_ >= check_interval_) {
      last_check_ = t;
      blocked = pathBlocked();
    }
    const bool astray =
        tracker_->crossTrackErrorM(position) > path_settings_.max_cross_track_m ||
        lagging_.update(t, tracker_->lagM(position) >= 0.8 * path_settings_.max_lag_m);
    if (blocked || astray) {
      if (blocked) ++stops_;
      if (astray) ++astray_;
      hold_m_ = position;
      toPlanning();
    } else if (!planning_ && t - last_plan_ >= replan_interval_) {
      const uint64_t revision =
          mapper_.withMap([](const OccupancyMap& map) { return map.revision(); });
      if (revision != path_revision_) startPlan(true);
    }
  }

  const double way = wayLeftM();
  if (way <= best_way_m_ - kProgressM) {
    best_way_m_ = way;
    best_way_time_ = t;
  }
  const double stalled = std::chrono::duration<double>(t - best_way_time_).count();
  if (stalled > p.stall_s()) {
    return Verdict::finish(absl::StrFormat(
        "the way left to the goal has shrunk by less than %.1f m in %.1f s (stall_s %.1f): "
        "%.2f m left; %s",
        kProgressM, stalled, p.stall_s(), way, summary()));
  }
  return Verdict::keepGoing();
}

}  // namespace behaviorlib::nav
