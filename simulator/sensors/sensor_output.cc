#include "simulator/sensors/sensor_output.h"

namespace behaviorlib::sim {

SensorOutput::SensorOutput(std::string robot_id, SensorKind kind, const Sink* sink,
                           std::shared_ptr<SensorChannel> channel, SensorFaultModel model,
                           uint64_t fault_seed)
    : robot_id_(std::move(robot_id)),
      kind_(kind),
      sink_(sink),
      channel_(std::move(channel)),
      model_(model),
      fault_rng_(fault_seed) {}

void SensorOutput::publish(SimTime stamp, SampleData data) {
  const SensorFault fault = channel_ ? channel_->faultAt(stamp) : SensorFault{};
  std::lock_guard lock(mutex_);
  // Samples still delayed go first once the delay ends: stamps stay in order.
  if (fault.type != SensorFaultType::kDelayed && !delayed_.empty()) flushDelayedLocked();
  switch (fault.type) {
    case SensorFaultType::kOk:
      break;
    case SensorFaultType::kOff:
      channel_->fault_dropped.fetch_add(1, std::memory_order_relaxed);
      return;
    case SensorFaultType::kStuck:
      if (last_) data = *last_;
      break;
    case SensorFaultType::kNoisy:
      addFaultNoise(data, model_, fault.intensity, fault_rng_);
      break;
    case SensorFaultType::kGarbage:
      garble(data, model_, fault_rng_);
      break;
    case SensorFaultType::kIntermittent: {
      // One draw per sample, dropped or not: the pattern does not depend on
      // earlier outcomes.
      const double u = static_cast<double>(fault_rng_() >> 11) * (1.0 / 9007199254740992.0);
      if (u < fault.intensity) {
        channel_->fault_dropped.fetch_add(1, std::memory_order_relaxed);
        return;
      }
      break;
    }
    case SensorFaultType::kDelayed:
      delayed_.push_back({stamp + fault.delay, stamp, std::move(data)});
      has_delayed_.store(true, std::memory_order_release);
      return;
  }
  emitLocked(stamp, std::move(data));
}

void SensorOutput::release(SimTime now) {
  if (!has_delayed_.load(std::memory_order_acquire)) return;
  std::lock_guard lock(mutex_);
  // In order: a later sample with a shorter delay waits for the earlier.
  while (!delayed_.empty() && delayed_.front().due <= now) {
    Delayed next = std::move(delayed_.front());
    delayed_.pop_front();
    emitLocked(next.stamp, std::move(next.data));
  }
  has_delayed_.store(!delayed_.empty(), std::memory_order_release);
}

void SensorOutput::flushDelayedLocked() {
  while (!delayed_.empty()) {
    Delayed next = std::move(delayed_.front());
    delayed_.pop_front();
    emitLocked(next.stamp, std::move(next.data));
  }
  has_delayed_.store(false, std::memory_order_release);
}

void SensorOutput::emitLocked(SimTime stamp, SampleData data) {
  last_ = data;
  SensorSample sample;
  sample.robot_id = robot_id_;
  sample.kind = kind_;
  sample.stamp = stamp;
  sample.seq = next_seq_.fetch_add(1, std::memory_order_relaxed);
  sample.data = std::move(data);
  if (channel_) channel_->published.fetch_add(1, std::memory_order_relaxed);
  (*sink_)(std::move(sample));
}

}  // namespace behaviorlib::sim
