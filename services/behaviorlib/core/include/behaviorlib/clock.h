#pragma once

// Clocks that behaviors take time from. A behavior never reads the host clock
// directly: ticks, maximum_execution_time, dwell and staleness all use the
// injected Clock, so simulated missions and unit tests run fast and
// deterministically.
//
//   behaviorlib::FakeClock clock;            // starts at 0
//   clock.advance(std::chrono::seconds(1));  // wakes every waiter
//
// SimClock (simulated time from the channel's `clock` topic) lives in
// services/channel/sim_clock.h; SteadyClock is for real robots.

#include <chrono>
#include <cstdint>
#include <vector>

#include "absl/base/thread_annotations.h"
#include "absl/synchronization/mutex.h"

namespace behaviorlib {

/// Time on a behavior's clock: nanoseconds since the Unix epoch (simulated
/// epoch for simulated time).
using Duration = std::chrono::nanoseconds;
using TimePoint = std::chrono::time_point<std::chrono::system_clock, Duration>;

/// A Duration from seconds given as a double (a parameter such as
/// `duration_s`), rounded toward zero to the nanosecond: `seconds(1.5)`.
constexpr Duration seconds(double s) {
  return std::chrono::duration_cast<Duration>(std::chrono::duration<double>(s));
}

/// The inverse: a Duration in seconds, as a double.
constexpr double toSeconds(Duration d) { return std::chrono::duration<double>(d).count(); }

/// Notified when a non-wall clock's time jumps forward, so that threads
/// waiting for a deadline on that clock re-check it at once.
class ClockListener {
 public:
  virtual ~ClockListener() = default;
  /// Called from the thread that advanced the clock; must not block.
  virtual void onClockAdvanced() = 0;
  /// Work a listener does on this clock outside the behaviors' ticks (a
  /// lease renewal): whether everything it had due up to `t` has run. The
  /// deterministic mode reports a granted time only once every listener has
  /// (Clock::listenersCaughtUp). Must not block.
  virtual bool caughtUp(TimePoint /*t*/) const { return true; }
};

/// Source of time for behaviors. Thread-safe.
class Clock {
 public:
  Clock() = default;
  Clock(const Clock&) = delete;
  Clock& operator=(const Clock&) = delete;
  virtual ~Clock() = default;

  /// Current time.
  virtual TimePoint now() const = 0;

  /// The longest wall time a waiter may sleep before re-reading now(), when
  /// `remaining` of this clock's time is left until its deadline. A wall
  /// clock returns `remaining`; clocks that notify listeners may return a
  /// bounded value as a safety net.
  virtual std::chrono::nanoseconds wallWaitFor(Duration remaining) const = 0;

  /// Whether the clock's time is currently valid (a SimClock that has not yet
  /// received simulated time is not). Behaviors do not tick on an invalid
  /// clock.
  virtual bool valid() const { return true; }

  /// Registers a listener notified whenever time advances (no-op for wall
  /// clocks, whose waiters use timed waits). The listener must outlive its
  /// registration.
  void addListener(ClockListener* listener) const;
  void removeListener(ClockListener* listener) const;
  /// Whether every listener ran what it had due up to `t`
  /// (ClockListener::caughtUp).
  bool listenersCaughtUp(TimePoint t) const;

 protected:
  /// Subclasses call this after their time advanced.
  void notifyListeners();

 private:
  mutable absl::Mutex listeners_mutex_;
  mutable std::vector<ClockListener*> listeners_ ABSL_GUARDED_BY(listeners_mutex_);
};

/// Host monotonic time, offset once at construction so that it reads as Unix
/// time (for timestamps) while never jumping.
class SteadyClock final : public Clock {
 public:
  SteadyClock();
  TimePoint now() const override;
  std::chrono::nanoseconds wallWaitFor(Duration remaining) const override { return remaining; }

 private:
  Duration offset_;
};

/// Manually driven time for unit tests. Starts at `start` (default: the
/// epoch plus one hour, so that zero never looks like a valid stamp).
class FakeClock final : public Clock {
 public:
  explicit FakeClock(TimePoint start = TimePoint(std::chrono::hours(1)));
  TimePoint now() const override;
  std::chrono::nanoseconds wallWaitFor(Duration remaining) const override;

  /// Moves time forward by `delta` and wakes every waiter.
  void advance(Duration delta);
  /// Sets time (must not go backwards) and wakes every waiter.
  void set(TimePoint t);

 private:
  mutable absl::Mutex mutex_;
  TimePoint now_ ABSL_GUARDED_BY(mutex_);
};

}  // namespace behaviorlib
