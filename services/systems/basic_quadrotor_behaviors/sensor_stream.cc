#include "behaviorlib/basic_quadrotor_behaviors/sensor_stream.h"

#include "behaviorlib/flight_common/flight_monitoring.h"

namespace behaviorlib::basic {

std::optional<std::string> SensorStream::problem(TimePoint now, TimePoint activated_at) const {
  if (!last_) {
    if (now - activated_at > timeout_) {
      return "no sample on " + topic_ + " within " + flight::secondsText(timeout_) +
             " of the activation";
    }
    return std::nullopt;
  }
  if (now - *last_ > timeout_) {
    return "the sensor on " + topic_ + " is silent: last sample " +
           flight::secondsText(now - *last_) + " ago (limit " + flight::secondsText(timeout_) + ")";
  }
  if (frozen_timeout_ > Duration::zero()) {
    const auto frozen = seconds(frozen_.frozenForS());
    if (frozen > frozen_timeout_) {
      return "the sensor on " + topic_ + " is frozen: the same value for " +
             flight::secondsText(frozen) + " (limit " + flight::secondsText(frozen_timeout_) + ")";
    }
  }
  return std::nullopt;
}

}  // namespace behaviorlib::basic
