#pragma once

// TAKE_OFF (goal-based): takes off through the platform's TAKE_OFF flight
// action to altitude_m above the take-off point, holding the vehicle's
// command lease while active, and finishes GOAL_ACHIEVED when the pose
// estimate has stayed within altitude_tolerance_m of the target with a
// vertical speed below max_vertical_speed_m_s for goal_dwell_s. The target
// is on the estimate; what the platform's own climb leaves (a drifting
// barometer, a converging EKF) is closed with vertical speeds, as often as
// the estimate moves away while the vehicle holds still.
//
//   checkSituation  before: flight controller answers, LANDED, battery >=
//                   min_battery_ratio, fresh pose estimate stating no more than
//                   max_pose_stddev_m of horizontal standard deviation (the
//                   pre-flight check: an EKF still converging); while active: no
//                   emergency, lease not taken; performance follows the battery
//                   and, once airborne, the wind (flight::WindWatch)
//   checkGoal       altitude within tolerance, small vertical speed, for a dwell
//   checkProgress   no climb towards the target over progress_window_s, or an
//                   unexpected landing: WRONG_PROGRESS
//   checkProcesses  stale pose/velocity estimate, unreachable flight controller,
//                   lease renewals failing: PROCESS_FAILURE
//   onDeactivate    leaves the vehicle hovering and releases the lease
//
// Config (its section of --config): the flight::FlightSettings keys plus
// altitude_tolerance_m [0.1], max_vertical_speed_m_s [0.1], goal_dwell_s [1],
// min_climb_m [0.1] (per progress window), max_pose_stddev_m [0.3] (0: no
// pre-flight check of the estimate).

#include <cmath>
#include <limits>
#include <memory>

#include "behaviorlib/behavior_execution_manager.h"
#include "behaviorlib/config/v1/basic_quadrotor_behaviors.pb.h"
#include "behaviorlib/flight_common/flight_monitoring.h"
#include "behaviorlib/flight_common/flight_support.h"
#include "behaviorlib/flight_common/vehicle.h"
#include "behaviorlib/flight_common/wind_watch.h"
#include "behaviorlib/v1/behaviors/basic_quadrotor_behaviors.pb.h"

namespace behaviorlib::basic {

class TakeOffBehavior final : public Behavior<v1::TakeOffParameters, config::v1::TakeOffConfig> {
 public:
  explicit TakeOffBehavior(flight::Vehicle& vehicle);

 protected:
  absl::Status onConfigure(const config::v1::TakeOffConfig& config) override;
  absl::Status onActivate() override;
  void onExecute() override;
  void onDeactivate() override;
  void onPause() override;
  void onResume() override;
  absl::Status onModify(const v1::TakeOffParameters& new_parameters) override;

  Situation checkSituation() override;
  Verdict checkGoal() override;
  Verdict checkProgress() override;
  Verdict checkProcesses() override;

 private:
  void correctAltitude();

  flight::Vehicle& vehicle_;
  flight::FlightSettings settings_;
  flight::WindWatch wind_;
  double altitude_tolerance_m_ = 0.1;
  double max_vertical_speed_m_s_ = 0.1;
  double min_climb_m_ = 0.1;
  double max_pose_stddev_m_ = 0.3;
  flight::DwellTracker dwell_{std::chrono::seconds(1)};
  // Hovering still after the take-off action, before correctAltitude acts:
  // the platform's own climb settles first.
  flight::DwellTracker settled_{std::chrono::seconds(1)};
  flight::ProgressWindow climb_{std::chrono::seconds(3)};

  // Activation state (worker thread only).
  bool active_ = false;
  std::unique_ptr<flight::VehicleLease> lease_;
  double origin_x_ = 0, origin_y_ = 0, origin_z_ = 0, origin_yaw_ = 0;
  double target_z_ = 0;
  // Altitude last commanded to the platform (NaN: a setpoint must be sent).
  double commanded_z_ = std::numeric_limits<double>::quiet_NaN();
  bool seen_airborne_ = false;
  // Closing the rest of the climb on the estimate (correctAltitude).
  bool correcting_ = false;
  // The last setpoint was this behavior's vertical speed of zero: the
  // platform holds the vehicle still, though it reports FLYING.
  bool holding_zero_speed_ = false;
  std::string command_error_;
  // Inputs read by checkProcesses() for the checks after it.
  flight::Held<v1::FlightStatus> status_;
  flight::Held<v1::PoseStamped> pose_;
  flight::Held<v1::TwistStamped> twist_;
};

/// Yaw (rad, CCW from +x) of a quaternion (w, x, y, z).
double yawOf(const v1::Quaternion& q);

}  // namespace behaviorlib::basic
