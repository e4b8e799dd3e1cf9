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

#include <Eigen/Core>
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

/// Wind over the whole world: a steady velocity plus turbulence.
struct Wind {
  Eigen::Vector3d velocity_m_s = Eigen::Vector3d::Zero();  ///< world ENU
  /// Standard deviation of the gusts per axis (m/s): an Ornstein-Uhlenbeck
  /// process per vehicle (simulator/dynamics/gust.h); 0: steady wind.
  double gust_stddev_m_s = 0.0;
};

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

  // Fault injection (Simulator.InjectFailure). A model without motors, a
  // battery or drag keeps the defaults, which do nothing.

  /// Number of motors whose efficiency setMotorEfficiency can change.
  virtual int motorCount() const { return 0; }
  /// The fraction of its nominal thrust motor `motor` (0..motorCount()-1)
  /// produces from now on, in [0, 1]; 0 is a dead motor. The autopilot is
  /// not told.
  virtual void setMotorEfficiency(int /*motor*/, double /*efficiency*/) {}
  /// A failing cell: the battery loses `ratio` (0..1) of its full charge at
  /// once (not below empty).
  virtual void dropBatteryCharge(double /*ratio*/) {}
  /// The air the vehicle flies in from now on.
  virtual void setWind(const Wind& /*wind*/) {}
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

/// The pace of free-running time: simulated time `sim` held at the host's
/// monotonic `wall` and advances `scale` simulated seconds per wall second
/// from there (0: lock-step, time moves only by advance()). `generation`
/// changes with every new line: a new scale, lock-step entered or left, a
/// Reset (`epoch` changes too), or the physics falling behind the line by
/// more than Simulation::kSlipLag (it then slips: the line restarts from
/// where the physics is, instead of bursting to catch up).
struct Pace {
  SimTime sim{0};
  std::chrono::steady_clock::time_point wall{};
  double scale = 0.0;
  uint64_t epoch = 0;
  uint64_t generation = 0;
};

class Simulation {
 public:
  /// How far the physics may fall behind the scaled wall clock before the
  /// pace slips, and how long a line lasts at least before the next slip
  /// (wall time), which bounds the lines published under load.
  static constexpr SimDuration kSlipLag = std::chrono::milliseconds(50);
  static constexpr std::chrono::milliseconds kMinLineAge{20};
  /// The shortest sleep of the free-running loop between batches of steps.
  static constexpr std::chrono::milliseconds kMinWallSleep{1};

  /// Called after every physics step with the simulated time and every
  /// vehicle (mutex held: must be quick, must not call back in).
  using StepListener = std::function<void(SimTime now, const std::vector<VehicleReport>& vehicles)>;

  explicit Simulation(SimulationOptions options);

  /// Adds a vehicle; ALREADY_EXISTS for a duplicate robot id.
  absl::Status addVehicle(const std::string& robot_id, std::unique_ptr<VehicleModel> model);
  std::vector<std::string> robotIds() const;
  /// Replaces every vehicle and restarts simulated time at zero (Reset); the
  /// wind becomes calm. Listeners stay registered. `then`, when given, runs under the
  /// simulation's mutex once the new vehicles are in place and before the
  /// next step (e.g. to restart sensors in step with the new vehicles); it
  /// must not call back in.
  void resetVehicles(std::map<std::string, std::unique_ptr<VehicleModel>> vehicles,
                     const std::function<void()>& then = {});
  void addStepListener(StepListener listener);

  /// Wall time the physics took: called after every batch of `steps` steps
  /// (up to 100 when free-running, a whole advance() in lock-step) with the
  /// wall time of the batch, listeners included. Mutex held: must be quick.
  using StepTimer = std::function<void(int steps, std::chrono::nanoseconds wall)>;
  /// Replaces the step timer (empty: none).
  void setStepTimer(StepTimer timer);

  /// Sets the wind for every vehicle, present and added later (until the next
  /// resetVehicles, which makes it calm).
  void setWind(const Wind& wind);
  Wind wind() const;

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
  /// The current pace line (scale 0 before runRealTime and in lock-step).
  /// Safe from step listeners.
  Pace pace() const;
  /// Times the pace slipped (the physics fell behind the scaled wall clock).
  uint64_t slipCount() const { return slips_.load(); }

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
  /// Runs `f` on the model (the physics) of `robot_id` under the simulation's
  /// mutex (NOT_FOUND for an unknown vehicle), with the current time: faults
  /// applied there take effect from the next step on.
  template <class F>
  auto withModel(const std::string& robot_id, F&& f)
      -> absl::StatusOr<decltype(f(std::declval<VehicleModel&>(), SimTime{}))> {
    std::lock_guard lock(mutex_);
    auto it = vehicles_.find(robot_id);
    if (it == vehicles_.end()) return unknownVehicle(robot_id);
    return f(*it->second.model, now_);
  }
  /// Calls `f(now, report)` under the simulation's mutex for every vehicle,
  /// or only for `robot_id` when it is not empty, as step listeners see them
  /// (e.g. to send a watcher the current state before the next step).
  template <class F>
  void visitVehicles(const std::string& robot_id, F&& f) const {
    std::lock_guard lock(mutex_);
    for (const auto& [id, vehicle] : vehicles_) {
      if (!robot_id.empty() && id != robot_id) continue;
      f(now_, VehicleReport{&id, vehicle.model->snapshot(), &vehicle.platform});
    }
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
  /// Steps until `target` or `max_steps`, reporting to the step timer.
  void stepBatchLocked(SimTime target, int max_steps);
  absl::Status unknownVehicle(const std::string& robot_id) const;

  SimulationOptions options_;
  mutable std::mutex mutex_;
  SimTime now_{0};
  uint64_t epoch_ = 0;  // incremented by resetVehicles: pacing re-anchors
  std::map<std::string, Vehicle> vehicles_;
  std::vector<StepListener> listeners_;
  std::vector<VehicleReport> reports_;  // reused every step
  StepTimer step_timer_;
  Wind wind_;
  std::atomic<double> real_time_factor_{0.0};
  // Guards pace_ alone (taken after mutex_ when both are), so that step
  // listeners, which run under mutex_, can read it.
  mutable std::mutex pace_mutex_;
  Pace pace_;
  std::atomic<uint64_t> slips_{0};
  void setPace(SimTime sim, std::chrono::steady_clock::time_point wall, double scale,
               uint64_t epoch);
};

}  // namespace behaviorlib::sim
