#include "behaviorlib/motion_behaviors/velocity_check.h"

#include "behaviorlib/motion_behaviors/motion_messages.h"

namespace behaviorlib::motion_behaviors {

std::optional<std::string> velocityProblem(const motion::StateEstimate& state,
                                           const Eigen::Vector3d& want, double min_altitude_m,
                                           double max_error_m_s, TimePoint now,
                                           TimePoint changed_at, flight::DwellTracker* off_speed) {
  using flight::fixed2;
  if (want.z() < 0.0 && state.position_m.z() < min_altitude_m) {
    return "descending at " + fixed2(want.z()) + " m/s the vehicle reached " +
           fixed2(state.position_m.z()) + " m, below min_altitude_m " + fixed2(min_altitude_m);
  }
  const double error = (state.velocity_m_s - want).norm();
  const bool settled = now - changed_at >= off_speed->dwell();
  if (off_speed->update(now, settled && error > max_error_m_s)) {
    return "the velocity has been more than " + fixed2(max_error_m_s) + " m/s from the request " +
           pointText(want) + " for " + flight::secondsText(off_speed->dwell()) + " (now " +
           pointText(state.velocity_m_s) + ")";
  }
  return std::nullopt;
}

}  // namespace behaviorlib::motion_behaviors
