#pragma once

// SensorSystem: the simulated sensors of every vehicle of a world, without
// any transport. Attach it to the simulation's step listener; it samples each
// vehicle's true state in simulated time and hands every sample to a sink.
//
//   SensorSystem sensors(config, [&](SensorSample s) { publish(std::move(s)); });
//   sensors.reset(world, /*seed=*/42);          // (and again on every world reset)
//   simulation.addStepListener([&](SimTime now, const std::vector<VehicleReport>& v) {
//     sensors.onStep(now, v, /*wait_for_frames=*/lock_step);
//   });
//   sensors.setCameraWanted("drone1", true);     // render only while someone looks
//
// Threads: onStep() and reset() run on the physics thread (or with it
// stopped) and never ray-cast or render: lidar scans and camera frames are
// made by worker threads (SensorWorkers) from the pose snapshot taken at the
// step, and stamped with that step's time. When a sensor's previous frame is
// still being made, the new frame is dropped and counted -- unless
// `wait_for_frames` (lock-step), when the step waits for it, so that a
// lock-step run loses no frame and is reproducible. The sink is called from
// the physics thread and from the workers: it must be thread-safe.
//
// Reproducibility: the same seed and the same vehicle states give the same
// samples, bit for bit (each sensor has its own generator; see
// sensor_suite.h). The camera is rendered only while wanted, which depends
// on subscribers, so camera images may differ in number, not in content.
//
// Faults (sensor_faults.h): setFault() injects one into a vehicle's sensor
// for the samples stamped after a given simulated time; reset() clears them.
// Each vehicle's sensor keeps its counters (published, removed by a fault,
// frames dropped) across resets, for metrics (stats()).

#include <array>
#include <atomic>
#include <chrono>
#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <set>
#include <string>
#include <vector>

#include "simulator/core/simulation.h"
#include "simulator/sensors/sensor_config.h"
#include "simulator/sensors/sensor_suite.h"
#include "simulator/sensors/sensor_workers.h"

namespace behaviorlib::sim {

class SensorSystem {
 public:
  using Sink = SensorOutput::Sink;
  /// Told the wall time a worker took to make one lidar scan or camera
  /// frame (ray casting, or rendering and encoding); called on the workers.
  using FrameTimer = std::function<void(SensorKind kind, std::chrono::nanoseconds wall)>;

  /// Starts config.worker_threads workers. Precondition: config.validate()
  /// is OK (std::invalid_argument otherwise). Starts with an empty world and
  /// seed 1.
  SensorSystem(SensorConfig config, Sink sink, FrameTimer frame_timer = {});
  /// Stops the workers; frames in flight are dropped.
  ~SensorSystem();
  SensorSystem(const SensorSystem&) = delete;
  SensorSystem& operator=(const SensorSystem&) = delete;

  const SensorConfig& config() const { return config_; }

  /// Restarts every sensor for `world` (null: an empty field) and `seed`:
  /// new generators, biases and drifts, sequence numbers from 0, schedules
  /// from time 0, no faults; frames of the old world still in flight (and
  /// samples a fault delays) are discarded. Must not run concurrently with
  /// onStep (call it from the simulation's reset, see
  /// Simulation::resetVehicles).
  void reset(std::shared_ptr<const world::World> world, uint64_t seed);

  /// Samples every vehicle's sensors due at `now`. A vehicle seen for the
  /// first time gets its suite here.
  void onStep(SimTime now, const std::vector<VehicleReport>& vehicles, bool wait_for_frames);

  /// Whether `robot_id`'s camera should render (default: no). Thread-safe.
  void setCameraWanted(const std::string& robot_id, bool wanted);
  /// Replaces the set of vehicles whose camera renders. Thread-safe.
  void setWantedCameras(std::set<std::string> robot_ids);
  bool cameraWanted(const std::string& robot_id) const;

  /// Samples handed to the sink so far, per sensor kind (all vehicles).
  uint64_t publishedCount(SensorKind kind) const;
  /// Lidar or camera frames dropped because the previous one of the same
  /// sensor was not done yet, per sensor kind (all vehicles).
  uint64_t droppedCount(SensorKind kind) const;

  /// Blocks until no frame is queued or being made (tests).
  void waitIdle();

  /// Injects `fault` (kOk clears) into `robot_id`'s sensor `kind` for the
  /// samples stamped after `since` (the current simulated time: a frame
  /// still being made keeps the fault of its stamp). Works for a vehicle
  /// whose sensors have not sampled yet. Thread-safe.
  void setFault(const std::string& robot_id, SensorKind kind, SimTime since,
                const SensorFault& fault);
  /// The last fault set on `robot_id`'s sensor `kind` (kOk if none).
  SensorFault fault(const std::string& robot_id, SensorKind kind) const;

  /// One vehicle's sensor as metrics see it.
  struct SensorStats {
    std::string robot_id;
    SensorKind kind = SensorKind::kImu;
    uint64_t published = 0;       ///< handed to the sink
    uint64_t fault_dropped = 0;   ///< removed by a fault (off, intermittent)
    uint64_t frames_dropped = 0;  ///< lidar/camera: the previous frame was not done
    SensorFaultType fault = SensorFaultType::kOk;  ///< the last fault set
  };
  /// Every vehicle's sensors seen so far (since construction, across
  /// resets), by robot id and kind. Thread-safe.
  std::vector<SensorStats> stats() const;

 private:
  void submit(FrameRequest request, bool wait);
  void makeFrame(const std::shared_ptr<const SensorScene>& scene, const FrameRequest& request);
  /// The channels of `robot_id`'s sensors, made on first use.
  const SensorChannels& channelsOf(const std::string& robot_id);

  const SensorConfig config_;
  const Sink user_sink_;
  const Sink sink_;  ///< counts, then calls user_sink_
  const FrameTimer frame_timer_;

  mutable std::mutex channels_mutex_;
  std::map<std::string, SensorChannels> channels_;  ///< never erased
  std::array<std::atomic<uint64_t>, kSensorKindCount> published_{};
  std::array<std::atomic<uint64_t>, kSensorKindCount> dropped_{};

  // Physics thread only.
  uint64_t seed_ = 1;
  std::shared_ptr<const SensorScene> scene_;
  std::map<std::string, std::unique_ptr<SensorSuite>> suites_;
  std::vector<FrameRequest> frames_;  ///< reused every step

  mutable std::mutex wanted_mutex_;
  std::set<std::string> wanted_cameras_;

  /// Held by a worker while it publishes a frame, and by reset() while it
  /// retires the scene: no frame of an old world is published after reset().
  std::mutex emit_mutex_;

  SensorWorkers workers_;  // last: stopped first
};

}  // namespace behaviorlib::sim
