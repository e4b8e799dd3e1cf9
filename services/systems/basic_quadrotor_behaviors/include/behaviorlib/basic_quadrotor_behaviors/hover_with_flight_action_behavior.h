#pragma once

// HOVER_WITH_FLIGHT_ACTION_CONTROL (recurrent): holds the vehicle where it is
// through the platform's HOVER flight action, keeping the command lease
// while active, until deactivated.
//
//   checkSituation  before: flight controller answers, FLYING or HOVERING,
//                   battery >= min_battery_ratio, fresh pose estimate; while
//                   active: battery above the minimum (else SITUATION_CHANGE),
//                   no emergency, lease not taken; performance follows the battery
//                   and the wind (flight::WindWatch: the wind estimated from the
//                   vehicle's lean, every tick while active)
//   checkGoal       none (recurrent)
//   checkProgress   drift from the hover point beyond max_drift_m, or the
//                   platform leaving the hover: WRONG_PROGRESS
//   checkProcesses  stale pose estimate, unreachable flight controller, lease
//                   renewals failing: PROCESS_FAILURE
//   onDeactivate    releases the lease; the platform keeps hovering
//
// Config: the flight::FlightSettings keys.

#include <memory>

#include "behaviorlib/behavior_execution_manager.h"
#include "behaviorlib/config/v1/basic_quadrotor_behaviors.pb.h"
#include "behaviorlib/flight_common/flight_support.h"
#include "behaviorlib/flight_common/vehicle.h"
#include "behaviorlib/flight_common/wind_watch.h"
#include "behaviorlib/v1/behaviors/basic_quadrotor_behaviors.pb.h"

namespace behaviorlib::basic {

class HoverWithFlightActionControlBehavior final
    : public Behavior<v1::HoverWithFlightActionControlParameters, config::v1::FlightConfig> {
 public:
  explicit HoverWithFlightActionControlBehavior(flight::Vehicle& vehicle);

 protected:
  absl::Status onConfigure(const config::v1::FlightConfig& config) override;
  absl::Status onActivate() override;
  void onDeactivate() override;

  Situation checkSituation() override;
  Verdict checkProgress() override;
  Verdict checkProcesses() override;

 private:
  flight::Vehicle& vehicle_;
  flight::FlightSettings settings_;
  flight::WindWatch wind_;

  bool active_ = false;
  std::unique_ptr<flight::VehicleLease> lease_;
  double hover_x_ = 0, hover_y_ = 0, hover_z_ = 0;
  bool seen_hovering_ = false;
  flight::Held<v1::FlightStatus> status_;
  flight::Held<v1::PoseStamped> pose_;
};

}  // namespace behaviorlib::basic
