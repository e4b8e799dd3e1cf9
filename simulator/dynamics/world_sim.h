#pragma once

// WorldSim: several quadrotors, each with its robot id, its autopilot and its
// current setpoint, advanced together with a fixed physics step (1 kHz by
// default). Wind is a mean velocity plus optional turbulence (an
// Ornstein-Uhlenbeck gust per vehicle) drawn from a std::mt19937_64 per
// vehicle seeded from the world's seed and the robot id: the same seed, the
// same vehicles and the same setpoints give the same trajectories, bit for
// bit, whatever other vehicles are added.
//
//   WorldSim world({.seed = 7});
//   SimVehicle* drone = world.addVehicle("drone1", {.position_m = {0, 0, 2}});
//   drone->setSetpoint(PositionYaw{{5.0, 0.0, 2.0}, 0.0});
//   world.advance(10.0);                       // 10 000 steps of 1 ms
//   drone->quadrotor().state().position_m;     // ~(5, 0, 2)
//
// Not thread-safe: callers serialize access (one mutex per world).

#include <Eigen/Core>
#include <cstdint>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include "formats/world/collision_world.h"
#include "simulator/dynamics/autopilot.h"
#include "simulator/dynamics/gust.h"
#include "simulator/dynamics/quadrotor.h"
#include "simulator/dynamics/vehicle_params.h"

namespace behaviorlib::sim {

struct WorldSimOptions {
  /// The fixed physics step (s): 1 ms is 1 kHz.
  double physics_step_s = 0.001;
  /// Seed of the per-vehicle random generators (turbulence).
  std::uint64_t seed = 1;
  /// Mean wind, world frame (m/s).
  Eigen::Vector3d wind_m_s = Eigen::Vector3d::Zero();
  /// Standard deviation of the turbulence per axis (m/s); 0 turns it off.
  double gust_std_m_s = 0.0;
  /// Correlation time of the turbulence (s).
  double gust_time_constant_s = kDefaultGustTimeConstantS;
};

/// One vehicle of a WorldSim: its dynamics, its autopilot, its setpoint.
class SimVehicle {
 public:
  SimVehicle(std::string robot_id, const QuadrotorParams& params, const QuadrotorState& initial,
             const AutopilotParams& autopilot, std::uint64_t seed);

  const std::string& robotId() const { return robot_id_; }
  /// The dynamics; mutable for fault injection (motor efficiency, battery)
  /// and respawns (Quadrotor::reset, then autopilot().reset()).
  Quadrotor& quadrotor() { return quadrotor_; }
  const Quadrotor& quadrotor() const { return quadrotor_; }
  const QuadrotorState& state() const { return quadrotor_.state(); }
  Autopilot& autopilot() { return autopilot_; }
  const Autopilot& autopilot() const { return autopilot_; }

  /// The setpoint the autopilot tracks from the next step on (held until
  /// replaced). A new vehicle is Idle.
  void setSetpoint(const Setpoint& setpoint) { setpoint_ = setpoint; }
  const Setpoint& setpoint() const { return setpoint_; }
  /// Motor commands of the last step.
  const MotorCommands& motorCommands() const { return commands_; }
  /// Turbulence currently added to the mean wind (m/s, world).
  const Eigen::Vector3d& gust() const { return gusts_.gust(); }

  /// One physics step: autopilot, wind, dynamics.
  void step(double dt_s, const WorldSimOptions& options);

 private:
  std::string robot_id_;
  Quadrotor quadrotor_;
  Autopilot autopilot_;
  Setpoint setpoint_ = Idle{};
  MotorCommands commands_{};
  GustModel gusts_;
};

/// Several vehicles in one world. See the file comment.
class WorldSim {
 public:
  explicit WorldSim(WorldSimOptions options = {});

  /// Adds a vehicle; null if `robot_id` is empty or taken. The pointer stays
  /// valid until the vehicle is removed or the world destroyed.
  SimVehicle* addVehicle(const std::string& robot_id, const QuadrotorState& initial = {},
                         const QuadrotorParams& params = {}, const AutopilotParams& autopilot = {});
  bool removeVehicle(const std::string& robot_id);
  /// The vehicle with this id, or null.
  SimVehicle* vehicle(const std::string& robot_id);
  const SimVehicle* vehicle(const std::string& robot_id) const;
  /// Robot ids in ascending order (the order vehicles are stepped in).
  std::vector<std::string> robotIds() const;
  std::size_t vehicleCount() const { return vehicles_.size(); }

  /// Sets a vehicle's setpoint; false if there is no such vehicle.
  bool setSetpoint(const std::string& robot_id, const Setpoint& setpoint);

  /// Advances every vehicle by one physics step.
  void step() { step(options_.physics_step_s); }
  /// Advances every vehicle by one step of `dt_s` seconds.
  void step(double dt_s);
  /// Advances by `duration_s` in whole physics steps (rounded to nearest).
  void advance(double duration_s);

  /// Simulated time since the start (ns), exact in whole nanoseconds.
  std::int64_t timeNs() const { return time_ns_; }
  double timeS() const { return static_cast<double>(time_ns_) * 1e-9; }
  std::uint64_t stepCount() const { return step_count_; }

  /// Mean wind for every vehicle (world frame, m/s).
  void setWindVelocity(const Eigen::Vector3d& wind_m_s) { options_.wind_m_s = wind_m_s; }
  /// Static geometry for every vehicle, present and future (not owned).
  void setCollisionWorld(const world::CollisionWorld* world);
  const WorldSimOptions& options() const { return options_; }

 private:
  WorldSimOptions options_;
  const world::CollisionWorld* collision_world_ = nullptr;
  std::map<std::string, std::unique_ptr<SimVehicle>> vehicles_;
  std::int64_t time_ns_ = 0;
  std::uint64_t step_count_ = 0;
};

}  // namespace behaviorlib::sim
