#include "behaviorlib/quadrotor_motion_with_platform_control/platform_behaviors.h"

#include <cmath>
#include <numbers>

#include "behaviorlib/motion_behaviors/motion_messages.h"
#include "behaviorlib/motion_behaviors/reference_support.h"
#include "behaviorlib/motion_behaviors/rotate_behavior.h"
#include "behaviorlib/motion_behaviors/velocity_check.h"

namespace behaviorlib::platform_motion {

using flight::fixed2;
using flight::secondsText;
using motion_behaviors::pointText;

namespace {

BehaviorOptions platformBehaviorOptions(Duration maximum_execution_time) {
  BehaviorOptions options;
  options.frequency_hz = 20.0;
  options.maximum_execution_time = maximum_execution_time;
  options.watchdog_timeout = std::chrono::seconds(2);
  return options;
}

std::string degrees(double rad) { return fixed2(rad * 180.0 / std::numbers::pi) + " deg"; }

}  // namespace

void PlatformMotionSettings::configure(const config::v1::PlatformMotionConfig& config) {
  goal_dwell = seconds(config.goal_dwell_s());
  min_altitude_m = config.min_altitude_m();
  max_drift_m = config.max_drift_m();
  min_progress_m = config.min_progress_m();
}

// ---- MOVE_VERTICAL_WITH_PLATFORM_CONTROL ----------------------------------

MoveVerticalBehavior::MoveVerticalBehavior(flight::Vehicle& vehicle)
    : Behavior(platformBehaviorOptions(std::chrono::seconds(120))), support_(vehicle) {}

absl::Status MoveVerticalBehavior::onConfigure(
    const config::v1::MoveVerticalWithPlatformControlConfig& config) {
  if (auto s = support_.configure(config.platform().flight()); !s.ok()) return s;
  settings_.configure(config.platform());
  max_vertical_speed_m_s_ = config.max_vertical_speed_m_s();
  goal_.setDwell(settings_.goal_dwell);
  progress_.setWindow(support_.settings().progress_window);
  return absl::OkStatus();
}

absl::StatusOr<double> MoveVerticalBehavior::targetOf(
    const v1::MoveVerticalWithPlatformControlParameters& p) const {
  if (p.has_altitude_m() == p.has_distance_m()) {
    return absl::InvalidArgumentError(
        "set exactly one of parameter 'altitude_m' (where to go) and parameter 'distance_m' (how "
        "far to move)");
  }
  const double target = p.has_altitude_m() ? p.altitude_m() : start_z_m_ + p.distance_m();
  if (target < settings_.min_altitude_m) {
    return absl::InvalidArgumentError(
        std::string("parameter '") + (p.has_altitude_m() ? "altitude_m" : "distance_m") +
        "' leads to " + fixed2(target) + " m, below the minimum altitude " +
        fixed2(settings_.min_altitude_m) + " m (min_altitude_m)");
  }
  return target;
}

void MoveVerticalBehavior::restart() {
  goal_.reset();
  progress_.reset();
  reference_z_m_ = support_.state().position_m.z();
  last_update_ = now();
}

absl::Status MoveVerticalBehavior::onActivate() {
  auto check = [this]() -> absl::Status {
    hold_m_ = support_.state().position_m;
    start_z_m_ = hold_m_.z();
    yaw_rad_ = support_.yawRad();
    auto target = targetOf(parameters());
    if (!target.ok()) return target.status();
    target_z_m_ = *target;
    return absl::OkStatus();
  };
  if (auto s = support_.begin(robotId() + "/" + name(), check); !s.ok()) return s;
  restart();
  return absl::OkStatus();
}

void MoveVerticalBehavior::onExecute() {
  const TimePoint t = now();
  const double step = parameters().speed_m_s() * std::max(toSeconds(t - last_update_), 0.0);
  last_update_ = t;
  const double to_go = target_z_m_ - reference_z_m_;
  reference_z_m_ =
      std::abs(to_go) <= step ? target_z_m_ : reference_z_m_ + std::copysign(step, to_go);
  support_.goTo({hold_m_.x(), hold_m_.y(), reference_z_m_}, yaw_rad_);
}

void MoveVerticalBehavior::onDeactivate() { support_.end(); }

void MoveVerticalBehavior::onPause() { support_.holdHere(); }

void MoveVerticalBehavior::onResume() { restart(); }

absl::Status MoveVerticalBehavior::onModify(
    const v1::MoveVerticalWithPlatformControlParameters& new_parameters) {
  auto target = targetOf(new_parameters);
  if (!target.ok()) return target.status();
  target_z_m_ = *target;
  restart();
  return absl::OkStatus();
}

Situation MoveVerticalBehavior::checkSituation() {
  return support_.active() ? support_.situationActive() : support_.situationBefore(now(), name());
}

Verdict MoveVerticalBehavior::checkGoal() {
  const double z = support_.state().position_m.z();
  const double vz = support_.state().velocity_m_s.z();
  const double tolerance = parameters().tolerance_m();
  const bool holds =
      std::abs(z - target_z_m_) <= tolerance && std::abs(vz) <= max_vertical_speed_m_s_;
  if (!goal_.update(now(), holds)) return Verdict::keepGoing();
  return Verdict::finish("at " + fixed2(z) + " m (target " + fixed2(target_z_m_) +
                         " m, tolerance " + fixed2(tolerance) + " m) for " +
                         secondsText(goal_.dwell()));
}

Verdict MoveVerticalBehavior::checkProgress() {
  const Eigen::Vector3d p = support_.state().position_m;
  const double drift = std::hypot(p.x() - hold_m_.x(), p.y() - hold_m_.y());
  if (drift > settings_.max_drift_m) {
    return Verdict::finish("drifted " + fixed2(drift) + " m sideways from " + pointText(hold_m_) +
                           " (max_drift_m " + fixed2(settings_.max_drift_m) + ")");
  }
  progress_.add(now(), p.z());
  const double to_go = target_z_m_ - p.z();
  if (progress_.full() && std::abs(to_go) > parameters().tolerance_m()) {
    const double towards = to_go > 0 ? progress_.change() : -progress_.change();
    if (towards < settings_.min_progress_m) {
      return Verdict::finish("no progress towards " + fixed2(target_z_m_) + " m: altitude " +
                             fixed2(p.z()) + " m, moved " + fixed2(towards) + " m towards it in " +
                             secondsText(progress_.window()) + " (min_progress_m " +
                             fixed2(settings_.min_progress_m) + ")");
    }
  }
  return Verdict::keepGoing();
}

Verdict MoveVerticalBehavior::checkProcesses() {
  if (auto problem = support_.checkProcesses(now())) return Verdict::finish(*problem);
  return Verdict::keepGoing();
}

// ---- MOVE_AT_SPEED_WITH_PLATFORM_CONTROL ----------------------------------

MoveAtSpeedBehavior::MoveAtSpeedBehavior(flight::Vehicle& vehicle)
    : Behavior(platformBehaviorOptions(Duration::zero())), support_(vehicle) {}

absl::Status MoveAtSpeedBehavior::onConfigure(
    const config::v1::MoveAtSpeedWithPlatformControlConfig& config) {
  if (auto s = support_.configure(config.platform().flight()); !s.ok()) return s;
  settings_.configure(config.platform());
  max_speed_error_m_s_ = config.max_speed_error_m_s();
  off_speed_.setDwell(support_.settings().progress_window);
  return absl::OkStatus();
}

Eigen::Vector3d MoveAtSpeedBehavior::requested() const {
  const auto& p = parameters();
  return {p.velocity_x_m_s(), p.velocity_y_m_s(), p.velocity_z_m_s()};
}

absl::Status MoveAtSpeedBehavior::onActivate() {
  if (auto s = support_.begin(robotId() + "/" + name()); !s.ok()) return s;
  off_speed_.reset();
  changed_at_ = now();
  return absl::OkStatus();
}

void MoveAtSpeedBehavior::onExecute() {
  v1::SetpointRequest setpoint;
  motion_behaviors::toProto(requested(),
                            setpoint.mutable_velocity_yaw_rate()->mutable_velocity_m_s());
  setpoint.mutable_velocity_yaw_rate()->set_yaw_rate_rad_s(parameters().yaw_rate_rad_s());
  support_.send(std::move(setpoint));
}

void MoveAtSpeedBehavior::onDeactivate() { support_.end(); }

void MoveAtSpeedBehavior::onPause() { support_.holdHere(); }

void MoveAtSpeedBehavior::onResume() {
  off_speed_.reset();
  changed_at_ = now();
}

absl::Status MoveAtSpeedBehavior::onModify(const v1::MoveAtSpeedWithPlatformControlParameters&) {
  off_speed_.reset();
  changed_at_ = now();
  return absl::OkStatus();
}

Situation MoveAtSpeedBehavior::checkSituation() {
  return support_.active() ? support_.situationActive() : support_.situationBefore(now(), name());
}

Verdict MoveAtSpeedBehavior::checkGoal() {
  const double duration = parameters().duration_s();
  if (duration <= 0.0 || toSeconds(activeTime()) < duration) return Verdict::keepGoing();
  return Verdict::finish("moved at " + pointText(requested()) + " m/s for " +
                         secondsText(activeTime()));
}

Verdict MoveAtSpeedBehavior::checkProgress() {
  if (auto problem = motion_behaviors::velocityProblem(
          support_.state(), requested(), settings_.min_altitude_m, max_speed_error_m_s_, now(),
          changed_at_, &off_speed_)) {
    return Verdict::finish(*problem);
  }
  return Verdict::keepGoing();
}

Verdict MoveAtSpeedBehavior::checkProcesses() {
  if (auto problem = support_.checkProcesses(now())) return Verdict::finish(*problem);
  return Verdict::keepGoing();
}

// ---- ROTATE_WITH_PLATFORM_CONTROL -----------------------------------------

RotateWithPlatformControlBehavior::RotateWithPlatformControlBehavior(flight::Vehicle& vehicle)
    : Behavior(platformBehaviorOptions(std::chrono::seconds(60))), support_(vehicle) {}

absl::Status RotateWithPlatformControlBehavior::onConfigure(
    const config::v1::RotateWithPlatformControlConfig& config) {
  if (auto s = support_.configure(config.platform().flight()); !s.ok()) return s;
  settings_.configure(config.platform());
  max_yaw_lag_rad_ = config.max_yaw_lag_rad();
  goal_.setDwell(settings_.goal_dwell);
  lagging_.setDwell(support_.settings().progress_window);
  return absl::OkStatus();
}

void RotateWithPlatformControlBehavior::setTarget(
    const v1::RotateWithPlatformControlParameters& p) {
  target_yaw_rad_ = motion::wrapAngle(p.relative() ? start_yaw_rad_ + p.yaw_rad() : p.yaw_rad());
  goal_.reset();
  lagging_.reset();
}

absl::Status RotateWithPlatformControlBehavior::onActivate() {
  if (auto s = support_.begin(robotId() + "/" + name()); !s.ok()) return s;
  hold_m_ = support_.state().position_m;
  start_yaw_rad_ = reference_yaw_rad_ = support_.yawRad();
  setTarget(parameters());
  last_update_ = now();
  return absl::OkStatus();
}

void RotateWithPlatformControlBehavior::onExecute() {
  const TimePoint t = now();
  const double step = parameters().yaw_rate_rad_s() * std::max(toSeconds(t - last_update_), 0.0);
  last_update_ = t;
  reference_yaw_rad_ = motion_behaviors::turnTowards(reference_yaw_rad_, target_yaw_rad_, step);
  support_.goTo(hold_m_, reference_yaw_rad_);
}

void RotateWithPlatformControlBehavior::onDeactivate() { support_.end(); }

void RotateWithPlatformControlBehavior::onPause() { support_.holdHere(); }

void RotateWithPlatformControlBehavior::onResume() {
  reference_yaw_rad_ = support_.yawRad();
  last_update_ = now();
  goal_.reset();
  lagging_.reset();
}

absl::Status RotateWithPlatformControlBehavior::onModify(
    const v1::RotateWithPlatformControlParameters& new_parameters) {
  setTarget(new_parameters);
  return absl::OkStatus();
}

Situation RotateWithPlatformControlBehavior::checkSituation() {
  return support_.active() ? support_.situationActive() : support_.situationBefore(now(), name());
}

Verdict RotateWithPlatformControlBehavior::checkGoal() {
  const double yaw = support_.yawRad();
  const double error = motion::wrapAngle(yaw - target_yaw_rad_);
  const double tolerance = parameters().tolerance_rad();
  if (!goal_.update(now(), std::abs(error) <= tolerance)) return Verdict::keepGoing();
  return Verdict::finish("yaw " + degrees(yaw) + " within " + degrees(tolerance) + " of " +
                         degrees(target_yaw_rad_) + " for " + secondsText(goal_.dwell()));
}

Verdict RotateWithPlatformControlBehavior::checkProgress() {
  const double drift = (support_.state().position_m - hold_m_).norm();
  if (drift > settings_.max_drift_m) {
    return Verdict::finish("drifted " + fixed2(drift) + " m from " + pointText(hold_m_) +
                           " while turning (max_drift_m " + fixed2(settings_.max_drift_m) + ")");
  }
  const double lag = std::abs(motion::wrapAngle(support_.yawRad() - reference_yaw_rad_));
  if (lagging_.update(now(), lag > max_yaw_lag_rad_)) {
    return Verdict::finish("the yaw has been more than " + degrees(max_yaw_lag_rad_) +
                           " behind the setpoint for " + secondsText(lagging_.dwell()));
  }
  return Verdict::keepGoing();
}

Verdict RotateWithPlatformControlBehavior::checkProcesses() {
  if (auto problem = support_.checkProcesses(now())) return Verdict::finish(*problem);
  return Verdict::keepGoing();
}

}  // namespace behaviorlib::platform_motion
