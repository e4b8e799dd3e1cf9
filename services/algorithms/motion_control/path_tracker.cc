#include "behaviorlib/motion_control/path_tracker.h"

#include <algorithm>
#include <cmath>
#include <string>

namespace behaviorlib::motion {

PathTracker::PathTracker(std::vector<Eigen::Vector3d> waypoints, PathTrackerParams params)
    : waypoints_(std::move(waypoints)), params_(params) {}

absl::StatusOr<PathTracker> PathTracker::create(std::vector<Eigen::Vector3d> waypoints,
                                                PathTrackerParams params) {
  if (waypoints.empty()) return absl::InvalidArgumentError("path: the path has no point");
  for (size_t i = 0; i < waypoints.size(); ++i) {
    if (!waypoints[i].allFinite()) {
      return absl::InvalidArgumentError("path: point " + std::to_string(i) +
                                        " has a coordinate that is not a finite number");
    }
  }
  if (!(params.speed_m_s > 0.0) || params.speed_m_s > 20.0) {
    return absl::InvalidArgumentError("speed_m_s must be within (0, 20]");
  }
  if (!(params.acceleration_m_s2 > 0.0) || params.acceleration_m_s2 > 10.0) {
    return absl::InvalidArgumentError("acceleration_m_s2 must be within (0, 10]");
  }
  double length = 0.0;
  for (size_t i = 1; i < waypoints.size(); ++i) length += (waypoints[i] - waypoints[i - 1]).norm();
  if (length > params.max_length_m) {
    return absl::InvalidArgumentError("path: its length " + std::to_string(length) +
                                      " m exceeds the maximum of " +
                                      std::to_string(params.max_length_m) + " m");
  }
  PathTracker tracker(std::move(waypoints), params);
  tracker.start(tracker.waypoints_.front(), 0.0);
  return tracker;
}

void PathTracker::start(const Eigen::Vector3d& position_m, double yaw_rad) {
  startAt(position_m, yaw_rad, Eigen::Vector3d::Zero());
}

void PathTracker::continueFrom(const ReferencePoint& from, double yaw_rad) {
  startAt(from.position_m, yaw_rad, from.velocity_m_s);
}

void PathTracker::startAt(const Eigen::Vector3d& position_m, double yaw_rad,
                          const Eigen::Vector3d& velocity) {
  points_.clear();
  points_.push_back(position_m);
  for (const auto& w : waypoints_) {
    if ((w - points_.back()).norm() > 1e-6) points_.push_back(w);
  }
  yaw_rad_ = yaw_rad;
  time_s_ = 0.0;
  double entry = 0.0;
  if (points_.size() > 1) {
    entry = std::max(0.0, velocity.dot((points_[1] - points_[0]).normalized()));
  }
  plan(entry);
}

void PathTracker::plan(double entry_speed) {
  segments_.clear();
  length_m_ = 0.0;
  double t = 0.0;
  const double v = params_.speed_m_s, a = params_.acceleration_m_s2;
  for (size_t i = 1; i < points_.size(); ++i) {
    Segment s;
    s.start = points_[i - 1];
    const Eigen::Vector3d d = points_[i] - points_[i - 1];
    s.length = d.norm();
    s.direction = d / s.length;
    const double u = i == 1 ? entry_speed : 0.0;
    s.entry_speed = u;
    if (u * u >= 2.0 * a * s.length) {
      // Too short to stop in from u at a: brake at once, as hard as it takes.
      s.peak_speed = u;
      s.first_accel = 0.0;
      s.first_time = 0.0;
      s.braking = u * u / (2.0 * s.length);
      s.braking_time = 2.0 * s.length / u;
    } else {
      // Up (or down) from u to the peak, then down to rest, both at a; the
      // peak is the speed, or what the length allows.
      s.peak_speed = std::min(v, std::sqrt(a * s.length + 0.5 * u * u));
      s.first_accel = s.peak_speed >= u ? a : -a;
      s.first_time = std::abs(s.peak_speed - u) / a;
      s.braking = a;
      s.braking_time = s.peak_speed / a;
    }
    const double first_m = 0.5 * (u + s.peak_speed) * s.first_time;
    const double braking_m = 0.5 * s.peak_speed * s.braking_time;
    const double cruise_m = std::max(0.0, s.length - first_m - braking_m);
    s.duration = s.first_time + cruise_m / s.peak_speed + s.braking_time;
    s.start_time = t;
    t += s.duration;
    length_m_ += s.length;
    segments_.push_back(s);
  }
  total_time_s_ = t;
}

ReferencePoint PathTracker::sample(double t_s) const {
  ReferencePoint p;
  p.yaw_rad = yaw_rad_;
  if (segments_.empty()) {
    p.position_m = points_.back();
    return p;
  }
  if (t_s >= total_time_s_) {
    // At rest at the last point. (Computed within the last segment, the time
    // could fall a rounding error short of its end, and the reference kept the
    // braking acceleration for as long as it was held there.)
    p.position_m = points_.back();
    return p;
  }
  t_s = std::max(t_s, 0.0);
  auto it = std::upper_bound(segments_.begin(), segments_.end(), t_s,
                             [](double t, const Segment& s) { return t < s.start_time; });
  const Segment& s = *std::prev(it);
  const double tau = std::min(t_s - s.start_time, s.duration);
  double distance, speed, accel;
  if (tau < s.first_time) {
    distance = s.entry_speed * tau + 0.5 * s.first_accel * tau * tau;
    speed = s.entry_speed + s.first_accel * tau;
    accel = s.first_accel;
  } else if (tau < s.duration - s.braking_time) {
    distance =
        0.5 * (s.entry_speed + s.peak_speed) * s.first_time + s.peak_speed * (tau - s.first_time);
    speed = s.peak_speed;
    accel = 0.0;
  } else {
    const double left = s.duration - tau;
    distance = s.length - 0.5 * s.braking * left * left;
    speed = s.braking * left;
    accel = left > 0.0 ? -s.braking : 0.0;
  }
  p.position_m = s.start + s.direction * std::min(distance, s.length);
  p.velocity_m_s = s.direction * speed;
  p.acceleration_m_s2 = s.direction * accel;
  return p;
}

MotionReference PathTracker::update(const Eigen::Vector3d& position_m, double dt_s) {
  const double lag = lagM(position_m);
  const double half = 0.5 * params_.max_lag_m;
  const double rate = std::clamp((params_.max_lag_m - lag) / half, 0.0, 1.0);
  time_s_ = std::min(total_time_s_, time_s_ + rate * std::max(dt_s, 0.0));
  MotionReference reference;
  reference.mode = MotionReference::Mode::kTrajectory;
  reference.point = sample(time_s_);
  if (rate < 1.0) {
    // Waiting for the vehicle: no feed-forward pulling it along the path.
    reference.point.velocity_m_s *= rate;
    reference.point.acceleration_m_s2 *= rate;
  }
  reference.horizon_step_s = params_.horizon_step_s;
  reference.horizon.reserve(params_.horizon_steps);
  for (int k = 1; k <= params_.horizon_steps; ++k) {
    reference.horizon.push_back(sample(time_s_ + rate * k * params_.horizon_step_s));
  }
  return reference;
}

double PathTracker::crossTrackErrorM(const Eigen::Vector3d& position_m) const {
  if (segments_.empty()) return (position_m - points_.back()).norm();
  double best = std::numeric_limits<double>::infinity();
  for (const auto& s : segments_) {
    const double along = std::clamp((position_m - s.start).dot(s.direction), 0.0, s.length);
    best = std::min(best, (position_m - (s.start + s.direction * along)).norm());
  }
  return best;
}

double PathTracker::lagM(const Eigen::Vector3d& position_m) const {
  return (position_m - sample(time_s_).position_m).norm();
}

double PathTracker::remainingM() const {
  if (segments_.empty()) return 0.0;
  const ReferencePoint now = sample(time_s_);
  double remaining = 0.0;
  bool after = false;
  for (const auto& s : segments_) {
    if (after) {
      remaining += s.length;
    } else if (time_s_ < s.start_time + s.duration) {
      remaining += (s.start + s.direction * s.length - now.position_m).norm();
      after = true;
    }
  }
  return remaining;
}

}  // namespace behaviorlib::motion
