#pragma once

// Simulated time from the channel's `clock` topic (behaviorlib.v1.Clock
// samples published by the simulator).
//
//   behaviorlib::channel::ChannelClient channel("127.0.0.1:50051");
//   behaviorlib::channel::SimClock clock(channel);
//   // clock.valid() is false until the first Clock sample arrives; waiters
//   // registered with addListener() are woken by every sample.
//   if (clock.stale(std::chrono::seconds(2))) { /* simulator dead? */ }
//
// Unit tests drive it without a network:
//
//   behaviorlib::channel::SimClock clock;
//   clock.onClockSample(sample);

#include <chrono>
#include <memory>
#include <mutex>
#include <string>

#include "behaviorlib/clock.h"

namespace behaviorlib::v1 {
class Clock;
}  // namespace behaviorlib::v1

namespace behaviorlib::channel {

class ChannelClient;
class Subscription;

/// A Clock following the simulator's time. Thread-safe.
class SimClock final : public behaviorlib::Clock {
 public:
  /// A clock fed only through onClockSample() (tests, or callers with their
  /// own subscription).
  SimClock();
  /// Subscribes to the `clock` topic on `client` (LATEST mode, latest sample
  /// first). `client` must outlive construction only; the subscription keeps
  /// its own connection state.
  explicit SimClock(ChannelClient& client);
  /// Connects to the broker at `address` ("host:port") with its own client.
  explicit SimClock(const std::string& address);
  /// Stops the subscription before the clock goes away.
  ~SimClock() override;

  /// The last received simulated time (the epoch before any sample).
  TimePoint now() const override;
  /// A bounded wall wait: `remaining` simulated time divided by the time
  /// scale (or 50 ms in lock-step, time_scale 0), never more than 50 ms, as
  /// a safety net for the listener notifications.
  std::chrono::nanoseconds wallWaitFor(Duration remaining) const override;
  /// False until the first sample arrived.
  bool valid() const override;

  /// Takes one Clock sample: updates the time, then notifies listeners.
  void onClockSample(const v1::Clock& sample);

  /// Host wall time (system clock) when the last sample arrived; the epoch
  /// before any sample.
  TimePoint lastWallUpdate() const;
  /// True when no sample arrived within the last `wall_limit` of host time
  /// (also before the first sample): the simulator may be dead or paused
  /// its publishing.
  bool stale(std::chrono::nanoseconds wall_limit) const;
  /// Simulated seconds per wall second of the last sample (0: lock-step).
  double timeScale() const;
  /// Whether the last sample said the simulation is paused.
  bool paused() const;

 private:
  void subscribe(ChannelClient& client);

  mutable std::mutex mutex_;
  TimePoint now_{};
  bool valid_ = false;
  double time_scale_ = 0;
  bool paused_ = false;
  TimePoint last_wall_update_{};
  // Monotonic, so that staleness is immune to host clock jumps.
  std::chrono::steady_clock::time_point last_steady_update_{};

  // Declared last: destroyed (stopping the reader thread that calls
  // onClockSample) before the state above.
  std::unique_ptr<ChannelClient> own_client_;
  std::unique_ptr<Subscription> subscription_;
};

}  // namespace behaviorlib::channel
