#pragma once

// What the flight behaviors (TAKE_OFF, LAND, HOVER_WITH_FLIGHT_ACTION_CONTROL,
// and the motion behaviors) share: their --config settings and the checks of their inputs.
//
// Config keys of each flight behavior's section (defaults in brackets; declared
// once in proto/behaviorlib/config/v1/flight.proto, FlightConfig):
//   pose_timeout_s [0.5]        pose/twist estimate older than this (behavior
//                               clock): PROCESS_FAILURE
//   lease_ttl_s [2]             ttl of the command lease (renewed every ttl/4)
//   preempt_lease [false]       take the lease from another holder
//   min_battery_ratio [0.3]     below it the behavior is infeasible
//   full_battery_ratio [0.6]    at or above it the performance estimate is 1
//   progress_window_s [3]       window of the progress checks
// and the wind estimate of the performance (flight_common/wind_watch.h):
//   mass_kg [1.5]               the airframe's mass
//   linear_drag_n_s_m [0.25]    its body-axis (x, y) drag: F = -(c1 v + c2 |v| v)
//   quadratic_drag_n_s2_m2 [0.04]
//   wind_time_constant_s [1]    low-pass filter of the estimate
//   calm_wind_m_s [2]           up to this wind the performance is not lowered
//   max_wind_m_s [10]           at and beyond it the wind's factor is 0.2
// plus the library's frequency_hz, maximum_execution_time_s, watchdog_timeout_s.

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <chrono>
#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "absl/functional/function_ref.h"
#include "absl/status/status.h"
#include "behaviorlib/behavior_execution_manager.h"
#include "behaviorlib/channel/channel_client.h"
#include "behaviorlib/config/v1/flight.pb.h"
#include "behaviorlib/flight_common/vehicle.h"
#include "behaviorlib/motion_control/wind_estimator.h"

namespace behaviorlib::flight {

/// Wall-time bound of a one-off read of the channel (GetLatest) from a
/// behavior's user function: under the behaviors' 1 s watchdog, with room
/// for a loaded machine (300 ms refused activations beside a CPU hog).
constexpr std::chrono::milliseconds kChannelReadTimeout{700};

struct FlightSettings {
  Duration pose_timeout = std::chrono::milliseconds(500);
  Duration lease_ttl = std::chrono::seconds(2);
  bool preempt_lease = false;
  double min_battery_ratio = 0.3;
  double full_battery_ratio = 0.6;
  Duration progress_window = std::chrono::seconds(3);
  /// The airframe's drag model and the wind estimate's filter.
  motion::WindEstimatorParams wind;
  /// Wind speeds (m/s) where the performance estimate starts to fall, and
  /// where it reaches its floor (x0.2).
  double calm_wind_m_s = 2.0;
  double max_wind_m_s = 10.0;

  /// Takes the decoded keys (ranges already checked) and checks the rules
  /// between them; INVALID_ARGUMENT naming the keys.
  absl::Status configure(const config::v1::FlightConfig& config);
};

/// Defaults of the flight behaviors' execution: 20 Hz, the given maximum
/// execution time, and a 2 s watchdog (a user function may make up to three
/// bounded calls to the flight controller and the channel).
BehaviorOptions flightBehaviorOptions(Duration maximum_execution_time);

/// True for the airborne states (TAKING_OFF, FLYING, HOVERING, LANDING).
bool airborne(v1::FlightState state);
/// True while the platform accepts setpoints: FLYING or HOVERING.
bool flying(v1::FlightState state);

/// A reason a situation is not suitable (the text of Situation::reasons),
/// with its code.
struct SituationProblem {
  v1::SituationReason code = v1::SITUATION_REASON_UNSPECIFIED;
  std::string reason;
};

/// Makes `situation` infeasible (performance 0) with `reason` as its first
/// reason, ahead of those already there.
void refuseFirst(Situation* situation, v1::SituationReason code, std::string reason);

/// A fresh sample's problem: "pose estimate on <topic> is 0.4 s old (limit
/// 0.25 s)"; nullopt when fresh. `what` names the input; it is called only
/// for a stale one, so that a check run every tick builds no string:
///   staleness([&] { return "the pose estimate on " + topic; }, header, now, limit)
std::optional<std::string> staleness(absl::FunctionRef<std::string()> what,
                                     const v1::Header& header, TimePoint now, Duration limit);

/// A sensor topic robots/{robot}/{name} that a behavior needs fresh before it
/// is activated, `what` naming the sensor in messages ("IMU", "lidar").
struct SensorNeed {
  std::string name;
  Duration limit;
  std::string what;
};
/// checkSituation() of the behaviors that read sensors off the data channel:
/// the newest sample of each topic (any message with a `header`) at most
/// twice its limit old (a little older than the timeout is fine before the
/// activation, where the channel read itself takes time). The first problem
/// ("no lidar: nothing on robots/drone1/lidar/scan ..."), with its code, or
/// nullopt.
std::optional<SituationProblem> missingSensor(channel::ChannelClient& channel,
                                              const std::string& robot_id,
                                              const std::vector<SensorNeed>& needs, TimePoint now);

/// checkProcesses() of the flight behaviors: the flight controller answers
/// (flight status known), the pose (and, if `need_twist`, twist) estimate is
/// fresh on the behavior clock, and the lease (if any) is still renewed. The
/// first problem found, as a message; nullopt when all is well. Takes the
/// latest into `status`, `pose`, `twist` (shared, not copied: it runs every
/// tick): on a problem, those read before it (a stale pose included) hold
/// the latest samples, the others are left as they were.
std::optional<std::string> checkFlightInputs(Vehicle& vehicle, TimePoint now,
                                             const FlightSettings& settings,
                                             const VehicleLease* lease, bool need_twist,
                                             Held<v1::FlightStatus>* status,
                                             Held<v1::PoseStamped>* pose,
                                             Held<v1::TwistStamped>* twist);

/// checkSituation() reasons shared by the flight behaviors before they are
/// activated: a flight controller that answers, a fresh pose estimate (and
/// velocity estimate, with `need_twist`: what checkFlightInputs will need,
/// so that an activation is not refused by its first tick because one
/// estimate arrived before the other) and the battery above the minimum.
/// Appends to `situation` and returns the flight status when known.
std::optional<v1::FlightStatus> checkFlightPreconditions(Vehicle& vehicle, TimePoint now,
                                                         const FlightSettings& settings,
                                                         bool check_battery, bool need_twist,
                                                         Situation* situation);

/// While active: the situation turns infeasible on an emergency or crash,
/// a lease taken by another holder, or (if `check_battery`) the battery
/// below the minimum; the performance follows the battery.
Situation activeFlightSituation(const v1::FlightStatus& status, const VehicleLease* lease,
                                const FlightSettings& settings, bool check_battery);

}  // namespace behaviorlib::flight
