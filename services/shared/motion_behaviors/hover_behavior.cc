#include "behaviorlib/motion_behaviors/hover_behavior.h"

#include "behaviorlib/flight_common/flight_monitoring.h"
#include "behaviorlib/motion_behaviors/motion_messages.h"
#include "behaviorlib/v1/behaviors/quadrotor_motion_with_mpc_control.pb.h"
#include "behaviorlib/v1/behaviors/quadrotor_motion_with_pid_control.pb.h"

namespace behaviorlib::motion_behaviors {

template <class Params>
HoverBehavior<Params>::HoverBehavior(flight::Vehicle& vehicle, MotionLink& link)
    : Behavior<Params, config::v1::MotionConfig>(referenceBehaviorOptions(Duration::zero())),
      support_(vehicle, link) {}

template <class Params>
absl::Status HoverBehavior<Params>::onConfigure(const config::v1::MotionConfig& config) {
  return support_.configure(config);
}

template <class Params>
absl::Status HoverBehavior<Params>::onActivate() {
  if (auto s = support_.begin(this->now(), this->activationId()); !s.ok()) return s;
  hold_m_ = support_.state().position_m;
  yaw_rad_ = support_.yawRad();
  return absl::OkStatus();
}

template <class Params>
void HoverBehavior<Params>::onExecute() {
  (void)support_.publish(holdAt(hold_m_, yaw_rad_), this->now());
}

template <class Params>
void HoverBehavior<Params>::onDeactivate() {
  support_.end();
}

template <class Params>
Situation HoverBehavior<Params>::checkSituation() {
  return support_.active() ? support_.situationActive()
                           : support_.situationBefore(this->now(), this->name());
}

template <class Params>
Verdict HoverBehavior<Params>::checkProgress() {
  const Eigen::Vector3d position = support_.state().position_m;
  const double drift = (position - hold_m_).norm();
  const double limit = this->parameters().max_drift_m();
  if (drift > limit) {
    return Verdict::finish("drifted " + flight::fixed2(drift) + " m from the hover point " +
                           pointText(hold_m_) + ", beyond max_drift_m " + flight::fixed2(limit));
  }
  return Verdict::keepGoing();
}

template <class Params>
Verdict HoverBehavior<Params>::checkProcesses() {
  if (auto problem = support_.checkProcesses(this->now())) return Verdict::finish(*problem);
  return Verdict::keepGoing();
}

template class HoverBehavior<v1::KeepHoveringWithPidControlParameters>;
template class HoverBehavior<v1::HoverWithMpcControlParameters>;

}  // namespace behaviorlib::motion_behaviors
