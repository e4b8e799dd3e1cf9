#pragma once

// Simulation: simulated time, the fixed physics step and the vehicles of one
// world, each a VehicleModel (the physics) behind a VehiclePlatform (lease,
// flight states, failsafe). No gRPC: the simulator service drives it, tests
// drive it directly.
//
//   Simulation sim({.physics_step = 1ms});
//   sim.addVehicle("drone1", std::make_unique<MyModel>());
//   sim.advance(std::chrono::seconds(2));             // lock-step
//   // or: sim.runRealTime(5.0, stop_flag)            // 5x real time, paced by the wall clock
//
// Thread-safety: every public method takes the simulation's mutex; listeners
// run on the stepping thread with the mutex held and must not call back in.

#include <atomic>
#include <chrono>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "simulator/platform/vehicle_platform.h"

namespace behaviorlib::sim {

/// The physics of one vehicle, as the simulation needs it.
class VehicleModel {
 public:
  virtual ~VehicleModel() = default;
  /// What the autopilot should track from now on.
  virtual void command(const PlatformCommand& command) = 0;
  /// Advances the vehicle by `dt` seconds.
  virtual void step(double dt_s) = 0;
  /// Current state for the platform logic and for publishing.
  virtual VehicleSnapshot snapshot() const = 0;
};

struct SimulationOptions {
  /// Fixed physics step.
  SimDuration physics_step = std::chrono::milliseconds(1);
  PlatformOptions platform;
};

/// One vehicle as step listeners see it (valid during the call only).
struct VehicleReport {
  const std::string* robot_id;
  VehicleSnapshot snapshot;
  const VehiclePlatform* platform;
};

class Simulation {
 public:
  /// Called after every physics step with the simulated time and every
  /// vehicle (mutex held: must be quick, must not call back in).
  using StepListener = std::function<void(SimTime now, const std::vector<VehicleReport>& vehicles)>;

  explicit Simulation(SimulationOptions options);

  /// Adds a vehicle; ALREADY_EXISTS for a duplicate robot id.
  absl::Status addVehicle(const std::string& robot_id, std::unique_ptr<VehicleModel> model);
  std::vector<std::string> robotIds() const;
  /// Replaces every vehicle and restarts simulated time at zero (Reset).
  /// Listeners stay registered. `then`, when given, runs under the
  /// simulation's mutex once the new vehicles are in place and before the
  /// next step (e.g. to restart sensors in step with the new vehicles); it
  /// must not call back in.
  void resetVehicles(std::map<std::string, std::unique_ptr<VehicleModel>> vehicles,
                     const std::function<void()>& then = {});
  void addStepListener(StepListener listener);

  SimTime now() const;
  /// Advances simulated time by `duration` (rounded up to whole steps) as
  /// fast as possible; used in lock-step mode and by tests.
  void advance(SimDuration duration);
  /// Steps in real time scaled by `time_scale` (simulated seconds per wall
  /// second) until `stop` becomes true, except while `paused` (lock-step:
  /// others advance time); never runs ahead of the scaled wall clock, and
  /// reports the achieved rate through realTimeFactor().
  void runRealTime(const std::atomic<double>& time_scale, const std::atomic<bool>& paused,
                   const std::atomic<bool>& stop);
  /// Simulated seconds per wall second achieved by the last runRealTime.
  double realTimeFactor() const { return real_time_factor_.load(); }

  /// Runs `f` on the platform of `robot_id` under the simulation's mutex
  /// (NOT_FOUND for an unknown vehicle). The platform sees the current time.
  template <class F>
  auto withPlatform(const std::string& robot_id, F&& f)
      -> absl::StatusOr<decltype(f(std::declval<VehiclePlatform&>(), SimTime{}))> {
    std::lock_guard lock(mutex_);
    auto it = vehicles_.find(robot_id);
    if (it == vehicles_.end()) return unknownVehicle(robot_id);
    return f(it->second.platform, now_);
  }
  /// The vehicle's latest snapshot and flight state.
  absl::StatusOr<std::pair<VehicleSnapshot, v1::FlightState>> vehicleState(
      const std::string& robot_id) const;

 private:
  struct Vehicle {
    VehiclePlatform platform;
    std::unique_ptr<VehicleModel> model;
  };
  void stepLocked();
  absl::Status unknownVehicle(const std::string& robot_id) const;

  SimulationOptions options_;
  mutable std::mutex mutex_;
  SimTime now_{0};
  uint64_t epoch_ = 0;  // incremented by resetVehicles: pacing re-anchors
  std::map<std::string, Vehicle> vehicles_;
  std::vector<StepListener> listeners_;
  std::vector<VehicleReport> reports_;  // reused every step
  std::atomic<double> real_time_factor_{0.0};
};

}  // namespace behaviorlib::sim
