#include "behaviorlib/motion_behaviors/rotate_behavior.h"

#include <cmath>
#include <numbers>

#include "behaviorlib/motion_behaviors/motion_messages.h"
#include "behaviorlib/v1/behaviors/quadrotor_motion_with_mpc_control.pb.h"
#include "behaviorlib/v1/behaviors/quadrotor_motion_with_pid_control.pb.h"

namespace behaviorlib::motion_behaviors {

using flight::fixed2;
using flight::secondsText;

namespace {

std::string degrees(double rad) { return fixed2(rad * 180.0 / std::numbers::pi) + " deg"; }

}  // namespace

double turnTowards(double current, double target, double step) {
  const double error = motion::wrapAngle(target - current);
  if (std::abs(error) <= step) return motion::wrapAngle(target);
  return motion::wrapAngle(current + std::copysign(step, error));
}

template <class Params>
RotateBehavior<Params>::RotateBehavior(flight::Vehicle& vehicle, MotionLink& link)
    : ReferenceBehavior<Params, config::v1::RotateConfig>(vehicle, link, std::chrono::seconds(60)) {
}

template <class Params>
absl::Status RotateBehavior<Params>::onConfigure(const config::v1::RotateConfig& config) {
  if (auto s = support().configure(config.motion()); !s.ok()) return s;
  max_drift_m_ = config.max_drift_m();
  max_yaw_lag_rad_ = config.max_yaw_lag_rad();
  goal_.setDwell(support().settings().goal_dwell);
  lagging_.setDwell(support().settings().flight.progress_window);
  return absl::OkStatus();
}

template <class Params>
void RotateBehavior<Params>::setTarget(const Params& p) {
  target_yaw_rad_ = motion::wrapAngle(p.relative() ? start_yaw_rad_ + p.yaw_rad() : p.yaw_rad());
  goal_.reset();
  lagging_.reset();
}

template <class Params>
absl::Status RotateBehavior<Params>::onActivate() {
  if (auto s = support().begin(this->now(), this->activationId()); !s.ok()) return s;
  hold_m_ = support().state().position_m;
  start_yaw_rad_ = reference_yaw_rad_ = support().yawRad();
  setTarget(this->parameters());
  last_update_ = this->now();
  return absl::OkStatus();
}

template <class Params>
void RotateBehavior<Params>::onExecute() {
  const TimePoint t = this->now();
  const double dt = std::chrono::duration<double>(t - last_update_).count();
  last_update_ = t;
  reference_yaw_rad_ = turnTowards(reference_yaw_rad_, target_yaw_rad_,
                                   this->parameters().yaw_rate_rad_s() * std::max(dt, 0.0));
  (void)support().publish(holdAt(hold_m_, reference_yaw_rad_), t);
}

template <class Params>
void RotateBehavior<Params>::onResume() {
  last_update_ = this->now();
  goal_.reset();
  lagging_.reset();
}

template <class Params>
absl::Status RotateBehavior<Params>::onModify(const Params& new_parameters) {
  setTarget(new_parameters);
  return absl::OkStatus();
}

template <class Params>
Verdict RotateBehavior<Params>::checkGoal() {
  const double yaw = support().yawRad();
  const double error = motion::wrapAngle(yaw - target_yaw_rad_);
  const double tolerance = this->parameters().tolerance_rad();
  if (!goal_.update(this->now(), std::abs(error) <= tolerance)) return Verdict::keepGoing();
  return Verdict::finish("yaw " + degrees(yaw) + " within " + degrees(tolerance) + " of " +
                         degrees(target_yaw_rad_) + " for " + secondsText(goal_.dwell()) +
                         " (error " + degrees(error) + ")");
}

template <class Params>
Verdict RotateBehavior<Params>::checkProgress() {
  const Eigen::Vector3d position = support().state().position_m;
  const double drift = (position - hold_m_).norm();
  if (drift > max_drift_m_) {
    return Verdict::finish("drifted " + fixed2(drift) + " m from " + pointText(hold_m_) +
                           " while turning (max_drift_m " + fixed2(max_drift_m_) + ")");
  }
  const double lag = std::abs(motion::wrapAngle(support().yawRad() - reference_yaw_rad_));
  if (lagging_.update(this->now(), lag > max_yaw_lag_rad_)) {
    return Verdict::finish("the yaw has been more than " + degrees(max_yaw_lag_rad_) +
                           " behind the reference for " + secondsText(lagging_.dwell()) + " (now " +
                           degrees(lag) + ")");
  }
  return Verdict::keepGoing();
}

template class RotateBehavior<v1::RotateWithPidControlParameters>;
template class RotateBehavior<v1::RotateWithMpcControlParameters>;

}  // namespace behaviorlib::motion_behaviors
