#pragma once

// What the behaviors that command the platform themselves share — the motion
// controllers (QUADROTOR_*_CONTROL) and the platform-control behaviors
// (MOVE_VERTICAL / MOVE_AT_SPEED / ROTATE_WITH_PLATFORM_CONTROL): the
// vehicle's command lease while active, their inputs (the pose and velocity
// estimates, the platform's flight status), their situation, and setpoints
// streamed under the lease. Each behavior owns one CommanderSupport and calls
// it from its hooks:
//
//   onConfigure     support_.configure(config)      // the FlightSettings keys
//   checkSituation  active ? support_.situationActive() : support_.situationBefore(now(), name())
//   onActivate      support_.begin(robotId() + "/" + name(), checks)   // estimate, checks, lease
//   checkProcesses  if (auto problem = support_.checkProcesses(now())) -> PROCESS_FAILURE
//   onExecute       support_.send(setpoint)
//   onPause         support_.holdHere()
//   onDeactivate    support_.end()     // releases the lease: the platform hovers
//
// Config keys (defaults in brackets): pose_timeout_s [0.5], lease_ttl_s [2],
// preempt_lease [false], min_battery_ratio [0.3], full_battery_ratio [0.6],
// progress_window_s [3], and the wind estimate's mass_kg, linear_drag_n_s_m,
// quadratic_drag_n_s2_m2, wind_time_constant_s, calm_wind_m_s [2],
// max_wind_m_s [10] (flight::FlightSettings). The performance estimate is the
// battery's factor times the wind's (flight::WindWatch, fed every tick by
// checkProcesses(), once by situationBefore()).

#include <yaml-cpp/yaml.h>

#include <functional>
#include <memory>
#include <optional>
#include <string>

#include "behaviorlib/behavior_execution_manager.h"
#include "behaviorlib/config/v1/flight.pb.h"
#include "behaviorlib/flight_common/flight_support.h"
#include "behaviorlib/flight_common/vehicle.h"
#include "behaviorlib/flight_common/wind_watch.h"
#include "behaviorlib/motion_control/motion_types.h"

namespace behaviorlib::motion_behaviors {

class CommanderSupport {
 public:
  explicit CommanderSupport(flight::Vehicle& vehicle) : vehicle_(vehicle) {}

  absl::Status configure(const config::v1::FlightConfig& config);
  const flight::FlightSettings& settings() const { return settings_; }

  /// Before activation: a flight controller that answers, FLYING or
  /// HOVERING, a fresh pose estimate, the battery, the lease free (unless
  /// preempt_lease); the performance follows the battery and the wind.
  Situation situationBefore(TimePoint now, const std::string& behavior);
  /// While active: no emergency, still flying, the battery; the performance
  /// follows the battery and the wind.
  Situation situationActive() const;

  /// Reads the first estimate (state()), runs `check` (the behavior's own
  /// parameter checks, which may use it), and only then takes the lease for
  /// `holder`. An error refuses the activation with nothing commanded.
  absl::Status begin(const std::string& holder,
                     const std::function<absl::Status()>& check = nullptr);
  /// Releases the lease (the platform hovers where the vehicle is). Safe to
  /// call twice.
  void end();
  bool active() const { return lease_ != nullptr; }

  /// Stale estimate, flight controller gone, lease lost or not renewed, a
  /// refused setpoint or a failure() reported: the problem; nullopt when all
  /// is well. Refreshes state(), pose(), twist().
  std::optional<std::string> checkProcesses(TimePoint now);
  /// Reports a failure for the next checkProcesses() (the first one stays).
  void fail(std::string problem);

  /// Streams a setpoint under the lease; a refusal is reported by the next
  /// checkProcesses(). False when it was not sent.
  bool send(v1::SetpointRequest setpoint);
  /// A position + yaw setpoint (world frame).
  void goTo(const Eigen::Vector3d& position_m, double yaw_rad);
  /// Holds the current position and yaw.
  void holdHere();

  const motion::StateEstimate& state() const { return state_; }
  double yawRad() const { return state_.yawRad(); }
  const v1::PoseStamped& pose() const { return *pose_; }
  const v1::TwistStamped& twist() const { return *twist_; }
  const flight::WindWatch& wind() const { return wind_; }

 private:
  flight::Vehicle& vehicle_;
  flight::FlightSettings settings_;
  std::unique_ptr<flight::VehicleLease> lease_;
  std::string failure_;
  flight::Held<v1::FlightStatus> status_;
  flight::Held<v1::PoseStamped> pose_;
  flight::Held<v1::TwistStamped> twist_;
  motion::StateEstimate state_;
  flight::WindWatch wind_;
};

}  // namespace behaviorlib::motion_behaviors
