#pragma once

// Simulated time from the channel's `clock` topic (behaviorlib.v1.Clock
// samples published by the simulator).
//
// Free-running, the simulator publishes its time line (a simulated time, the
// host wall time it held at, and the time scale) only when the line changes
// and once a wall second; SimClock extrapolates the line on the host's
// monotonic clock, so a process needs no message per tick to know the time
// (decision 16). In lock-step (time scale 0) time moves only with samples.
//
//   behaviorlib::channel::ChannelClient channel("127.0.0.1:50051");
//   behaviorlib::channel::SimClock clock(channel);
//   // clock.valid() is false until the first Clock sample arrives; waiters
//   // registered with addListener() are woken by every sample.
//   if (clock.stale(std::chrono::seconds(3))) { /* simulator dead? */ }
//
// When the simulator dies while running, the clock runs on at the last time
// scale: a behavior system's staleness checks (a pose older than a few
// periods) then report PROCESS_FAILURE instead of freezing with the dead
// simulator's time. A restarted simulator (a new epoch) is followed at once.
//
// Unit tests drive it without a network, with fake host clocks:
//
//   behaviorlib::channel::SimClock clock(SimClock::HostClocks{...});
//   clock.onClockSample(sample);

#include <chrono>
#include <functional>
#include <memory>
#include <string>

#include "absl/base/thread_annotations.h"
#include "absl/synchronization/mutex.h"
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
  /// The host clocks SimClock reads: monotonic time to extrapolate on, and
  /// wall (system) time to place a sample's `wall_time`. Tests fake both.
  struct HostClocks {
    std::function<std::chrono::steady_clock::time_point()> steady = [] {
      return std::chrono::steady_clock::now();
    };
    std::function<std::chrono::system_clock::time_point()> system = [] {
      return std::chrono::system_clock::now();
    };
  };

  /// A clock fed only through onClockSample() (tests, or callers with their
  /// own subscription).
  SimClock();
  explicit SimClock(HostClocks host);
  /// Subscribes to the `clock` topic on `client` (LATEST mode, latest sample
  /// first). `client` must outlive construction only; the subscription keeps
  /// its own connection state.
  explicit SimClock(ChannelClient& client);
  /// Connects to the broker at `address` ("host:port") with its own client.
  explicit SimClock(const std::string& address);
  /// Stops the subscription before the clock goes away.
  ~SimClock() override;

  /// The time line of the last sample, extrapolated to this instant (the
  /// epoch before any sample); never earlier than a previous reading within
  /// one epoch of the simulator.
  TimePoint now() const override;
  /// A bounded wall wait: `remaining` simulated time divided by the time
  /// scale (or 50 ms in lock-step, time_scale 0), never more than 50 ms, as
  /// a safety net for the listener notifications.
  std::chrono::nanoseconds wallWaitFor(Duration remaining) const override;
  /// False until the first sample arrived.
  bool valid() const override;

  /// Takes one Clock sample: a new time line, then notifies listeners.
  void onClockSample(const v1::Clock& sample);

  /// Host wall time (system clock) when the last sample arrived; the epoch
  /// before any sample.
  TimePoint lastWallUpdate() const;
  /// True when no sample arrived within the last `wall_limit` of host time
  /// (also before the first sample). A running simulator sends one at least
  /// once a wall second.
  bool stale(std::chrono::nanoseconds wall_limit) const;
  /// Simulated seconds per wall second of the last sample (0: lock-step).
  double timeScale() const;
  /// Whether the last sample said the simulation is paused.
  bool paused() const;
  /// Samples taken so far (tests and metrics).
  uint64_t sampleCount() const;

 private:
  void subscribe(ChannelClient& client);
  TimePoint lineAtLocked(std::chrono::steady_clock::time_point at) const
      ABSL_EXCLUSIVE_LOCKS_REQUIRED(mutex_);

  const HostClocks host_;
  mutable absl::Mutex mutex_;
  // The line: anchor_time_ held at anchor_steady_, advancing time_scale_
  // (0 in lock-step or paused: standing).
  TimePoint anchor_time_ ABSL_GUARDED_BY(mutex_) = {};
  std::chrono::steady_clock::time_point anchor_steady_ ABSL_GUARDED_BY(mutex_) = {};
  bool valid_ ABSL_GUARDED_BY(mutex_) = false;
  double time_scale_ ABSL_GUARDED_BY(mutex_) = 0;
  bool paused_ ABSL_GUARDED_BY(mutex_) = false;
  uint64_t epoch_ ABSL_GUARDED_BY(mutex_) = 0;
  uint64_t samples_ ABSL_GUARDED_BY(mutex_) = 0;
  // The latest reading: now() never returns less within an epoch.
  mutable TimePoint floor_ ABSL_GUARDED_BY(mutex_) = {};
  TimePoint last_wall_update_ ABSL_GUARDED_BY(mutex_) = {};
  // Monotonic, so that staleness is immune to host clock jumps.
  std::chrono::steady_clock::time_point last_steady_update_ ABSL_GUARDED_BY(mutex_) = {};

  // Declared last: destroyed (stopping the reader thread that calls
  // onClockSample) before the state above.
  std::unique_ptr<ChannelClient> own_client_;
  std::unique_ptr<Subscription> subscription_;
};

}  // namespace behaviorlib::channel
