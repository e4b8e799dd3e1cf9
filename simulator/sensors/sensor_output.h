#pragma once

// SensorOutput: the last stage of one sensor of one vehicle. Every sample the
// sensor produces passes through publish() exactly once, in stamp order and
// on one thread at a time; it is numbered here and handed to the sink.
//
// This is the one place where per-sample faults are to be applied (off,
// stuck, noisy, garbage, intermittent, delayed): each needs only the stamp,
// the sample and the sensor's identity, which publish() has.

#include <cstdint>
#include <functional>
#include <string>
#include <utility>

#include "simulator/sensors/sensor_samples.h"

namespace behaviorlib::sim {

class SensorOutput {
 public:
  /// Receives every sample; called from the physics thread or a sensor
  /// worker, so it must be thread-safe.
  using Sink = std::function<void(SensorSample sample)>;

  /// `sink` must outlive the output.
  SensorOutput(std::string robot_id, SensorKind kind, const Sink* sink)
      : robot_id_(std::move(robot_id)), kind_(kind), sink_(sink) {}

  const std::string& robotId() const { return robot_id_; }
  SensorKind kind() const { return kind_; }
  /// Samples published so far.
  uint64_t count() const { return next_seq_; }

  void publish(SimTime stamp, SampleData data) {
    SensorSample sample;
    sample.robot_id = robot_id_;
    sample.kind = kind_;
    sample.stamp = stamp;
    sample.seq = next_seq_++;
    sample.data = std::move(data);
    (*sink_)(std::move(sample));
  }

 private:
  std::string robot_id_;
  SensorKind kind_;
  const Sink* sink_;
  uint64_t next_seq_ = 0;
};

}  // namespace behaviorlib::sim
