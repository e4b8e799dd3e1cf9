#pragma once

// What the high-level motion behaviors (FOLLOW_PATH*, ROTATE_WITH_*_CONTROL,
// KEEP_HOVERING_WITH_PID_CONTROL, KEEP_MOVING_WITH_PID_CONTROL,
// HOVER_WITH_MPC_CONTROL) share: their configuration, their inputs (the pose
// estimate, the platform's flight status), publishing motion references, and
// watching that a motion controller follows them. Each behavior derives from
// ReferenceBehavior, which owns one ReferenceSupport and calls it from the
// hooks they share (checkSituation, checkProcesses, onDeactivate); the
// behavior calls it from the others:
//
//   onConfigure     support().configure(config)
//   checkSituation  active ? support().situationActive() : support().situationBefore(now(), name())
//   onActivate      support().begin(now(), activationId())   // reads the first estimate
//   checkProcesses  if (auto problem = support().checkProcesses(now())) -> PROCESS_FAILURE
//   onExecute       support().publish(reference, now())
//   onDeactivate    support().end()
//
// They never command the platform: the active motion controller turns their
// references into setpoints.
//
// Config keys of each behavior's section (defaults in brackets), besides the
// library's frequency_hz, maximum_execution_time_s and watchdog_timeout_s:
//   pose_timeout_s [0.5]         pose/velocity estimate older than this: PROCESS_FAILURE
//   controller_timeout_s [0.5]   a controller status older than this, or one that
//                                followed none of this activation's references for
//                                this long: no controller follows (PROCESS_FAILURE)
//   controller_grace_s [1]       ... checked only after this long since activation (or since
//                                the status subscription was established, if later)
//   goal_dwell_s [1]             a goal condition must hold this long
//   progress_window_s [3]        window of the progress checks
//   min_altitude_m [0.2]         lowest altitude a reference may ask for
//   min_battery_ratio [0.3], full_battery_ratio [0.6]   as the flight behaviors
//   mass_kg, linear_drag_n_s_m, quadratic_drag_n_s2_m2, wind_time_constant_s,
//   calm_wind_m_s [2], max_wind_m_s [10]   the wind estimate (flight_common/wind_watch.h)
//
// The performance estimate (checkSituation) is the battery's factor times the
// wind's: the wind is estimated every tick from the lean of the vehicle
// (WindWatch), and once from the latest estimate before activation.

#include <yaml-cpp/yaml.h>

#include <optional>
#include <string>

#include "absl/status/status.h"
#include "behaviorlib/behavior_execution_manager.h"
#include "behaviorlib/config/v1/motion.pb.h"
#include "behaviorlib/flight_common/flight_support.h"
#include "behaviorlib/flight_common/vehicle.h"
#include "behaviorlib/flight_common/wind_watch.h"
#include "behaviorlib/motion_behaviors/motion_link.h"
#include "behaviorlib/motion_control/motion_types.h"
#include "behaviorlib/v1/motion.pb.h"

namespace behaviorlib::motion_behaviors {

struct MotionSettings {
  flight::FlightSettings flight;
  Duration controller_timeout = std::chrono::milliseconds(500);
  Duration controller_grace = std::chrono::seconds(1);
  Duration goal_dwell = std::chrono::seconds(1);
  double min_altitude_m = 0.2;

  /// Takes the decoded keys (flight keys included); INVALID_ARGUMENT when
  /// the rules between them do not hold.
  absl::Status configure(const config::v1::MotionConfig& config);
};

/// Execution defaults of the high-level motion behaviors: 50 Hz, the given
/// maximum execution time, a 2 s watchdog.
BehaviorOptions referenceBehaviorOptions(Duration maximum_execution_time);

class ReferenceSupport {
 public:
  ReferenceSupport(flight::Vehicle& vehicle, MotionLink& link);

  absl::Status configure(const config::v1::MotionConfig& config);
  const MotionSettings& settings() const { return settings_; }

  /// Before activation: a flight controller that answers, the vehicle
  /// FLYING or HOVERING, a fresh pose estimate, the battery above the
  /// minimum; the performance follows the battery and the wind.
  Situation situationBefore(TimePoint now, const std::string& behavior);
  /// While active (from the inputs checkProcesses() read): infeasible when
  /// the vehicle is no longer flying (landing, emergency) or the battery is
  /// below the minimum; the performance follows the battery and the wind.
  Situation situationActive() const;

  /// Starts following the estimate and the controller's status and reads
  /// the first estimate (an error refuses the activation). `source` (the
  /// activation id) names the references published from now on.
  absl::Status begin(TimePoint now, const std::string& source);
  /// Stops following. Safe to call twice.
  void end();
  bool active() const { return active_; }

  /// checkProcesses(): the flight controller answers, the pose and velocity
  /// estimates are fresh, and (after controller_grace_s) a motion controller
  /// publishes its status and follows this activation's references. The
  /// problem as a message; nullopt when all is well. Refreshes state().
  std::optional<std::string> checkProcesses(TimePoint now);

  /// Publishes `reference` stamped `now` under this activation's source.
  absl::Status publish(const motion::MotionReference& reference, TimePoint now);

  /// The estimate read by the last begin() or checkProcesses().
  const motion::StateEstimate& state() const { return state_; }
  double yawRad() const { return state_.yawRad(); }
  const v1::FlightStatus& flightStatus() const { return *status_; }
  /// The wind estimate (fed by checkProcesses()).
  const flight::WindWatch& wind() const { return wind_; }
  /// The controller that last followed this activation's references ("" if none).
  const std::string& controller() const { return controller_; }
  MotionLink& link() { return link_; }

 private:
  std::optional<std::string> checkController(TimePoint now);

  flight::Vehicle& vehicle_;
  MotionLink& link_;
  MotionSettings settings_;

  bool active_ = false;
  std::string source_;
  TimePoint began_{};
  TimePoint last_followed_{};
  std::string controller_;
  uint64_t seq_ = 0;
  flight::Held<v1::FlightStatus> status_;
  flight::Held<v1::PoseStamped> pose_;
  flight::Held<v1::TwistStamped> twist_;
  motion::StateEstimate state_;
  flight::WindWatch wind_;
};

/// The base of the behaviors that fly by publishing motion references
/// (FOLLOW_PATH*, ROTATE_WITH_*_CONTROL, KEEP_HOVERING_WITH_PID_CONTROL,
/// HOVER_WITH_MPC_CONTROL, KEEP_MOVING_WITH_PID_CONTROL,
/// EXPLORE_WITH_FRONTIERS): it owns their ReferenceSupport and gives the hooks
/// they share. One that overrides a hook and still wants this one calls it.
template <class Params, class Config>
class ReferenceBehavior : public Behavior<Params, Config> {
 protected:
  ReferenceBehavior(flight::Vehicle& vehicle, MotionLink& link, Duration maximum_execution_time)
      : Behavior<Params, Config>(referenceBehaviorOptions(maximum_execution_time)),
        support_(vehicle, link) {}

  /// Before activation: a flight controller, FLYING or HOVERING, a fresh
  /// estimate, the battery; while active: still flying, the battery.
  Situation checkSituation() override {
    return support_.active() ? support_.situationActive()
                             : support_.situationBefore(this->now(), this->name());
  }
  /// A stale estimate, a flight controller gone, no motion controller
  /// following: PROCESS_FAILURE.
  Verdict checkProcesses() override {
    if (auto problem = support_.checkProcesses(this->now())) return Verdict::finish(*problem);
    return Verdict::keepGoing();
  }
  /// Stops following the estimate and the controller's status.
  void onDeactivate() override { support_.end(); }

  ReferenceSupport& support() { return support_; }
  const ReferenceSupport& support() const { return support_; }

 private:
  ReferenceSupport support_;
};

}  // namespace behaviorlib::motion_behaviors
