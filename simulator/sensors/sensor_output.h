#pragma once

// SensorOutput: the last stage of one sensor of one vehicle. Every sample the
// sensor produces passes through publish() exactly once, in stamp order and
// on one thread at a time; the fault in effect for the sample's stamp
// (SensorChannel, sensor_faults.h) is applied here, then the sample is
// numbered and handed to the sink.
//
//   SensorOutput output("drone1", SensorKind::kGps, &sink, channel, model, seed);
//   every physics step:  output.release(now);   // delayed samples now due
//   when a sample is due: output.publish(stamp, PositionFixData{...});
//
// `seq` counts the published samples (from 0): a sample a fault removes
// takes no number, as with a sensor that stopped sending.

#include <atomic>
#include <cstdint>
#include <deque>
#include <functional>
#include <memory>
#include <mutex>
#include <optional>
#include <random>
#include <string>
#include <utility>

#include "simulator/sensors/sensor_faults.h"
#include "simulator/sensors/sensor_samples.h"

namespace behaviorlib::sim {

class SensorOutput {
 public:
  /// Receives every sample; called from the physics thread or a sensor
  /// worker, so it must be thread-safe.
  using Sink = std::function<void(SensorSample sample)>;

  /// `sink` must outlive the output. Without a `channel` no fault applies.
  /// `fault_seed` seeds the generator of the faults' random draws.
  SensorOutput(std::string robot_id, SensorKind kind, const Sink* sink,
               std::shared_ptr<SensorChannel> channel = nullptr, SensorFaultModel model = {},
               uint64_t fault_seed = 0);
  SensorOutput(const SensorOutput&) = delete;
  SensorOutput& operator=(const SensorOutput&) = delete;

  const std::string& robotId() const { return robot_id_; }
  SensorKind kind() const { return kind_; }
  /// The channel (faults and counters), or null.
  SensorChannel* channel() const { return channel_.get(); }
  /// Samples published so far.
  uint64_t count() const { return next_seq_.load(); }

  /// Takes one sample measured at `stamp` through the fault in effect.
  void publish(SimTime stamp, SampleData data);
  /// Publishes the delayed samples whose time (stamp + delay) is at or
  /// before `now`. Call once per physics step, on the physics thread.
  void release(SimTime now);

 private:
  struct Delayed {
    SimTime due;
    SimTime stamp;
    SampleData data;
  };
  /// Numbers and hands on one sample; mutex_ held.
  void emitLocked(SimTime stamp, SampleData data);
  void flushDelayedLocked();

  const std::string robot_id_;
  const SensorKind kind_;
  const Sink* const sink_;
  const std::shared_ptr<SensorChannel> channel_;
  const SensorFaultModel model_;

  std::mutex mutex_;  ///< publish() (physics or worker thread) vs release()
  std::atomic<uint64_t> next_seq_{0};
  std::mt19937_64 fault_rng_;
  std::optional<SampleData> last_;  ///< the last published data (kStuck)
  std::deque<Delayed> delayed_;     ///< kDelayed, stamp order
  std::atomic<bool> has_delayed_{false};
};

}  // namespace behaviorlib::sim
