#include "behaviorlib/motion_behaviors/follow_path_behavior.h"

#include <cmath>

#include "behaviorlib/motion_behaviors/motion_messages.h"
#include "behaviorlib/v1/behaviors/quadrotor_motion_with_mpc_control.pb.h"
#include "behaviorlib/v1/behaviors/quadrotor_motion_with_pid_control.pb.h"

namespace behaviorlib::motion_behaviors {

using flight::fixed2;
using flight::secondsText;

void PathSettings::configure(const config::v1::PathConfig& config) {
  max_path_length_m = config.max_path_length_m();
  max_path_points = config.max_path_points();
  max_lag_m = config.max_lag_m();
  max_cross_track_m = config.max_cross_track_m();
  min_progress_m = config.min_progress_m();
  horizon_steps = config.horizon_steps();
  horizon_step_s = config.horizon_spacing_s();
}

absl::StatusOr<motion::PathTracker> makePathTracker(
    const google::protobuf::RepeatedPtrField<v1::Vector3>& path, double speed_m_s,
    double acceleration_m_s2, const PathSettings& settings, double min_altitude_m) {
  if (path.empty()) return absl::InvalidArgumentError("parameter 'path_m' has no point");
  if (path.size() > settings.max_path_points) {
    return absl::InvalidArgumentError(
        "parameter 'path_m' has " + std::to_string(path.size()) + " points; at most " +
        std::to_string(settings.max_path_points) + " are accepted (max_path_points)");
  }
  std::vector<Eigen::Vector3d> points;
  points.reserve(path.size());
  for (int i = 0; i < path.size(); ++i) {
    const Eigen::Vector3d p = toEigen(path[i]);
    const std::string name = "parameter 'path_m[" + std::to_string(i) + "]'";
    if (!p.allFinite()) {
      return absl::InvalidArgumentError(name + " has a coordinate that is not a finite number");
    }
    if (p.z() < min_altitude_m) {
      return absl::InvalidArgumentError(name + " " + pointText(p) +
                                        " is below the minimum altitude " + fixed2(min_altitude_m) +
                                        " m (min_altitude_m)");
    }
    points.push_back(p);
  }
  motion::PathTrackerParams params;
  params.speed_m_s = speed_m_s;
  params.acceleration_m_s2 = acceleration_m_s2;
  params.max_lag_m = settings.max_lag_m;
  params.horizon_steps = settings.horizon_steps;
  params.horizon_step_s = settings.horizon_step_s;
  params.max_length_m = settings.max_path_length_m;
  auto tracker = motion::PathTracker::create(std::move(points), params);
  if (!tracker.ok()) {
    return absl::InvalidArgumentError(
        "parameter 'path_m': " + std::string(tracker.status().message()) + " (max_path_length_m)");
  }
  return tracker;
}

template <class Params>
FollowPathBehavior<Params>::FollowPathBehavior(flight::Vehicle& vehicle, MotionLink& link)
    : ReferenceBehavior<Params, config::v1::FollowPathConfig>(vehicle, link, Duration::zero()) {}

template <class Params>
absl::Status FollowPathBehavior<Params>::onConfigure(const config::v1::FollowPathConfig& config) {
  if (auto s = support().configure(config.motion()); !s.ok()) return s;
  path_settings_.configure(config.path());
  goal_.setDwell(support().settings().goal_dwell);
  lagging_.setDwell(support().settings().flight.progress_window);
  progress_.setWindow(support().settings().flight.progress_window);
  return absl::OkStatus();
}

template <class Params>
void FollowPathBehavior<Params>::restartWindows() {
  goal_.reset();
  lagging_.reset();
  progress_.reset();
  last_update_ = this->now();
}

template <class Params>
absl::Status FollowPathBehavior<Params>::onActivate() {
  const Params& p = this->parameters();
  auto tracker = makePathTracker(p.path_m(), p.speed_m_s(), p.acceleration_m_s2(), path_settings_,
                                 support().settings().min_altitude_m);
  if (!tracker.ok()) return tracker.status();
  if (auto s = support().begin(this->now(), this->activationId()); !s.ok()) return s;
  tracker_ = std::move(*tracker);
  tracker_->start(support().state().position_m, support().yawRad());
  tolerance_m_ = p.tolerance_m();
  if (this->options().maximum_execution_time == Duration::zero()) {
    this->setMaximumExecutionTime(seconds(3.0 * tracker_->totalTimeS() + 10.0));
  }
  cross_track_sum_sq_ = cross_track_max_ = 0.0;
  cross_track_samples_ = 0;
  restartWindows();
  return absl::OkStatus();
}

template <class Params>
void FollowPathBehavior<Params>::onExecute() {
  const TimePoint t = this->now();
  const double dt = std::chrono::duration<double>(t - last_update_).count();
  last_update_ = t;
  const motion::MotionReference reference = tracker_->update(support().state().position_m, dt);
  // A refused sample shows in the controller's status (it stops following).
  (void)support().publish(reference, t);
}

template <class Params>
void FollowPathBehavior<Params>::onDeactivate() {
  support().end();
  tracker_.reset();
}

template <class Params>
void FollowPathBehavior<Params>::onResume() {
  restartWindows();
}

template <class Params>
absl::Status FollowPathBehavior<Params>::onModify(const Params& p) {
  auto tracker = makePathTracker(p.path_m(), p.speed_m_s(), p.acceleration_m_s2(), path_settings_,
                                 support().settings().min_altitude_m);
  if (!tracker.ok()) return tracker.status();
  // Taken up from the reference where it is, without a jump or a stop: the
  // controller follows on, and no motion is lost to the change.
  tracker->continueFrom(tracker_->current(), support().yawRad());
  tracker_ = std::move(*tracker);
  tolerance_m_ = p.tolerance_m();
  restartWindows();
  return absl::OkStatus();
}

template <class Params>
Verdict FollowPathBehavior<Params>::checkGoal() {
  const Eigen::Vector3d position = support().state().position_m;
  const Eigen::Vector3d last = tracker_->points().back();
  const double distance = (position - last).norm();
  if (!goal_.update(this->now(), tracker_->referenceAtEnd() && distance <= tolerance_m_)) {
    return Verdict::keepGoing();
  }
  const double rms =
      cross_track_samples_ > 0
          ? std::sqrt(cross_track_sum_sq_ / static_cast<double>(cross_track_samples_))
          : 0.0;
  return Verdict::finish("reached the last waypoint " + pointText(last) + " within " +
                         fixed2(tolerance_m_) + " m for " + secondsText(goal_.dwell()) + "; " +
                         fixed2(tracker_->lengthM()) + " m flown, cross-track error RMS " +
                         fixed2(rms) + " m, max " + fixed2(cross_track_max_) + " m");
}

template <class Params>
Verdict FollowPathBehavior<Params>::checkProgress() {
  const TimePoint t = this->now();
  const Eigen::Vector3d position = support().state().position_m;
  const double cross_track = tracker_->crossTrackErrorM(position);
  cross_track_sum_sq_ += cross_track * cross_track;
  cross_track_max_ = std::max(cross_track_max_, cross_track);
  ++cross_track_samples_;
  if (cross_track > path_settings_.max_cross_track_m) {
    return Verdict::finish("the vehicle is " + fixed2(cross_track) + " m from the path at " +
                           pointText(position) + " (max_cross_track_m " +
                           fixed2(path_settings_.max_cross_track_m) + ")");
  }
  const double lag = tracker_->lagM(position);
  if (lagging_.update(t, lag >= 0.8 * path_settings_.max_lag_m)) {
    return Verdict::finish("the vehicle has lagged the reference by at least " +
                           fixed2(0.8 * path_settings_.max_lag_m) + " m for " +
                           secondsText(lagging_.dwell()) + " (now " + fixed2(lag) + " m, at " +
                           pointText(position) + ")");
  }
  if (!tracker_->referenceAtEnd()) {
    progress_.add(t, tracker_->lengthM() - tracker_->remainingM());
    if (progress_.full() && progress_.change() < path_settings_.min_progress_m) {
      return Verdict::finish("no progress along the path: " + fixed2(progress_.change()) +
                             " m in " + secondsText(progress_.window()) + " (min_progress_m " +
                             fixed2(path_settings_.min_progress_m) + "), " +
                             fixed2(tracker_->remainingM()) + " m to go");
    }
  } else {
    progress_.reset();
  }
  return Verdict::keepGoing();
}

template class FollowPathBehavior<v1::FollowPathParameters>;
template class FollowPathBehavior<v1::FollowPathWithMpcControlParameters>;

}  // namespace behaviorlib::motion_behaviors
