#pragma once

// The coordinator's own event log: every accepted behavior event of every
// system, plus system state changes, numbered 1, 2, 3... per coordinator run
// (with a random incarnation id per run), kept in a bounded buffer and served
// to resumable, filtered subscriptions (Coordinator.WatchEvents).
//
//   FleetEventLog log({.capacity = 10000});
//   auto sub = log.subscribe({.since_seq = 0, .robot_ids = {"drone1"}}, [&] { /* wake */ });
//   log.append(event);             // assigns seq, incarnation, wall_time
//   while (auto e = sub->pop()) { ... }
//
// The semantics follow the behavior systems' EventLog (docs/decisions/0002):
// replay and registration are atomic with respect to appends; a subscriber
// whose undelivered queue exceeds its limit is marked overflowed and stops
// receiving, so appending never waits for a subscriber. Unlike EventLog,
// retention is by count only: the oldest events are evicted first.

#include <atomic>
#include <cstdint>
#include <deque>
#include <functional>
#include <memory>
#include <mutex>
#include <string>
#include <vector>

#include "behaviorlib/v1/coordinator.pb.h"

namespace behaviorlib::coordinator {

using FleetEventPtr = std::shared_ptr<const v1::FleetEvent>;

/// A stored event and its wire form, serialized once on first use and shared
/// by every subscriber that writes it (the WatchEvents streams write the
/// bytes instead of copying the message into each subscriber's response).
class FleetEventRecord {
 public:
  explicit FleetEventRecord(v1::FleetEvent event) : event_(std::move(event)) {}
  const v1::FleetEvent& event() const { return event_; }
  /// event() serialized (thread-safe; computed once).
  const std::string& wire() const;

 private:
  const v1::FleetEvent event_;
  mutable std::once_flag serialized_;
  mutable std::string wire_;
};
using FleetEventRecordPtr = std::shared_ptr<const FleetEventRecord>;

struct FleetEventLogOptions {
  /// Maximum retained events (oldest evicted first).
  size_t capacity = 10000;
  /// Maximum undelivered live events per subscriber before it is cut off.
  size_t subscriber_queue_limit = 4096;
  /// Incarnation id; empty means a fresh random one (the normal case).
  std::string incarnation;
};

struct FleetSubscribeOptions {
  /// Replay retained events with seq > since_seq.
  uint64_t since_seq = 0;
  /// The incarnation since_seq refers to; empty means "the current one".
  std::string incarnation;
  /// Only events of these robots; empty means all.
  std::vector<std::string> robot_ids;
  /// Only behavior events of these behaviors (system events are left out);
  /// empty means all.
  std::vector<std::string> behaviors;
};

/// Whether `event` passes the robot and behavior filters.
bool matchesFilter(const v1::FleetEvent& event, const std::vector<std::string>& robot_ids,
                   const std::vector<std::string>& behaviors);

class FleetEventLog;

/// One subscriber's view: the replay summary, then a queue of events.
/// Thread-safe; destroy it (or call cancel()) to unsubscribe.
class FleetSubscription {
 public:
  ~FleetSubscription();
  FleetSubscription(const FleetSubscription&) = delete;
  FleetSubscription& operator=(const FleetSubscription&) = delete;

  /// What the replay covers (the first WatchEvents message).
  const v1::WatchEventsStart& start() const { return start_; }
  /// Next queued event, or nullptr when none is queued.
  FleetEventPtr pop();
  /// Up to `max` queued events, oldest first (empty when none).
  std::vector<FleetEventPtr> popUpTo(size_t max);
  /// popUpTo() with the events' wire forms, also stopping before the wire
  /// forms' total would exceed `max_bytes` (at least one event is popped).
  std::vector<FleetEventRecordPtr> popRecordsUpTo(size_t max,
                                                  size_t max_bytes = static_cast<size_t>(-1));
  /// True once the queue overflowed; nothing more is delivered.
  bool overflowed() const;
  /// Seq of the last event handed out by pop(), or the since_seq the
  /// subscription started from (so it is always a valid resume point).
  uint64_t lastPoppedSeq() const;
  /// Stops delivery; the wake callback is never called after this returns.
  /// May be called from inside wake.
  void cancel();

 private:
  friend class FleetEventLog;
  struct WakeSlot;

  FleetSubscription() = default;
  // Under the log's lock; returns whether wake must be called afterwards.
  bool deliver(const FleetEventRecordPtr& record);

  std::atomic<FleetEventLog*> log_{nullptr};
  v1::WatchEventsStart start_;
  std::vector<std::string> robot_ids_;
  std::vector<std::string> behaviors_;
  size_t limit_ = 0;
  std::shared_ptr<WakeSlot> wake_;
  mutable std::mutex mutex_;
  std::deque<FleetEventRecordPtr> queue_;
  size_t replay_left_ = 0;  // replayed events at the front of queue_
  bool overflowed_ = false;
  bool cancelled_ = false;
  uint64_t last_popped_seq_ = 0;
};

class FleetEventLog {
 public:
  explicit FleetEventLog(FleetEventLogOptions options = {});
  FleetEventLog(const FleetEventLog&) = delete;
  FleetEventLog& operator=(const FleetEventLog&) = delete;
  /// Detaches live subscriptions (they keep what is queued).
  ~FleetEventLog();

  const std::string& incarnation() const { return options_.incarnation; }

  /// Appends: fills seq, incarnation and wall_time, retains the event and
  /// hands it to every matching subscriber. Never blocks on subscribers.
  FleetEventPtr append(v1::FleetEvent event);
  /// append() for several events at once, in order: one lock, and each
  /// subscriber woken once.
  void appendAll(std::vector<v1::FleetEvent> events);

  /// Subscribes: computes the replay summary, queues the matching retained
  /// events after since_seq (all retained ones if the incarnation differs),
  /// then each new matching event. `wake` is called (never under a lock of
  /// the log or the subscription) when the queue becomes non-empty or the
  /// subscription overflows; it must not block. Drain once after
  /// subscribing: the replay is queued without a wake.
  std::unique_ptr<FleetSubscription> subscribe(const FleetSubscribeOptions& options,
                                               std::function<void()> wake);

  /// Seq of the newest event (0 if none).
  uint64_t latestSeq() const;
  /// Number of retained events.
  size_t retainedCount() const;

 private:
  friend class FleetSubscription;
  // Appends in order under one lock; returns the last event stored.
  FleetEventPtr appendEvents(std::vector<v1::FleetEvent> events);
  void unsubscribe(FleetSubscription* subscription);

  FleetEventLogOptions options_;
  mutable std::mutex mutex_;
  uint64_t next_seq_ = 1;
  std::deque<FleetEventRecordPtr> retained_;
  std::vector<FleetSubscription*> subscribers_;
};

}  // namespace behaviorlib::coordinator
