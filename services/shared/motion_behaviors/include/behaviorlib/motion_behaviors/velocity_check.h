#pragma once

// checkProgress() of the behaviors that keep a constant velocity
// (KEEP_MOVING_WITH_PID_CONTROL, MOVE_AT_SPEED_WITH_PLATFORM_CONTROL).

#include <Eigen/Core>
#include <optional>
#include <string>

#include "behaviorlib/clock.h"
#include "behaviorlib/flight_common/flight_monitoring.h"
#include "behaviorlib/motion_control/motion_types.h"

namespace behaviorlib::motion_behaviors {

/// A descent (`want` z < 0) that took the vehicle below `min_altitude_m`, or
/// the estimated velocity more than `max_error_m_s` from `want` for a whole
/// `off_speed` dwell, the first dwell after `changed_at` (the acceleration)
/// not counted. The problem as a message; nullopt when all is well.
std::optional<std::string> velocityProblem(const motion::StateEstimate& state,
                                           const Eigen::Vector3d& want, double min_altitude_m,
                                           double max_error_m_s, TimePoint now,
                                           TimePoint changed_at, flight::DwellTracker* off_speed);

}  // namespace behaviorlib::motion_behaviors
