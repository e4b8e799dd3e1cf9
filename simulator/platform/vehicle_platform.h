#pragma once

// VehiclePlatform: the autopilot logic of one vehicle that sits above the
// control loops, independent of gRPC and of the physics: the command-source
// lease, the flight-state machine (the paper's LANDED, TAKING_OFF, FLYING,
// HOVERING, LANDING, EMERGENCY), the lease-loss failsafe (hover, then land, as
// autopilots do on offboard loss) and the validation of commands.
//
//   VehiclePlatform platform("drone1", {});
//   auto lease = platform.acquireLease("controller", 500ms, false, now);
//   platform.executeAction(v1::FLIGHT_ACTION_TAKE_OFF, lease->lease_id, 2.0, false, now);
//   every physics step:
//     platform.update(now, snapshot);             // state machine, lease expiry
//     autopilot.track(platform.command());        // what to fly now
//
// All times are simulated time. Not thread-safe: the simulator serializes
// calls (one mutex per world).

#include <Eigen/Geometry>
#include <chrono>
#include <string>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "behaviorlib/v1/platform.pb.h"

namespace behaviorlib::sim {

using SimDuration = std::chrono::nanoseconds;
using SimTime = std::chrono::nanoseconds;  // since the simulation epoch

/// What the platform knows of the vehicle each step.
struct VehicleSnapshot {
  Eigen::Vector3d position_m = Eigen::Vector3d::Zero();    ///< world ENU
  Eigen::Vector3d velocity_m_s = Eigen::Vector3d::Zero();  ///< world ENU
  /// Acceleration over the last step, world ENU; zero while resting.
  Eigen::Vector3d acceleration_m_s2 = Eigen::Vector3d::Zero();
  double yaw_rad = 0.0;  ///< counter-clockwise from +x (east)
  Eigen::Quaterniond orientation = Eigen::Quaterniond::Identity();   ///< world <- body
  Eigen::Vector3d angular_velocity_rad_s = Eigen::Vector3d::Zero();  ///< body FLU
  bool on_ground = true;  ///< resting on the ground (landed)
  bool crashed = false;   ///< hard impact or collision
  double battery_ratio = 1.0;
  double battery_voltage_v = 0.0;  ///< terminal voltage under the present load
  double battery_current_a = 0.0;  ///< drawn from the battery
};

/// What the control loops should track now.
struct PlatformCommand {
  enum class Kind { kIdle, kThrustRates, kAttitudeThrust, kVelocityYawRate, kPositionYaw };
  Kind kind = Kind::kIdle;                                          ///< kIdle: motors off
  Eigen::Vector3d vector = Eigen::Vector3d::Zero();                 ///< rates, velocity or position
  Eigen::Quaterniond orientation = Eigen::Quaterniond::Identity();  ///< world <- body
  double thrust_ratio = 0.0;                                        ///< 0..1
  double yaw_rad = 0.0;                                             ///< for kPositionYaw
  double yaw_rate_rad_s = 0.0;                                      ///< for kVelocityYawRate
};

struct PlatformOptions {
  SimDuration default_lease_ttl = std::chrono::milliseconds(500);
  /// After the lease is lost: hover this long, then land.
  SimDuration failsafe_hover_time = std::chrono::seconds(5);
  double takeoff_speed_m_s = 1.0;
  double land_speed_m_s = 0.6;
  double emergency_descent_m_s = 1.5;
  /// Take-off is done within this distance of the target altitude.
  double takeoff_tolerance_m = 0.1;
  // Validation limits of setpoints.
  double max_speed_m_s = 20.0;
  double max_rate_rad_s = 10.0;
  double max_altitude_m = 500.0;
};

class VehiclePlatform {
 public:
  VehiclePlatform(std::string robot_id, PlatformOptions options);

  const std::string& robotId() const { return robot_id_; }
  v1::FlightState state() const { return state_; }
  const PlatformCommand& command() const { return command_; }
  bool failsafeActive() const { return failsafe_active_; }
  /// Holder of the live lease, or "" (expired leases are not held).
  const std::string& leaseHolder() const { return lease_holder_; }

  /// Advances the state machine: lease expiry and failsafe, take-off done,
  /// touch-down, crash. Call once per physics step.
  void update(SimTime now, const VehicleSnapshot& vehicle);

  absl::StatusOr<v1::AcquireLeaseResponse> acquireLease(const std::string& holder, SimDuration ttl,
                                                        bool preempt, SimTime now);
  absl::StatusOr<v1::RenewLeaseResponse> renewLease(const std::string& lease_id, SimTime now);
  absl::Status releaseLease(const std::string& lease_id, SimTime now);
  absl::StatusOr<v1::FlightState> executeAction(v1::FlightAction action,
                                                const std::string& lease_id, double altitude_m,
                                                bool confirm, SimTime now);
  /// Validates and applies a setpoint (renews the lease).
  absl::StatusOr<v1::FlightState> setpoint(const v1::SetpointRequest& request, SimTime now);

 private:
  absl::Status checkLease(const std::string& lease_id, SimTime now) const;
  void hoverHere();
  void expireLease(SimTime now);

  std::string robot_id_;
  PlatformOptions options_;
  v1::FlightState state_ = v1::FLIGHT_STATE_LANDED;
  PlatformCommand command_;
  VehicleSnapshot vehicle_;

  std::string lease_id_;
  std::string lease_holder_;
  SimDuration lease_ttl_{0};
  SimTime lease_expiry_{0};
  uint64_t lease_counter_ = 0;

  bool failsafe_active_ = false;
  SimTime failsafe_since_{0};
  double takeoff_altitude_m_ = 1.0;
  Eigen::Vector3d takeoff_origin_m_ = Eigen::Vector3d::Zero();
};

}  // namespace behaviorlib::sim
