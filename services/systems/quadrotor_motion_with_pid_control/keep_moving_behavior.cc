#include "behaviorlib/quadrotor_motion_with_pid_control/keep_moving_behavior.h"

#include "behaviorlib/motion_behaviors/velocity_check.h"

namespace behaviorlib::motion_behaviors {

KeepMovingWithPidControlBehavior::KeepMovingWithPidControlBehavior(flight::Vehicle& vehicle,
                                                                   MotionLink& link)
    : ReferenceBehavior(vehicle, link, Duration::zero()) {}

absl::Status KeepMovingWithPidControlBehavior::onConfigure(const config::v1::MotionConfig& config) {
  if (auto s = support().configure(config); !s.ok()) return s;
  off_speed_.setDwell(support().settings().flight.progress_window);
  return absl::OkStatus();
}

Eigen::Vector3d KeepMovingWithPidControlBehavior::requested() const {
  const auto& p = parameters();
  return {p.velocity_x_m_s(), p.velocity_y_m_s(), p.velocity_z_m_s()};
}

absl::Status KeepMovingWithPidControlBehavior::onActivate() {
  if (auto s = support().begin(now(), activationId()); !s.ok()) return s;
  off_speed_.reset();
  changed_at_ = now();
  return absl::OkStatus();
}

void KeepMovingWithPidControlBehavior::onExecute() {
  motion::MotionReference reference;
  reference.mode = motion::MotionReference::Mode::kVelocity;
  reference.point.position_m = support().state().position_m;
  reference.point.velocity_m_s = requested();
  reference.point.yaw_rad = support().yawRad();
  reference.yaw_rate_rad_s = parameters().yaw_rate_rad_s();
  (void)support().publish(reference, now());
}

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

Verdict KeepMovingWithPidControlBehavior::checkProgress() {
  if (auto problem =
          velocityProblem(support().state(), requested(), support().settings().min_altitude_m,
                          parameters().max_speed_error_m_s(), now(), changed_at_, &off_speed_)) {
    return Verdict::finish(*problem);
  }
  return Verdict::keepGoing();
}

}  // namespace behaviorlib::motion_behaviors
