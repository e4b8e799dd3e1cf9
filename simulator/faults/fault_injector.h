#pragma once

// FaultInjector: Simulator.InjectFailure without gRPC. Validates a request
// (every refusal says what is accepted) and applies it: a sensor fault to
// the vehicle's sensor (SensorSystem::setFault), a motor or battery fault to
// the vehicle's physics (VehicleModel), the wind to every vehicle
// (Simulation::setWind). Each takes effect from the current simulated time
// on, under the simulation's mutex, so that in lock-step the same
// time-stamped requests give the same run. Semantics: simulator.proto
// (FailureComponent, FailureType) and simulator/sensors/README.md.
//
//   FaultInjector faults(simulation, &sensor_system);
//   worlds.on_reset = [&](...) { sensors.reset(...); faults.reset(); };
//   absl::Status s = faults.inject(request);   // INVALID_ARGUMENT, NOT_FOUND, ...
//
// Thread-safe.

#include <map>
#include <mutex>
#include <set>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "absl/status/status.h"
#include "behaviorlib/v1/simulator.pb.h"
#include "simulator/core/simulation.h"
#include "simulator/sensors/sensor_system.h"

namespace behaviorlib::sim {

class FaultInjector {
 public:
  /// Longest accepted FAILURE_TYPE_DELAYED delay.
  static constexpr SimDuration kMaxDelay = std::chrono::seconds(10);
  /// Strongest accepted steady wind (m/s) and gust standard deviation (m/s).
  static constexpr double kMaxWindMS = 30.0;
  static constexpr double kMaxGustStddevMS = 10.0;

  /// `sensors` may be null when the simulator publishes no sensors; sensor
  /// faults are then refused with FAILED_PRECONDITION. Both must outlive
  /// the injector.
  FaultInjector(Simulation& simulation, SensorSystem* sensors);

  /// Validates and applies one request. INVALID_ARGUMENT for an unset or
  /// unknown component or type, a type the component does not have, an
  /// intensity outside [0, 1] (or 0 where it is the fault's strength), a
  /// negative or out-of-range delay, a motor index out of range, a bad wind;
  /// NOT_FOUND for an unknown vehicle; FAILED_PRECONDITION for a sensor
  /// when there are no sensors.
  absl::Status inject(const v1::InjectFailureRequest& request);

  /// Forgets the faults (the simulation's Reset replaced the vehicles and
  /// calmed the wind; SensorSystem::reset cleared the sensors' faults).
  void reset();

  /// Faults in effect, per vehicle and component ("gps", "motor", ...;
  /// the wind under robot id ""): the number active (motors: how many are
  /// failed; others 0 or 1). Every pair ever faulted is listed, 0 once
  /// cleared.
  struct Active {
    std::string robot_id;
    std::string component;
    int count = 0;
  };
  std::vector<Active> active() const;

  /// "gps", "imu", "baro", "lidar", "camera", "motor", "battery", "wind",
  /// "linear_speed"; "" for an unknown value.
  static std::string_view componentName(v1::FailureComponent component);

 private:
  absl::Status injectSensor(const v1::InjectFailureRequest& request, SensorKind kind);
  absl::Status injectMotor(const v1::InjectFailureRequest& request);
  absl::Status injectBattery(const v1::InjectFailureRequest& request);
  absl::Status injectWind(const v1::InjectFailureRequest& request);
  void setActive(const std::string& robot_id, std::string_view component, int count);

  Simulation& simulation_;
  SensorSystem* const sensors_;

  mutable std::mutex mutex_;
  std::map<std::pair<std::string, std::string>, int> active_;
  std::map<std::string, std::set<int>> failed_motors_;  ///< by robot id
};

}  // namespace behaviorlib::sim
