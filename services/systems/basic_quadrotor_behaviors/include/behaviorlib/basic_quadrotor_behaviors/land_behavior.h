#pragma once

// LAND (goal-based): lands where the vehicle is through the platform's LAND
// flight action, holding the vehicle's command lease while active, and
// finishes GOAL_ACHIEVED when the platform reports LANDED.
//
//   checkSituation  before: flight controller answers, the vehicle in the air,
//                   fresh pose estimate; while active: no emergency, lease not
//                   taken; performance follows the battery and the wind
//                   (flight::WindWatch)
//   checkGoal       the platform reports LANDED
//   checkProgress   descent below min_descent_m over progress_window_s, a
//                   climb, or the platform leaving the landing: WRONG_PROGRESS
//   checkProcesses  stale pose estimate, unreachable flight controller, lease
//                   renewals failing: PROCESS_FAILURE
//   onDeactivate    before touch-down: hover where it is; releases the lease
//
// Config: the flight::FlightSettings keys plus min_descent_m [0.1] (per window).

#include <memory>

#include "behaviorlib/behavior_execution_manager.h"
#include "behaviorlib/config/v1/basic_quadrotor_behaviors.pb.h"
#include "behaviorlib/flight_common/flight_monitoring.h"
#include "behaviorlib/flight_common/flight_support.h"
#include "behaviorlib/flight_common/vehicle.h"
#include "behaviorlib/flight_common/wind_watch.h"
#include "behaviorlib/v1/behaviors/basic_quadrotor_behaviors.pb.h"

namespace behaviorlib::basic {

class LandBehavior final : public Behavior<v1::LandParameters, config::v1::LandConfig> {
 public:
  explicit LandBehavior(flight::Vehicle& vehicle);

 protected:
  absl::Status onConfigure(const config::v1::LandConfig& config) override;
  absl::Status onActivate() override;
  void onDeactivate() override;
  void onPause() override;
  void onResume() override;

  Situation checkSituation() override;
  Verdict checkGoal() override;
  Verdict checkProgress() override;
  Verdict checkProcesses() override;

 private:
  flight::Vehicle& vehicle_;
  flight::FlightSettings settings_;
  flight::WindWatch wind_;
  double min_descent_m_ = 0.1;
  flight::ProgressWindow descent_{std::chrono::seconds(3)};

  bool active_ = false;
  std::unique_ptr<flight::VehicleLease> lease_;
  bool seen_landing_ = false;
  std::string command_error_;
  flight::Held<v1::FlightStatus> status_;
  flight::Held<v1::PoseStamped> pose_;
};

}  // namespace behaviorlib::basic
