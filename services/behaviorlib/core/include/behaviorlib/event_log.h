#pragma once

// The per-process log of behavior lifecycle events, with resumable
// subscriptions (BehaviorSystem.WatchEvents).
//
//   EventLog log({.robot_id = "drone1", .system = "basic_quadrotor_behaviors"});
//   auto sub = log.subscribe({.since_seq = 0}, [&] { /* events available */ });
//   log.append(event);                  // assigns seq, incarnation, robot, system, wall_time
//   while (auto e = sub->pop()) { ... }
//
// Events are numbered 1, 2, 3... per process run; each run has a new random
// incarnation id. Retained events are replayed to new subscribers: an event is
// kept until `retention` (wall time) after the activation it belongs to
// finished, and at most `capacity` events are kept (oldest evicted first).
// A subscriber's queue is bounded: when it overflows the subscription is
// marked overflowed and stops receiving, so a slow subscriber never blocks
// behaviors or other subscribers; it resumes with since_seq.

#include <atomic>
#include <chrono>
#include <cstdint>
#include <deque>
#include <functional>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <vector>

#include "behaviorlib/v1/behavior.pb.h"

namespace behaviorlib {

using EventPtr = std::shared_ptr<const v1::BehaviorEvent>;

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

class EventLog;

/// One subscriber's view: the replay summary, then a queue of events.
/// Thread-safe; destroy it (or call cancel()) to unsubscribe.
class EventSubscription {
 public:
  ~EventSubscription();
  EventSubscription(const EventSubscription&) = delete;
  EventSubscription& operator=(const EventSubscription&) = delete;

  /// What the replay covers (the first WatchEvents message).
  const v1::WatchEventsStart& start() const { return start_; }
  /// Next queued event, or nullptr when none is queued.
  EventPtr pop();
  /// Up to `max` queued events, oldest first (empty when none).
  std::vector<EventPtr> popUpTo(size_t max);
  /// True once the queue overflowed; no further events are delivered.
  bool overflowed() const;
  /// Seq of the last event handed out by pop() (0 if none).
  uint64_t lastPoppedSeq() const;
  /// Stops delivery; the wake callback is never called after this returns.
  /// Waits for a wake running on another thread to return, so do not call it
  /// (or destroy the subscription) while holding a lock that wake takes. It
  /// may be called from inside wake itself.
  void cancel();

 private:
  friend class EventLog;
  // The wake callback lives apart from the subscription so that an appender
  // that is about to call it keeps it alive even if the subscription is
  // destroyed meanwhile (or from inside the callback); see event_log.cc.
  struct WakeSlot;

  EventSubscription() = default;
  // Called by EventLog under its lock; returns whether wake must be called
  // (after the lock is released).
  bool deliver(const EventPtr& event);

  // Cleared by cancel() or by the log's destructor (detach).
  std::atomic<EventLog*> log_{nullptr};
  v1::WatchEventsStart start_;
  std::vector<std::string> behaviors_;
  size_t limit_ = 0;
  std::shared_ptr<WakeSlot> wake_;
  mutable std::mutex mutex_;
  std::deque<EventPtr> queue_;
  // Replayed events still at the front of queue_: they do not count against
  // limit_, which bounds how far the subscriber lags behind live events.
  size_t replay_left_ = 0;
  bool overflowed_ = false;
  bool cancelled_ = false;
  uint64_t last_popped_seq_ = 0;
};

class EventLog {
 public:
  explicit EventLog(EventLogOptions options);
  EventLog(const EventLog&) = delete;
  EventLog& operator=(const EventLog&) = delete;
  /// Detaches live subscriptions: they keep their queued events and may be
  /// destroyed later, but receive nothing more. Must not run concurrently
  /// with append() or with cancel()/destruction of one of its subscriptions.
  ~EventLog();

  const std::string& incarnation() const { return options_.incarnation; }
  const std::string& robotId() const { return options_.robot_id; }
  const std::string& system() const { return options_.system; }

  /// Appends an event: fills seq, incarnation, robot_id, system and
  /// wall_time, retains it and hands it to every matching subscriber.
  /// A `finished` event starts the retention countdown of every retained
  /// event of its activation. Never blocks on subscribers. Returns the stored
  /// event.
  EventPtr append(v1::BehaviorEvent event);

  /// Subscribes: computes the replay summary, queues the retained events
  /// after since_seq (all retained ones if the incarnation differs), then
  /// queues each new event. `wake` is called (from the appending thread, never
  /// under the subscription's lock) when the queue goes from empty to
  /// non-empty or the subscription overflows; it must not block.
  ///
  /// The replay is queued before subscribe returns without a wake, so drain
  /// the queue once after subscribing. wake may run on an appending thread
  /// before subscribe returns, and may be spurious (pop() returns nullptr).
  /// It runs under neither the log's nor the subscription's lock: it may call
  /// pop(), overflowed(), lastPoppedSeq(), cancel() and even destroy the
  /// subscription. Replayed events do not count against
  /// subscriber_queue_limit.
  std::unique_ptr<EventSubscription> subscribe(const SubscribeOptions& options,
                                               std::function<void()> wake);

  /// Seq of the newest event (0 if none).
  uint64_t latestSeq() const;
  /// Number of retained events (as a subscriber would see them now).
  size_t retainedCount() const;

  /// For tests: the wall clock used for retention (defaults to steady time).
  /// Set it before appending: expiry times already computed are kept.
  void setWallClockForTesting(std::function<std::chrono::nanoseconds()> now);

 private:
  friend class EventSubscription;
  struct Retained {
    EventPtr event;
    std::chrono::nanoseconds expires_at;  // max() while the activation runs
  };
  void evictLocked(std::chrono::nanoseconds now);
  void unsubscribe(EventSubscription* subscription);

  EventLogOptions options_;
  std::function<std::chrono::nanoseconds()> wall_now_;
  mutable std::mutex mutex_;
  uint64_t next_seq_ = 1;
  std::deque<Retained> retained_;
  std::vector<EventSubscription*> subscribers_;
};

/// A fresh random 128-bit id as 32 lowercase hex digits.
std::string newIncarnationId();

}  // namespace behaviorlib
