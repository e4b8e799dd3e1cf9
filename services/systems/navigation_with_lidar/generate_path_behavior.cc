#include "behaviorlib/navigation_with_lidar/generate_path_behavior.h"

#include <google/protobuf/struct.pb.h>
#include <google/protobuf/util/time_util.h>

#include <cmath>
#include <iostream>
#include <sstream>
#include <string>
#include <vector>

#include "behaviorlib/flight_common/flight_monitoring.h"
#include "behaviorlib/flight_common/flight_support.h"
#include "behaviorlib/flight_common/vehicle.h"

namespace behaviorlib::nav {
namespace {

std::string text(const Eigen::Vector3d& p) {
  std::ostringstream out;
  out.precision(3);
  out << "(" << p.x() << ", " << p.y() << ", " << p.z() << ")";
  return out.str();
}

Eigen::Vector3d vec(const v1::Vector3& v) { return {v.x(), v.y(), v.z()}; }

// Whether the lidar has seen anything in the goal's column between the
// planning altitudes (a 2-D lidar sees one plane; walls are extruded).
bool columnSeen(const OccupancyMap& map, const Eigen::Vector3d& goal, double lo_z, double hi_z) {
  for (double z = lo_z; z <= hi_z; z += map.resolutionM()) {
    if (map.known({goal.x(), goal.y(), z})) return true;
  }
  return false;
}

BehaviorOptions generatePathOptions() {
  BehaviorOptions o;
  o.frequency_hz = 20.0;
  // onActivate builds an inflated grid under the map's lock.
  o.watchdog_timeout = std::chrono::seconds(3);
  return o;
}

}  // namespace

std::string pathTopic(const std::string& robot_id) {
  return "robots/" + robot_id + "/navigation/path";
}

GeneratePathBehavior::GeneratePathBehavior(LidarMapper& mapper, const server::BeliefClient* beliefs)
    : Behavior(generatePathOptions()), mapper_(mapper), beliefs_(beliefs) {}

absl::Status GeneratePathBehavior::onConfigure(
    const config::v1::GeneratePathWithOccupancyGridConfig& config) {
  pose_timeout_ = behaviorlib::seconds(config.pose_timeout_s());
  timeout_grace_s_ = config.timeout_grace_s();
  uncertainty_sigmas_ = config.uncertainty_sigmas();
  max_uncertainty_margin_m_ = config.max_uncertainty_margin_m();
  preferred_clearance_m_ = config.preferred_clearance_m();
  return absl::OkStatus();
}

std::string GeneratePathBehavior::beliefKey() const {
  return parameters().belief_key().empty() ? robotId() + "/path" : parameters().belief_key();
}

std::optional<flight::SituationProblem> GeneratePathBehavior::poseProblem() const {
  const std::optional<v1::PoseStamped> pose = mapper_.latestPose();
  if (!pose) {
    return flight::SituationProblem{
        v1::SITUATION_REASON_INPUT_MISSING,
        "no pose estimate on " + mapper_.poseTopic() +
            ": activate a self-localization behavior (SELF_LOCALIZE_WITH_GROUND_TRUTH, ...)"};
  }
  if (auto stale = flight::staleness([&] { return "the pose estimate on " + mapper_.poseTopic(); },
                                     pose->header(), now(), pose_timeout_)) {
    return flight::SituationProblem{v1::SITUATION_REASON_INPUT_STALE, *stale};
  }
  return std::nullopt;
}

Situation GeneratePathBehavior::checkSituation() {
  if (!mapper_.channel()) {
    return Situation::infeasible(
        v1::SITUATION_REASON_CONFIGURATION,
        "no data channel configured: start the behavior system with --channel HOST:PORT");
  }
  if (activationId().empty()) {
    if (auto problem = poseProblem()) return Situation::infeasible(problem->code, problem->reason);
    const bool empty =
        mapper_.withMap([](const OccupancyMap& map) { return map.tree().size() == 0; });
    if (empty) {
      const MapperStats stats = mapper_.stats();
      return Situation::infeasible(
          v1::SITUATION_REASON_MAP_UNAVAILABLE,
          "the map is empty: no lidar scan on " + mapper_.scanTopic() +
              " has been mapped yet (is the simulator's lidar publishing?): " +
              std::to_string(stats.scans_received) + " scans received, " +
              std::to_string(stats.scans_without_pose) + " without a pose estimate within " +
              "pose_match_s of their stamp, " + std::to_string(stats.scans_dropped) + " dropped");
    }
  }
  return Situation::ok();
}

std::optional<GeneratePathBehavior::Box> GeneratePathBehavior::planningVolume(
    const OccupancyMap& map, const std::optional<Box>& bounds) const {
  auto volume = mapper_.planningVolumeLocked(map);
  if (volume && bounds) {
    volume->first = volume->first.cwiseMax(bounds->first);
    volume->second = volume->second.cwiseMin(bounds->second);
  }
  return volume;
}

std::optional<GeneratePathBehavior::Box> GeneratePathBehavior::boundsParameter() const {
  const auto& p = parameters();
  if (!p.has_bounds_min_m() || !p.has_bounds_max_m()) return std::nullopt;
  return Box{vec(p.bounds_min_m()), vec(p.bounds_max_m())};
}

absl::Status GeneratePathBehavior::onActivate() {
  const auto& p = parameters();
  const Eigen::Vector3d goal = vec(p.goal_m());
  if (!goal.allFinite()) return absl::InvalidArgumentError("goal_m must be finite coordinates");
  if (p.has_bounds_min_m() != p.has_bounds_max_m()) {
    return absl::InvalidArgumentError(
        "bounds_min_m and bounds_max_m go together: give both corners of the box, or neither");
  }
  if (p.has_bounds_min_m()) {
    const Eigen::Vector3d lo = vec(p.bounds_min_m()), hi = vec(p.bounds_max_m());
    if (!lo.allFinite() || !hi.allFinite() || (lo.array() >= hi.array()).any()) {
      return absl::InvalidArgumentError("bounds_min_m " + text(lo) +
                                        " must be below bounds_max_m " + text(hi) +
                                        " in every coordinate (finite, metres)");
    }
  }
  {
    // Out of bounds: outside the given box or the planning altitudes.
    const MapperSettings& m = mapper_.settings();
    const std::optional<Box> bounds = boundsParameter();
    const double lo_z = std::max(m.planning_min_z_m, bounds ? bounds->first.z() : -1e300);
    const double hi_z = std::min(m.planning_max_z_m, bounds ? bounds->second.z() : 1e300);
    if (goal.z() < lo_z || goal.z() > hi_z) {
      return absl::InvalidArgumentError("goal_m " + text(goal) + " is out of bounds: paths keep " +
                                        "between z " + flight::fixed2(lo_z) + " and " +
                                        flight::fixed2(hi_z) + " m");
    }
    if (bounds && ((goal.array() < bounds->first.array()).any() ||
                   (goal.array() > bounds->second.array()).any())) {
      return absl::InvalidArgumentError("goal_m " + text(goal) + " is out of bounds: outside " +
                                        "bounds_min_m " + text(bounds->first) +
                                        " .. bounds_max_m " + text(bounds->second));
    }
  }
  const std::optional<v1::PoseStamped> pose = mapper_.latestPose();
  if (!pose) return absl::FailedPreconditionError("no pose estimate on " + mapper_.poseTopic());
  start_m_ = vec(pose->pose().position_m());
  const double radius = p.vehicle_radius_m();
  absl::Status status = mapper_.withMap([&](const OccupancyMap& map) -> absl::Status {
    const auto volume = planningVolume(map, boundsParameter());
    if (!volume) return absl::FailedPreconditionError("the map is empty: nothing mapped yet");
    const auto& [lo, hi] = *volume;
    if ((start_m_.array() < lo.array()).any() || (start_m_.array() > hi.array()).any()) {
      return absl::FailedPreconditionError(
          "the vehicle at " + text(start_m_) + " is outside the planning volume (z " +
          flight::fixed2(lo.z()) + " .. " + flight::fixed2(hi.z()) + " m): take off first");
    }
    const InflatedGrid grid(map, lo, hi, radius + cellMarginM(map.resolutionM()));
    if (grid.blocked(start_m_)) {
      return absl::FailedPreconditionError(
          "the vehicle at " + text(start_m_) + " is closer than vehicle_radius_m (" +
          flight::fixed2(radius) + " m) to an obstacle: move it away first");
    }
    return absl::OkStatus();
  });
  if (!status.ok()) return status;
  replans_ = 0;
  map_changes_ = 0;
  waiting_since_.reset();
  paused_ = waiting_ = false;
  startAttempt();
  return absl::OkStatus();
}

void GeneratePathBehavior::startAttempt() {
  const auto& p = parameters();
  Attempt a;
  if (const std::optional<v1::PoseStamped> pose = mapper_.latestPose()) {
    start_m_ = vec(pose->pose().position_m());  // the vehicle may have moved while waiting
    a.stddev_m = pose->has_horizontal_stddev_m() ? pose->horizontal_stddev_m() : 0.0;
  }
  a.start_m = start_m_;
  a.goal_m = vec(p.goal_m());
  a.options.vehicle_radius_m = p.vehicle_radius_m();
  a.options.timeout_s = p.planning_time_limit_s();
  a.options.preferred_clearance_m = preferred_clearance_m_;
  a.options.uncertainty_margin_m =
      std::clamp(uncertainty_sigmas_ * a.stddev_m, 0.0, max_uncertainty_margin_m_);
  a.belief_key = beliefKey();
  a.bounds = boundsParameter();
  result_ = Result();
  attempt_started_ = std::chrono::steady_clock::now();
  // Planned on the behavior's background thread; the result comes back on
  // the worker, where only the current attempt's counts.
  // A newer attempt supersedes the running one: called off, its result
  // never reaches result_.
  attempt_.request_stop();
  attempt_ = inBackground<Result>([this, a](std::stop_token stop) { return plan(a, stop); },
                                  [this](const Result& r) { result_ = r; });
}

GeneratePathBehavior::Result GeneratePathBehavior::plan(const Attempt& attempt,
                                                        std::stop_token stop) const {
  Result r;
  if (stop.stop_requested()) return r;  // superseded while it waited
  std::optional<absl::StatusOr<PlannedPath>> planned;
  mapper_.withMap([&](const OccupancyMap& map) {
    r.map_revision = map.revision();
    const auto volume = planningVolume(map, attempt.bounds);
    if (!volume) {
      r.outcome = Outcome::kInvalid;
      r.message = "the map was cleared while planning";
      return;
    }
    PlanOptions options = attempt.options;
    options.bounds_min_m = volume->first;
    options.bounds_max_m = volume->second;
    const std::string unreachable = "the goal " + text(attempt.goal_m) + " is unreachable ";
    if ((attempt.goal_m.array() < volume->first.array()).any() ||
        (attempt.goal_m.array() > volume->second.array()).any()) {
      std::ostringstream out;
      out.precision(3);
      out << unreachable << "(unknown): it lies outside the space mapped so far (x "
          << volume->first.x() << " .. " << volume->second.x() << " m, y " << volume->first.y()
          << " .. " << volume->second.y() << " m)";
      r.outcome = Outcome::kUnknown;
      r.message = out.str();
      return;
    }
    const double bare = options.vehicle_radius_m + cellMarginM(map.resolutionM());
    const InflatedGrid grid(map, options.bounds_min_m, options.bounds_max_m,
                            bare + options.uncertainty_margin_m);
    if (grid.blocked(attempt.goal_m, bare)) {
      r.outcome = Outcome::kBlocked;
      r.message = unreachable + "(blocked): an occupied voxel of the map lies within " +
                  flight::fixed2(options.vehicle_radius_m) + " m (vehicle_radius_m) of it";
      return;
    }
    if (!grid.blocked(attempt.start_m, bare) &&
        !grid.connected(attempt.start_m, attempt.goal_m, bare)) {
      const std::string passage = "no free passage for a vehicle of radius " +
                                  flight::fixed2(options.vehicle_radius_m) +
                                  " m joins it to the vehicle at " + text(attempt.start_m);
      if (columnSeen(map, attempt.goal_m, volume->first.z(), volume->second.z())) {
        r.outcome = Outcome::kBlocked;
        r.message = unreachable + "(blocked): " + passage +
                    " in the map (a door narrower than the vehicle, or a closed space)";
      } else {
        r.outcome = Outcome::kUnknown;
        r.message = unreachable + "(unknown): it lies in space not yet seen, and " + passage +
                    " through the space mapped so far";
      }
      return;
    }
    planned = planPath(grid, attempt.start_m, attempt.goal_m, options);
  });
  if (!planned) return r;
  if (!planned->ok()) {
    const absl::Status& s = planned->status();
    r.outcome = s.code() == absl::StatusCode::kNotFound ? Outcome::kTimedOut : Outcome::kInvalid;
    r.message = std::string(s.message());
    return r;
  }
  const PlannedPath& path = **planned;
  if (stop.stop_requested()) return r;  // abandoned: write nothing
  // The channel's Path, and the belief FOLLOW_PATH takes as path_m.
  v1::Path message;
  auto* header = message.mutable_header();
  *header->mutable_stamp() =
      google::protobuf::util::TimeUtil::NanosecondsToTimestamp(now().time_since_epoch().count());
  header->set_frame_id("world");
  header->set_robot_id(robotId());
  google::protobuf::Value belief;
  auto* list = belief.mutable_list_value();
  for (const Eigen::Vector3d& w : path.waypoints_m) {
    auto* pose = message.add_poses();
    pose->mutable_position_m()->set_x(w.x());
    pose->mutable_position_m()->set_y(w.y());
    pose->mutable_position_m()->set_z(w.z());
    pose->mutable_orientation()->set_w(1.0);
    auto& fields = *list->add_values()->mutable_struct_value()->mutable_fields();
    fields["x"].set_number_value(w.x());
    fields["y"].set_number_value(w.y());
    fields["z"].set_number_value(w.z());
  }
  r.waypoints = path.waypoints_m.size();
  r.length_m = path.length_m;
  r.planning_time_s = path.planning_time_s;
  r.min_clearance_m = path.min_clearance_m;
  const double margin = attempt.options.uncertainty_margin_m;
  if (absl::Status s = mapper_.channel()->publish(pathTopic(robotId()), message); !s.ok()) {
    r.outcome = Outcome::kOutputFailed;
    r.message =
        "cannot publish the path on " + pathTopic(robotId()) + ": " + std::string(s.message());
    return r;
  }
  if (beliefs_) {
    auto written = beliefs_->write(attempt.belief_key, belief,
                                   robotId() + "/GENERATE_PATH_WITH_OCCUPANCY_GRID");
    if (!written.ok()) {
      r.outcome = Outcome::kOutputFailed;
      r.message = "cannot write the path to belief '" + attempt.belief_key +
                  "': " + std::string(written.status().message());
      return r;
    }
  }
  r.outcome = Outcome::kWritten;
  std::ostringstream out;
  out.precision(3);
  out << "path of " << r.waypoints << " waypoints, " << r.length_m << " m, planned in "
      << r.planning_time_s << " s, ";
  if (std::isfinite(r.min_clearance_m)) {
    out << "at least " << flight::fixed2(r.min_clearance_m)
        << " m of clearance beyond the vehicle's radius";
  } else {
    out << "no obstacle in reach";
  }
  if (margin > 0) {
    out << "; the map inflated by " << flight::fixed2(margin)
        << " m more for the pose estimate's uncertainty (horizontal_stddev_m "
        << flight::fixed2(attempt.stddev_m) << " m)"
        << (path.margin_kept ? "" : " except in a passage too narrow for it");
  }
  out << "; on " << pathTopic(robotId())
      << (beliefs_ ? " and in belief '" + attempt.belief_key + "'"
                   : " (no coordinator: not in belief memory)");
  r.message = out.str();
  return r;
}

void GeneratePathBehavior::onDeactivate() {
  attempt_.request_stop();  // the running attempt writes nothing
}

void GeneratePathBehavior::onPause() { paused_ = true; }

void GeneratePathBehavior::onResume() {
  paused_ = false;
  if (waiting_) {
    waiting_ = false;
    startAttempt();
  }
}

absl::Status GeneratePathBehavior::onModify(const v1::GeneratePathWithOccupancyGridParameters& n) {
  const auto& p = parameters();
  if (vec(n.goal_m()) != vec(p.goal_m()) || n.vehicle_radius_m() != p.vehicle_radius_m() ||
      n.belief_key() != p.belief_key()) {
    return absl::InvalidArgumentError(
        "only planning_time_limit_s and max_replans can change while planning: deactivate and "
        "activate again for another goal, radius or belief_key");
  }
  return absl::OkStatus();
}

Verdict GeneratePathBehavior::checkProcesses() {
  if (auto problem = poseProblem()) return Verdict::finish(problem->reason);
  if (result_.outcome == Outcome::kOutputFailed) return Verdict::finish(result_.message);
  return Verdict::keepGoing();
}

Verdict GeneratePathBehavior::checkGoal() {
  if (result_.outcome != Outcome::kWritten) return Verdict::keepGoing();
  if (!waiting_since_) return Verdict::finish(result_.message);
  const double waited = std::chrono::duration<double>(now() - *waiting_since_).count();
  return Verdict::finish(result_.message + "; after waiting " + flight::fixed2(waited) +
                         " s for the map (" + std::to_string(map_changes_) + " new attempts)");
}

uint64_t GeneratePathBehavior::mapRevision() const {
  return mapper_.withMap([](const OccupancyMap& map) { return map.revision(); });
}

Verdict GeneratePathBehavior::waitForTheMap() {
  if (!waiting_since_) waiting_since_ = now();
  const double waited = std::chrono::duration<double>(now() - *waiting_since_).count();
  const double limit = parameters().map_wait_s();
  if (waited >= limit) {
    return Verdict::finish(result_.message + "; waited " + flight::fixed2(waited) +
                           " s (map_wait_s " + flight::fixed2(limit) + ") for new scans, " +
                           std::to_string(map_changes_) + " new attempts on a changed map");
  }
  if (!paused_ && mapRevision() != result_.map_revision) {
    ++map_changes_;
    startAttempt();
  }
  return Verdict::keepGoing();
}

Verdict GeneratePathBehavior::checkProgress() {
  const Outcome outcome = result_.outcome;
  const std::string message = result_.message;
  if (outcome == Outcome::kUnknown || outcome == Outcome::kBlocked) return waitForTheMap();
  if (outcome == Outcome::kInvalid) {
    return Verdict::finish("the plan is no longer possible on the updated map: " + message);
  }
  const double limit = parameters().planning_time_limit_s();
  const double elapsed =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - attempt_started_).count();
  const bool timed_out =
      outcome == Outcome::kTimedOut ||
      (outcome == Outcome::kRunning && !waiting_ && elapsed > limit + timeout_grace_s_);
  if (!timed_out) return Verdict::keepGoing();
  const std::string why = outcome == Outcome::kTimedOut
                              ? message
                              : "planning attempt still running after " + flight::fixed2(elapsed) +
                                    " s (limit " + flight::fixed2(limit) + " s)";
  if (replans_ >= parameters().max_replans()) {
    // TIME_OUT is the library's to give: end now through the time-out.
    const std::string reason = "planning timed out on each of " + std::to_string(replans_ + 1) +
                               " attempt(s) (max_replans " +
                               std::to_string(parameters().max_replans()) + "); the last: " + why;
    std::cerr << robotId() << "/GENERATE_PATH_WITH_OCCUPANCY_GRID: " << reason << std::endl;
    setMaximumExecutionTime(std::max(activeTime(), Duration(1)), reason);
    return Verdict::keepGoing();
  }
  ++replans_;
  std::cerr << robotId() << "/GENERATE_PATH_WITH_OCCUPANCY_GRID: re-planning (" << replans_
            << " of " << parameters().max_replans() << "): " << why << std::endl;
  if (paused_) {
    waiting_ = true;
    result_ = Result();
  } else {
    startAttempt();
  }
  return Verdict::keepGoing();
}

}  // namespace behaviorlib::nav
