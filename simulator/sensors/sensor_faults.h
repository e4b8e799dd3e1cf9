#pragma once

// Faults of the simulated sensors, applied to single samples in
// SensorOutput::publish() (sensor_output.h): what each fault does to a
// sample's data, and SensorChannel, where a vehicle's sensor keeps the faults
// injected into it and its counters.
//
//   channel->setFault(/*since=*/now, {SensorFaultType::kIntermittent, 0.5});
//   // samples stamped after `now` are dropped with probability 0.5
//
// The faults (simulator/sensors/README.md, "Faults", is the reference):
//   kOff           no samples
//   kStuck         the last published value again, with new stamps and seq
//   kNoisy         the configured noise's standard deviation times
//                  (1 + 20 intensity); the camera gets 50 * intensity grey
//                  levels of pixel noise
//   kGarbage       meaningless values (GPS and barometer jump 20-200 m, IMU
//                  and linear speed uniform over a sensor's full scale, the
//                  lidar random ranges with 10 % NaN, the camera noise)
//   kIntermittent  each sample dropped with probability `intensity`
//   kDelayed       each sample published `delay` of simulated time after its
//                  stamp (the stamp stays the measurement time)
// Random draws come from the output's own generator (seeded from the run's
// seed, the robot id and the sensor), in stamp order: reproducible.

#include <array>
#include <atomic>
#include <cstdint>
#include <mutex>
#include <random>
#include <string_view>
#include <vector>

#include "simulator/sensors/sensor_config.h"
#include "simulator/sensors/sensor_samples.h"

namespace behaviorlib::sim {

enum class SensorFaultType { kOk, kOff, kStuck, kNoisy, kGarbage, kIntermittent, kDelayed };

/// "ok", "off", "stuck", "noisy", "garbage", "intermittent", "delayed".
std::string_view sensorFaultName(SensorFaultType type);

/// One fault of one sensor.
struct SensorFault {
  SensorFaultType type = SensorFaultType::kOk;
  /// kNoisy: noise scale (see noisyScale); kIntermittent: the probability
  /// of dropping a sample. In [0, 1].
  double intensity = 0.0;
  /// kDelayed: how long after its stamp a sample is published (> 0).
  SimDuration delay{0};
};

/// The factor a kNoisy fault of `intensity` multiplies the configured noise's
/// standard deviation by: 1 + 20 intensity (x21 at intensity 1).
inline double noisyScale(double intensity) { return 1.0 + 20.0 * intensity; }

/// Grey levels of the pixel noise of a kNoisy camera per unit of intensity.
inline constexpr double kCameraNoiseGreyLevels = 50.0;

/// What a fault needs to know about one sensor: the standard deviations of
/// its configured noise and, for the camera, how it encodes.
struct SensorFaultModel {
  /// Per kind: IMU {gyro, accel, orientation}; GPS {horizontal, vertical};
  /// barometer {noise}; linear speed {noise}; battery {voltage, current};
  /// lidar {range}; none for the camera.
  std::array<double, 3> stddev{};
  int jpeg_quality = 90;

  static SensorFaultModel of(SensorKind kind, const SensorConfig& config);
};

/// Adds the extra noise of a kNoisy fault to `data`: Gaussian, so that the
/// total standard deviation is noisyScale(intensity) times the configured.
void addFaultNoise(SampleData& data, const SensorFaultModel& model, double intensity,
                   std::mt19937_64& rng);

/// Replaces `data` with meaningless values (see the file comment).
void garble(SampleData& data, const SensorFaultModel& model, std::mt19937_64& rng);

/// One sensor of one vehicle, across resets: the faults injected into it
/// (with the simulated time from which each applies) and its counters.
/// Thread-safe.
class SensorChannel {
 public:
  /// The fault for the samples stamped after `since` (and until the next
  /// fault). Faults are set in non-decreasing `since` order (simulated time);
  /// a fault with the same `since` as the last one replaces it.
  void setFault(SimTime since, const SensorFault& fault);
  /// The fault in effect for a sample stamped `stamp`: the last one set
  /// with since < stamp (kOk if none). Samples of frames still being made
  /// when a fault is set keep the fault of their stamp.
  SensorFault faultAt(SimTime stamp) const;
  /// The last fault set (kOk if none).
  SensorFault current() const;
  /// Forgets every fault (Reset: simulated time restarts).
  void clearFaults();

  /// Samples handed to the sink.
  std::atomic<uint64_t> published{0};
  /// Samples a fault removed (kOff, kIntermittent).
  std::atomic<uint64_t> fault_dropped{0};
  /// Lidar or camera frames dropped because the previous one was not done.
  std::atomic<uint64_t> frames_dropped{0};

 private:
  /// At most this many faults are remembered (the oldest are forgotten).
  static constexpr std::size_t kHistory = 64;

  std::atomic<bool> any_{false};  ///< fast path: no fault was ever set
  mutable std::mutex mutex_;
  std::vector<std::pair<SimTime, SensorFault>> history_;  ///< since ascending
};

}  // namespace behaviorlib::sim
