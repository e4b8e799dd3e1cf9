#include "behaviorlib/quadrotor_motion_with_pid_control/keep_moving_behavior.h"

#include "behaviorlib/motion_behaviors/velocity_check.h"

namespace behaviorlib::motion_behaviors {

KeepMovingWithPidControlBehavior::KeepMovingWithPidControlBehavior(flight::Vehicle& vehicle,
                                                                   MotionLink& link)
    : Behavior(referenceBehaviorOptions(Duration::zero())), support_(vehicle, link) {}

absl::Status KeepMovingWithPidControlBehavior::onConfigure(const config::v1::MotionConfig& config) {
  if (auto s = support_.configure(config); !s.ok()) return s;
  off_speed_.setDwell(support_.settings().flight.progress_window);
  return absl::OkStatus();
}

Eigen::Vector3d KeepMovingWithPidControlBehavior::requested() const {
  const auto& p = parameters();
  return {p.velocity_x_m_s(), p.velocity_y_m_s(), p.velocity_z_m_s()};
}

absl::Status KeepMovingWithPidControlBehavior::onActivate() {
  if (auto s = support_.begin(now(), activationId()); !s.ok()) return s;
  off_speed_.reset();
  changed_at_ = now();
  return absl::OkStatus();
}

void KeepMovingWithPidControlBehavior::onExecute() {
  motion::MotionReference reference;
  reference.mode = motion::MotionReference::Mode::kVelocity;
  reference.point.position_m = support_.state().position_m;
  reference.point.velocity_m_s = requested();
  reference.point.yaw_rad = support_.yawRad();
  reference.yaw_rate_rad_s = parameters().yaw_rate_rad_s();
  (void)support_.publish(reference, now());
}

void KeepMovingWithPidControlBehavior::onDeactivate() { support_.end(); }

void KeepMovingWithPidControlBehavior::onResume() {
  off_speed_.reset();
  changed_at_ = now();
}

absl::Status KeepMovingWithPidControlBehavior::onModify(
    const v1::KeepMovingWithPidControlParameters&) {
  off_speed_.reset();
  changed_at_ = now();
  return absl::OkStatus();
}

Situation KeepMovingWithPidControlBehavior::checkSituation() {
  return support_.active() ? support_.situationActive() : support_.situationBefore(now(), name());
}

Verdict KeepMovingWithPidControlBehavior::checkProgress() {
  if (auto problem =
          velocityProblem(support_.state(), requested(), support_.settings().min_altitude_m,
                          parameters().max_speed_error_m_s(), now(), changed_at_, &off_speed_)) {
    return Verdict::finish(*problem);
  }
  return Verdict::keepGoing();
}

Verdict KeepMovingWithPidControlBehavior::checkProcesses() {
  if (auto problem = support_.checkProcesses(now())) return Verdict::finish(*problem);
  return Verdict::keepGoing();
}

}  // namespace behaviorlib::motion_behaviors
