#pragma once

// SensorSuite: the sensors of one vehicle. Every physics step it is given the
// vehicle's true state; the sensors that are due (in simulated time) sample
// it. The cheap ones (IMU, GPS, barometer, linear speed, battery, camera
// info) are computed at once and published through their SensorOutput; the
// lidar and the camera only snapshot the pose and hand back a FrameRequest,
// for a worker thread to ray-cast or render (SensorSystem does that).
//
// Noise: each sensor has its own std::mt19937_64 seeded from (seed, robot
// id, sensor name) -- sensorSeed() -- so a run is reproducible and one
// vehicle's samples do not depend on the others. A lidar frame draws one
// number from its sensor's generator when it is due, the seed of that frame's
// noise, so frames are the same whichever thread casts them and whether or
// not earlier frames were dropped.

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <array>
#include <atomic>
#include <cstdint>
#include <memory>
#include <optional>
#include <random>
#include <string>
#include <string_view>
#include <vector>

#include "formats/world/world.h"
#include "simulator/sensors/sensor_config.h"
#include "simulator/sensors/sensor_faults.h"
#include "simulator/sensors/sensor_output.h"
#include "simulator/sensors/sensor_samples.h"
#include "simulator/sensors/sensor_workers.h"
#include "simulator/world/camera.h"
#include "simulator/world/lidar.h"

namespace behaviorlib::sim {

/// The seed of one sensor's generator: a hash of the run's seed, the robot id
/// and the sensor name (the same on every platform).
uint64_t sensorSeed(uint64_t seed, std::string_view robot_id, std::string_view sensor_name);

/// What the sensors of every vehicle share in one world: the world and the
/// lidar and camera models (const, usable from several threads). Replaced on
/// reset; `retired` then tells frames still in flight to vanish.
struct SensorScene {
  SensorScene(std::shared_ptr<const world::World> world, const SensorConfig& config);

  std::shared_ptr<const world::World> world;  ///< never null
  std::optional<Lidar> lidar;                 ///< when the lidar is enabled
  std::optional<Camera> camera;               ///< when the camera or its info is enabled
  mutable std::atomic<bool> retired{false};
};

/// A sensor whose frames are made on a worker (lidar, camera).
struct FrameSensor {
  FrameSensor(std::string robot_id, SensorKind kind, const SensorOutput::Sink* sink,
              std::shared_ptr<SensorChannel> channel, SensorFaultModel model, uint64_t fault_seed)
      : output(std::move(robot_id), kind, sink, std::move(channel), model, fault_seed) {}
  SensorOutput output;
  SensorWorkers::Slot slot;
};

/// Per sensor kind, the channel (faults, counters) of one vehicle's sensor;
/// null entries: no faults, no per-vehicle counters.
using SensorChannels = std::array<std::shared_ptr<SensorChannel>, kSensorKindCount>;

/// A frame to make: the sensor and the body pose at `stamp`.
struct FrameRequest {
  std::shared_ptr<FrameSensor> sensor;
  SimTime stamp{0};
  Eigen::Vector3d position_m = Eigen::Vector3d::Zero();
  Eigen::Quaterniond orientation = Eigen::Quaterniond::Identity();  ///< world <- body
  uint64_t noise_seed = 0;
};

/// Samples at `rate_hz` in simulated time: due at k / rate_hz for k = 1, 2,
/// ..., each taken at the first step at or after its due time (so n seconds
/// give n * rate_hz samples).
class RateSchedule {
 public:
  explicit RateSchedule(double rate_hz);
  bool enabled() const { return period_ns_ > 0; }
  double periodS() const { return static_cast<double>(period_ns_) * 1e-9; }
  /// True when a sample is due at `now` (then not again before the next due time).
  bool due(SimTime now);

 private:
  int64_t period_ns_ = 0;
  int64_t next_ns_ = 0;
};

class SensorSuite {
 public:
  /// `scene` and `sink` must outlive the suite's frames. Initial biases are
  /// drawn here. Each output applies the faults of its entry of `channels`.
  SensorSuite(std::string robot_id, const SensorConfig& config, uint64_t seed,
              std::shared_ptr<const SensorScene> scene, const SensorOutput::Sink* sink,
              const SensorChannels& channels = {});

  const std::string& robotId() const { return robot_id_; }

  /// Samples the sensors due at `now` from the true `state`: publishes the
  /// cheap ones and appends the lidar and camera frames to make to `frames`.
  /// First publishes the delayed samples (faults) due at `now`.
  void step(SimTime now, const VehicleSnapshot& state, std::vector<FrameRequest>* frames);

 private:
  struct Imu {
    RateSchedule schedule;
    std::mt19937_64 rng;
    SensorOutput output;
    Eigen::Vector3d gyro_bias = Eigen::Vector3d::Zero();
    Eigen::Vector3d accel_bias = Eigen::Vector3d::Zero();
  };
  /// A sensor with only a schedule, a generator and an output.
  struct Simple {
    RateSchedule schedule;
    std::mt19937_64 rng;
    SensorOutput output;
    double drift = 0.0;  ///< barometer only
  };
  struct Frames {
    RateSchedule schedule;
    std::mt19937_64 rng;
    std::shared_ptr<FrameSensor> sensor;
  };

  uint64_t faultSeed(uint64_t seed, SensorKind kind) const;
  Simple simple(SensorKind kind, double rate_hz, uint64_t seed, const SensorOutput::Sink* sink,
                const SensorChannels& channels) const;
  std::shared_ptr<FrameSensor> frameSensor(SensorKind kind, uint64_t seed,
                                           const SensorOutput::Sink* sink,
                                           const SensorChannels& channels) const;
  void sampleImu(SimTime now, const VehicleSnapshot& state);

  std::string robot_id_;
  SensorConfig config_;
  std::shared_ptr<const SensorScene> scene_;
  Imu imu_;
  Simple gps_;
  Simple baro_;
  Simple linear_speed_;
  Simple battery_;
  Simple camera_info_;
  Frames lidar_;
  Frames camera_;
};

}  // namespace behaviorlib::sim
