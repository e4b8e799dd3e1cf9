#include "behaviorlib/motion_behaviors/hover_behavior.h"

#include "behaviorlib/flight_common/flight_monitoring.h"
#include "behaviorlib/motion_behaviors/motion_messages.h"
#include "behaviorlib/v1/behaviors/quadrotor_motion_with_mpc_control.pb.h"
#include "behaviorlib/v1/behaviors/quadrotor_motion_with_pid_control.pb.h"

namespace behaviorlib::motion_behaviors {

template <class Params>
HoverBehavior<Params>::HoverBehavior(flight::Vehicle& vehicle, MotionLink& link)
    : ReferenceBehavior<Params, config::v1::MotionConfig>(vehicle, link, Duration::zero()) {}

template <class Params>
absl::Status HoverBehavior<Params>::onConfigure(const config::v1::MotionConfig& config) {
  return support().configure(config);
}

template <class Params>
absl::Status HoverBehavior<Params>::onActivate() {
  if (auto s = support().begin(this->now(), this->activationId()); !s.ok()) return s;
  hold_m_ = support().state().position_m;
  yaw_rad_ = support().yawRad();
  return absl::OkStatus();
}

template <class Params>
void HoverBehavior<Params>::onExecute() {
  (void)support().publish(holdAt(hold_m_, yaw_rad_), this->now());
}

template <class Params>
Verdict HoverBehavior<Params>::checkProgress() {
  const Eigen::Vector3d position = support().state().position_m;
  const double drift = (position - hold_m_).norm();
  const double limit = this->parameters().max_drift_m();
  if (drift > limit) {
    return Verdict::finish("drifted " + flight::fixed2(drift) + " m from the hover point " +
                           pointText(hold_m_) + ", beyond max_drift_m " + flight::fixed2(limit));
  }
  return Verdict::keepGoing();
}

template class HoverBehavior<v1::KeepHoveringWithPidControlParameters>;
template class HoverBehavior<v1::HoverWithMpcControlParameters>;

}  // namespace behaviorlib::motion_behaviors
