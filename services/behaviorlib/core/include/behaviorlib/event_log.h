#pragma once

// The per-process log of behavior lifecycle events, with resumable
// subscriptions (BehaviorSystem.WatchEvents): a ResumableLog of
// BehaviorEvents (resumable_log.h) that stamps the robot and the system and
// keeps each event until `retention` after its activation finished.
//
//   EventLog log({.robot_id = "drone1", .system = "basic_quadrotor_behaviors"});
//   auto sub = log.subscribe({.since_seq = 0}, [&] { /* events available */ });
//   log.append(event);                  // assigns seq, incarnation, robot, system, wall_time
//   while (auto e = sub->pop()) { ... }
//
// An event is kept until `retention` (wall time) after the activation it
// belongs to finished, and at most `capacity` events are kept (oldest evicted
// first). A subscriber's queue is bounded: when it overflows the
// subscription is marked overflowed and stops receiving, so a slow
// subscriber never blocks behaviors or other subscribers; it resumes with
// since_seq.

#include <chrono>
#include <cstdint>
#include <functional>
#include <memory>
#include <string>
#include <vector>

#include "behaviorlib/resumable_log.h"
#include "behaviorlib/v1/behavior.pb.h"

namespace behaviorlib {

/// Behavior events of the listed behaviors (all when empty).
struct BehaviorEventFilter {
  std::vector<std::string> behaviors;
  bool matches(const v1::BehaviorEvent& event) const;
};

/// An event is kept while its activation runs and `retention` after it
/// finished; an event of no activation `retention` after it was appended.
struct ActivationRetention {
  std::chrono::nanoseconds retention;

  template <class Older>
  std::chrono::nanoseconds onAppend(const v1::BehaviorEvent& event, std::chrono::nanoseconds now,
                                    Older& older) const {
    if (event.activation_id().empty()) return expiry(now);  // no `finished` would release it
    if (!event.has_finished()) return log_internal::kKeepForever;
    const std::chrono::nanoseconds expires_at = expiry(now);
    older.forEach([&](const v1::BehaviorEvent& e, std::chrono::nanoseconds& e_expires_at) {
      // Events already counting down keep their expiry, so a duplicate
      // `finished` cannot extend it.
      if (e_expires_at == log_internal::kKeepForever &&
          e.activation_id() == event.activation_id() && e.behavior() == event.behavior()) {
        e_expires_at = expires_at;
      }
    });
    return expires_at;
  }

 private:
  // Saturates so that a huge retention means "forever" instead of overflowing.
  std::chrono::nanoseconds expiry(std::chrono::nanoseconds now) const {
    if (retention > std::chrono::nanoseconds::zero() &&
        now > log_internal::kKeepForever - retention) {
      return log_internal::kKeepForever;
    }
    return now + retention;
  }
};

using BehaviorEventLog = ResumableLog<v1::BehaviorEvent, BehaviorEventFilter, ActivationRetention>;
using EventPtr = BehaviorEventLog::EventPtr;
using EventSubscription = BehaviorEventLog::Subscription;

struct EventLogOptions {
  std::string robot_id;
  std::string system;
  /// Maximum retained events (about 1 KiB each): enough for a subscriber to
  /// resume after an outage of many minutes at a few activations per second.
  size_t capacity = 2048;
  /// How long events are kept after their activation finished.
  std::chrono::nanoseconds retention = std::chrono::minutes(10);
  /// Maximum undelivered events per subscriber before it is cut off.
  size_t subscriber_queue_limit = 4096;
  /// Incarnation id; empty means a fresh random one (the normal case).
  std::string incarnation;
};

struct SubscribeOptions {
  /// Replay retained events with seq > since_seq.
  uint64_t since_seq = 0;
  /// The incarnation since_seq refers to; empty means "the current one".
  std::string incarnation;
  /// Only these behaviors; empty means all.
  std::vector<std::string> behaviors;
};

class EventLog {
 public:
  explicit EventLog(EventLogOptions options);

  const std::string& incarnation() const { return log_.incarnation(); }
  const std::string& robotId() const { return robot_id_; }
  const std::string& system() const { return system_; }

  /// Appends an event: fills seq, incarnation, robot_id, system and
  /// wall_time, retains it and hands it to every matching subscriber. A
  /// `finished` event starts the retention countdown of every retained
  /// event of its activation. Never blocks on subscribers.
  EventPtr append(v1::BehaviorEvent event);

  /// Subscribes (ResumableLog::subscribe): the replay is queued before this
  /// returns, without a wake, so drain the queue once after subscribing.
  std::unique_ptr<EventSubscription> subscribe(const SubscribeOptions& options,
                                               std::function<void()> wake);

  /// Seq of the newest event (0 if none).
  uint64_t latestSeq() const { return log_.latestSeq(); }
  /// Number of retained events (as a subscriber would see them now).
  size_t retainedCount() const { return log_.retainedCount(); }

  /// For tests: the wall clock used for retention (defaults to steady time).
  /// Set it before appending: expiry times already computed are kept.
  void setWallClockForTesting(std::function<std::chrono::nanoseconds()> now) {
    log_.setWallClockForTesting(std::move(now));
  }

 private:
  const std::string robot_id_;
  const std::string system_;
  BehaviorEventLog log_;
};

}  // namespace behaviorlib
