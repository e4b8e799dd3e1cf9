#pragma once

// The simulator's Prometheus metrics (served on its /metrics). Label sets are
// resolved once per vehicle and sensor, never per step; the physics thread
// only feeds the step-time histogram (once per batch of steps) and the
// workers the frame-time histogram. Everything else is read by a collector
// thread every `period` of wall time.
//
//   SimulatorMetrics metrics(runtime.registry(), simulation, time);
//   SensorPublisher sensors(client, simulation, time, config, metrics.frameTimer());
//   metrics.start({.sensors = &sensors, .faults = &faults, ...});
//
// Series (`robot` is the robot id, `sensor` the sensor's name as in
// simulator/sensors/README.md):
//   behaviorlib_simulator_real_time_factor           simulated s per wall s achieved
//                                                    (free-running; kept in lock-step)
//   behaviorlib_simulator_time_scale                 the time scale asked for
//   behaviorlib_simulator_lock_step                  1 in lock-step, else 0
//   behaviorlib_simulator_time_seconds               simulated time
//   behaviorlib_simulator_step_seconds               histogram: wall time of one physics
//                                                    step with its listeners (sensors,
//                                                    publishers), the mean of each batch
//   behaviorlib_simulator_vehicle_position_meters{robot,axis}  ground truth, world ENU
//   behaviorlib_simulator_vehicle_battery_ratio{robot}    state of charge, 0..1
//   behaviorlib_simulator_vehicle_flight_state{robot,state}  1 for the vehicle's state
//                       (LANDED, TAKING_OFF, FLYING, HOVERING, LANDING, EMERGENCY), 0
//                       for the others
//   behaviorlib_simulator_vehicle_crashed{robot}          1 after a crash
//   behaviorlib_simulator_sensor_samples_total{robot,sensor}
//   behaviorlib_simulator_sensor_samples_dropped_total{robot,sensor,reason}
//                       reason "fault" (off, intermittent) or "worker_busy"
//                       (lidar or camera frame due before the last was done)
//   behaviorlib_simulator_sensor_frame_seconds{sensor}    histogram: wall time to
//                       make one lidar scan or camera frame (cast, or render + encode)
//   behaviorlib_simulator_publish_dropped_total{stream}   samples the publishing queue
//                       dropped (broker too slow): stream "state" or "sensors"
//   behaviorlib_simulator_active_faults{robot,component}  injected faults in effect
//                       (motors: how many; the wind has robot "")

#include <prometheus/counter.h>
#include <prometheus/family.h>
#include <prometheus/gauge.h>
#include <prometheus/histogram.h>
#include <prometheus/registry.h>

#include <array>
#include <chrono>
#include <condition_variable>
#include <map>
#include <mutex>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "simulator/core/simulation.h"
#include "simulator/faults/fault_injector.h"
#include "simulator/sensors/sensor_system.h"
#include "simulator/service/simulator_service.h"  // TimeControl

namespace behaviorlib::sim {

class ChannelPublisher;
class SensorPublisher;

class SimulatorMetrics {
 public:
  /// What the collector reads besides the simulation (each may be null).
  struct Sources {
    const SensorPublisher* sensors = nullptr;
    const ChannelPublisher* state = nullptr;
    const FaultInjector* faults = nullptr;
  };

  /// Registers the families and the simulation's step timer. `registry`,
  /// `simulation` and `time` must outlive the metrics.
  SimulatorMetrics(prometheus::Registry& registry, Simulation& simulation, const TimeControl& time);
  /// Stops the collector and removes the step timer.
  ~SimulatorMetrics();
  SimulatorMetrics(const SimulatorMetrics&) = delete;
  SimulatorMetrics& operator=(const SimulatorMetrics&) = delete;

  /// For the SensorSystem: observes each frame's making time (any thread).
  SensorSystem::FrameTimer frameTimer();

  /// Starts the collector thread (every `period` of wall time). The sources
  /// must outlive the metrics, or stop() must be called first.
  void start(Sources sources, std::chrono::milliseconds period = std::chrono::milliseconds(250));
  /// Stops the collector (idempotent).
  void stop();
  /// Reads every source once (the collector does this every period).
  void update();

 private:
  struct VehicleSeries {
    std::array<prometheus::Gauge*, 3> position{};
    prometheus::Gauge* battery = nullptr;
    std::vector<std::pair<int, prometheus::Gauge*>> flight_state;  // by FlightState value
    prometheus::Gauge* crashed = nullptr;
  };
  struct SensorSeries {
    prometheus::Counter* samples = nullptr;
    prometheus::Counter* fault_dropped = nullptr;
    prometheus::Counter* busy_dropped = nullptr;
    uint64_t published = 0, fault = 0, busy = 0;  ///< last values read
  };
  void onBatch(int steps, std::chrono::nanoseconds wall);
  void updateVehicles();
  void updateSensors(const SensorSystem& sensors);
  void updateFaults(const FaultInjector& faults);
  void run(std::chrono::milliseconds period);

  Simulation& simulation_;
  const TimeControl& time_;

  prometheus::Gauge& real_time_factor_;
  prometheus::Gauge& time_scale_;
  prometheus::Gauge& lock_step_;
  prometheus::Gauge& time_seconds_;
  prometheus::Histogram& step_seconds_;
  prometheus::Family<prometheus::Gauge>& position_;
  prometheus::Family<prometheus::Gauge>& battery_;
  prometheus::Family<prometheus::Gauge>& flight_state_;
  prometheus::Family<prometheus::Gauge>& crashed_;
  prometheus::Family<prometheus::Counter>& samples_;
  prometheus::Family<prometheus::Counter>& samples_dropped_;
  prometheus::Family<prometheus::Histogram>& frame_seconds_;
  prometheus::Family<prometheus::Counter>& publish_dropped_;
  prometheus::Family<prometheus::Counter>& publish_gated_;
  prometheus::Counter& pace_slips_;
  prometheus::Family<prometheus::Gauge>& active_faults_;
  prometheus::Histogram* lidar_frame_seconds_;
  prometheus::Histogram* camera_frame_seconds_;
  prometheus::Counter& state_dropped_;
  prometheus::Counter& sensors_dropped_;
  prometheus::Counter& state_gated_;
  prometheus::Counter& sensors_gated_;

  // Physics thread only (onBatch).
  std::vector<double> step_increments_;

  // Collector (update() callers serialize on update_mutex_).
  std::mutex update_mutex_;
  Sources sources_;
  std::map<std::string, VehicleSeries> vehicles_;
  std::map<std::pair<std::string, SensorKind>, SensorSeries> sensors_;
  std::map<std::pair<std::string, std::string>, prometheus::Gauge*> faults_;
  uint64_t state_dropped_seen_ = 0, sensors_dropped_seen_ = 0;
  uint64_t state_gated_seen_ = 0, sensors_gated_seen_ = 0, slips_seen_ = 0;

  std::mutex thread_mutex_;
  std::condition_variable thread_cv_;
  bool stopping_ = false;
  std::thread thread_;
};

}  // namespace behaviorlib::sim
