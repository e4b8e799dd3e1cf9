#pragma once

// ResumableLog<Event, Filter, Retention>: a numbered, bounded log of events
// served to resumable, filtered subscriptions (decision 2). The behavior
// systems' EventLog (BehaviorSystem.WatchEvents) and the coordinator's
// FleetEventLog (Coordinator.WatchEvents) are both this template.
//
//   ResumableLog<v1::FleetEvent, MyFilter> log({.capacity = 10000});
//   auto sub = log.subscribe({.since_seq = 0, .filter = f}, [&] { /* wake */ });
//   log.append(event);             // assigns seq, incarnation, wall_time
//   while (auto e = sub->pop()) { ... }
//
// Events are numbered 1, 2, 3... per log (one process run); each run has a
// new random incarnation id, so a subscriber resuming with the seq of another
// run is told and replayed from the start. Replay and registration are atomic
// with respect to appends: an event appended concurrently is either replayed
// or delivered live, never both or neither. A subscriber whose undelivered
// live events exceed the limit is marked overflowed and stops receiving, so
// appending never waits for a subscriber; it resumes with since_seq.
//
// Event is a protobuf message with `seq`, `incarnation` and `wall_time`
// fields. Filter has `bool matches(const Event&) const`. Retention decides
// how long an event is kept beyond the capacity bound:
//   Duration onAppend(const Event& stored, Duration now, ExpiryUpdater& older)
// returns the new event's expiry on the log's wall clock (kKeepForever to
// keep it until the capacity evicts it) and may bring forward the expiry of
// older retained events. Eviction is from the front only, so retained seqs
// stay consecutive and a resume point's loss is exactly countable.

#include <google/protobuf/timestamp.pb.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdint>
#include <deque>
#include <functional>
#include <memory>
#include <string>
#include <utility>
#include <vector>

#include "absl/base/thread_annotations.h"
#include "absl/synchronization/mutex.h"
#include "behaviorlib/v1/behavior.pb.h"

namespace behaviorlib {

namespace log_internal {

constexpr std::chrono::nanoseconds kKeepForever = std::chrono::nanoseconds::max();

// The callback of one subscription, apart from it so that an appender about
// to call it keeps it alive even if the subscription is destroyed meanwhile.
// `mutex` is held while the callback runs and by cancel(), so no wake runs
// once cancel() has returned; a callback may cancel or destroy its own
// subscription (re-entry on the same thread is detected).
class WakeSlot {
 public:
  explicit WakeSlot(std::function<void()> wake) : wake_(std::move(wake)) {}
  void fire();
  void cancel();

 private:
  absl::Mutex mutex_;
  std::function<void()> wake_;
  bool cancelled_ ABSL_GUARDED_BY(mutex_) = false;
};

void setWallTime(google::protobuf::Timestamp* timestamp);
std::chrono::nanoseconds steadyNow();

}  // namespace log_internal

/// A fresh random 128-bit id as 32 lowercase hex digits.
std::string newIncarnationId();

/// A stored event and its wire form, serialized once on first use and shared
/// by every subscriber that writes it (a stream writes the bytes instead of
/// copying the message into each subscriber's response).
template <class Event>
class LogRecord {
 public:
  explicit LogRecord(Event event) : event_(std::move(event)) {}
  const Event& event() const { return event_; }
  /// event() serialized (thread-safe; computed once).
  const std::string& wire() const {
    std::call_once(serialized_, [this] { event_.SerializeToString(&wire_); });
    return wire_;
  }

 private:
  const Event event_;
  mutable std::once_flag serialized_;
  mutable std::string wire_;
};

/// Keeps every event until the capacity evicts it.
struct KeepUntilCapacity {
  template <class Event, class Older>
  std::chrono::nanoseconds onAppend(const Event&, std::chrono::nanoseconds, Older&) const {
    return log_internal::kKeepForever;
  }
};

struct ResumableLogOptions {
  /// Maximum retained events (oldest evicted first); 0 keeps none.
  size_t capacity = 10000;
  /// Maximum undelivered live events per subscriber before it is cut off.
  size_t subscriber_queue_limit = 4096;
  /// Incarnation id; empty means a fresh random one (the normal case).
  std::string incarnation;
};

template <class Event, class Filter, class Retention = KeepUntilCapacity>
class ResumableLog {
 private:
  struct Retained;

 public:
  using EventPtr = std::shared_ptr<const Event>;
  using Record = LogRecord<Event>;
  using RecordPtr = std::shared_ptr<const Record>;

  struct SubscribeOptions {
    /// Replay retained events with seq > since_seq.
    uint64_t since_seq = 0;
    /// The incarnation since_seq refers to; empty means "the current one".
    std::string incarnation;
    /// Which events this subscriber gets.
    Filter filter;
  };

  /// One subscriber's view: the replay summary, then a queue of events.
  /// Thread-safe; destroy it (or call cancel()) to unsubscribe.
  class Subscription {
   public:
    ~Subscription() { cancel(); }
    Subscription(const Subscription&) = delete;
    Subscription& operator=(const Subscription&) = delete;

    /// What the replay covers (the first WatchEvents message).
    const v1::WatchEventsStart& start() const { return start_; }
    /// Next queued event, or nullptr when none is queued.
    EventPtr pop() {
      std::vector<RecordPtr> one = popRecordsUpTo(1);
      return one.empty() ? nullptr : eventOf(one.front());
    }
    /// Up to `max` queued events, oldest first (empty when none).
    std::vector<EventPtr> popUpTo(size_t max) {
      std::vector<EventPtr> out;
      for (const RecordPtr& record : popRecordsUpTo(max)) out.push_back(eventOf(record));
      return out;
    }
    /// popUpTo() with the events' wire forms, also stopping before the wire
    /// forms' total would exceed `max_bytes` (at least one event is popped).
    std::vector<RecordPtr> popRecordsUpTo(size_t max, size_t max_bytes = SIZE_MAX) {
      absl::MutexLock lock(&mutex_);
      std::vector<RecordPtr> out;
      size_t bytes = 0;
      while (out.size() < max && !queue_.empty()) {
        if (max_bytes != SIZE_MAX) {
          const size_t size = queue_.front()->wire().size();
          if (!out.empty() && bytes + size > max_bytes) break;
          bytes += size;
        }
        out.push_back(std::move(queue_.front()));
        queue_.pop_front();
      }
      replay_left_ -= std::min(replay_left_, out.size());
      if (!out.empty()) last_popped_seq_ = out.back()->event().seq();
      return out;
    }
    /// True once the queue overflowed; nothing more is delivered.
    bool overflowed() const {
      absl::MutexLock lock(&mutex_);
      return overflowed_;
    }
    /// Seq of the last event handed out, or the since_seq the subscription
    /// started from (so it is always a valid resume point).
    uint64_t lastPoppedSeq() const {
      absl::MutexLock lock(&mutex_);
      return last_popped_seq_;
    }
    /// Stops delivery; the wake callback is never called after this returns.
    /// Waits for a wake running on another thread, so do not call it while
    /// holding a lock that wake takes. May be called from inside wake.
    void cancel() {
      {
        // Ignore deliveries racing with the unregistration below.
        absl::MutexLock lock(&mutex_);
        cancelled_ = true;
      }
      if (ResumableLog* log = log_.exchange(nullptr)) log->unsubscribe(this);
      if (wake_) wake_->cancel();
    }

   private:
    friend class ResumableLog;
    Subscription() = default;

    static EventPtr eventOf(const RecordPtr& record) { return EventPtr(record, &record->event()); }

    // Under the log's lock; returns whether wake must be called afterwards.
    bool deliver(const RecordPtr& record) {
      if (!filter_.matches(record->event())) return false;
      absl::MutexLock lock(&mutex_);
      if (cancelled_ || overflowed_) return false;
      if (queue_.size() - replay_left_ >= limit_) {
        // Keep what is queued so the reader drains it and resumes after the
        // last event it got; wake it once so it notices even when idle.
        overflowed_ = true;
        return true;
      }
      const bool was_empty = queue_.empty();
      queue_.push_back(record);
      return was_empty;
    }

    // Cleared by cancel() or by the log's destructor.
    std::atomic<ResumableLog*> log_{nullptr};
    v1::WatchEventsStart start_;
    Filter filter_;
    size_t limit_ = 0;
    std::shared_ptr<log_internal::WakeSlot> wake_;
    mutable absl::Mutex mutex_;
    std::deque<RecordPtr> queue_ ABSL_GUARDED_BY(mutex_);
    // Replayed events still at the front of queue_: they do not count against
    // limit_, which bounds how far the subscriber lags behind live events.
    size_t replay_left_ ABSL_GUARDED_BY(mutex_) = 0;
    bool overflowed_ ABSL_GUARDED_BY(mutex_) = false;
    bool cancelled_ ABSL_GUARDED_BY(mutex_) = false;
    uint64_t last_popped_seq_ ABSL_GUARDED_BY(mutex_) = 0;
  };

  /// The retained events older than the one being appended, for
  /// Retention::onAppend: it may shorten their expiry.
  class ExpiryUpdater {
   public:
    /// Calls `update(event, expires_at)` for each retained event; it may
    /// assign expires_at.
    template <class F>
    void forEach(F&& update) {
      for (Retained& r : retained_) update(r.record->event(), r.expires_at);
    }

   private:
    friend class ResumableLog;
    explicit ExpiryUpdater(std::deque<typename ResumableLog::Retained>& retained)
        : retained_(retained) {}
    std::deque<typename ResumableLog::Retained>& retained_;
  };

  explicit ResumableLog(ResumableLogOptions options, Retention retention = {})
      : options_(std::move(options)),
        retention_(std::move(retention)),
        wall_now_(&log_internal::steadyNow) {
    if (options_.incarnation.empty()) options_.incarnation = newIncarnationId();
  }
  ResumableLog(const ResumableLog&) = delete;
  ResumableLog& operator=(const ResumableLog&) = delete;
  /// Detaches live subscriptions: they keep their queued events and may be
  /// destroyed later, but receive nothing more. Must not run concurrently
  /// with append() or with cancel()/destruction of one of its subscriptions.
  ~ResumableLog() {
    absl::MutexLock lock(&mutex_);
    for (Subscription* subscription : subscribers_) subscription->log_.store(nullptr);
    subscribers_.clear();
  }

  const std::string& incarnation() const { return options_.incarnation; }

  /// Appends: fills seq, incarnation and wall_time, retains the event and
  /// hands it to every matching subscriber. Never blocks on subscribers.
  /// Returns the stored event.
  EventPtr append(Event event) {
    std::vector<Event> one;
    one.push_back(std::move(event));
    return appendEvents(std::move(one));
  }
  /// append() for several events at once, in order: one lock, and each
  /// subscriber woken once.
  void appendAll(std::vector<Event> events) {
    if (!events.empty()) appendEvents(std::move(events));
  }

  /// Subscribes: computes the replay summary, queues the matching retained
  /// events after since_seq (all retained ones if the incarnation differs),
  /// then each new matching event. `wake` is called (never under a lock of
  /// the log or the subscription) when the queue becomes non-empty or the
  /// subscription overflows; it must not block, and may be spurious. Drain
  /// once after subscribing: the replay is queued without a wake. Replayed
  /// events do not count against subscriber_queue_limit.
  std::unique_ptr<Subscription> subscribe(SubscribeOptions options, std::function<void()> wake) {
    std::unique_ptr<Subscription> subscription(new Subscription());
    subscription->filter_ = std::move(options.filter);
    subscription->limit_ = std::max<size_t>(1, options_.subscriber_queue_limit);
    subscription->wake_ = std::make_shared<log_internal::WakeSlot>(std::move(wake));

    v1::WatchEventsStart& start = subscription->start_;
    start.set_incarnation(options_.incarnation);
    const bool incarnation_changed =
        !options.incarnation.empty() && options.incarnation != options_.incarnation;
    start.set_incarnation_changed(incarnation_changed);
    // A since_seq of another run says nothing about this one.
    const uint64_t since_seq = incarnation_changed ? 0 : options.since_seq;

    absl::MutexLock lock(&mutex_);
    // Not yet visible to anyone else; locked for the analysis (and in the
    // order log -> subscription, as in deliver()).
    absl::MutexLock subscription_lock(&subscription->mutex_);
    evictLocked(wall_now_());
    const uint64_t latest_seq = next_seq_ - 1;
    const uint64_t oldest_retained_seq =
        retained_.empty() ? 0 : retained_.front().record->event().seq();
    start.set_oldest_retained_seq(oldest_retained_seq);
    start.set_latest_seq(latest_seq);
    // Retained seqs are consecutive, so the gap between since_seq and the
    // oldest retained event is exactly what was lost.
    uint64_t dropped = 0;
    if (!retained_.empty()) {
      if (since_seq + 1 < oldest_retained_seq) dropped = oldest_retained_seq - since_seq - 1;
    } else if (latest_seq > since_seq) {
      dropped = latest_seq - since_seq;
    }
    start.set_events_dropped(dropped > 0);
    start.set_dropped_count(dropped);

    auto first = std::partition_point(retained_.begin(), retained_.end(), [&](const Retained& r) {
      return r.record->event().seq() <= since_seq;
    });
    for (auto it = first; it != retained_.end(); ++it) {
      if (subscription->filter_.matches(it->record->event())) {
        subscription->queue_.push_back(it->record);
      }
    }
    subscription->replay_left_ = subscription->queue_.size();
    subscription->last_popped_seq_ = std::min(since_seq, latest_seq);
    subscription->log_.store(this);
    subscribers_.push_back(subscription.get());
    return subscription;
  }

  /// Seq of the newest event (0 if none).
  uint64_t latestSeq() const {
    absl::MutexLock lock(&mutex_);
    return next_seq_ - 1;
  }
  /// Number of retained events (as a subscriber would see them now).
  size_t retainedCount() const {
    absl::MutexLock lock(&mutex_);
    // What evictLocked would leave now, without mutating in a const call.
    const std::chrono::nanoseconds now = wall_now_();
    size_t expired = 0;
    while (expired < retained_.size() && retained_[expired].expires_at <= now) ++expired;
    return retained_.size() - expired;
  }

  /// For tests: the clock that retention expiries are on (defaults to steady
  /// time). Set it before appending: expiries already computed are kept.
  void setWallClockForTesting(std::function<std::chrono::nanoseconds()> now) {
    absl::MutexLock lock(&mutex_);
    wall_now_ = std::move(now);
  }

 private:
  struct Retained {
    std::shared_ptr<const LogRecord<Event>> record;
    std::chrono::nanoseconds expires_at;
  };

  EventPtr appendEvents(std::vector<Event> events) {
    std::vector<std::shared_ptr<log_internal::WakeSlot>> to_wake;
    RecordPtr stored;
    {
      absl::MutexLock lock(&mutex_);
      const std::chrono::nanoseconds now = wall_now_();
      for (Event& event : events) {
        event.set_incarnation(options_.incarnation);
        // Under the lock so that wall_time never goes backwards as seq grows.
        log_internal::setWallTime(event.mutable_wall_time());
        event.set_seq(next_seq_++);
        stored = std::make_shared<const Record>(std::move(event));
        ExpiryUpdater older(retained_);
        const std::chrono::nanoseconds expires_at =
            retention_.onAppend(stored->event(), now, older);
        retained_.push_back({stored, expires_at});
        evictLocked(now);
        for (Subscription* subscription : subscribers_) {
          if (subscription->deliver(stored)) to_wake.push_back(subscription->wake_);
        }
      }
    }
    // Outside the lock: a callback may pop, cancel or even append. A
    // subscriber's queue goes from empty to not empty once per batch.
    for (const auto& slot : to_wake) slot->fire();
    return stored ? Subscription::eventOf(stored) : nullptr;
  }

  void evictLocked(std::chrono::nanoseconds now) ABSL_EXCLUSIVE_LOCKS_REQUIRED(mutex_) {
    // Only from the front, so that retained seqs stay consecutive: an expired
    // event behind a longer-lived one waits for it.
    while (!retained_.empty() &&
           (retained_.size() > options_.capacity || retained_.front().expires_at <= now)) {
      retained_.pop_front();
    }
  }

  void unsubscribe(Subscription* subscription) {
    absl::MutexLock lock(&mutex_);
    subscribers_.erase(std::remove(subscribers_.begin(), subscribers_.end(), subscription),
                       subscribers_.end());
  }

  ResumableLogOptions options_;
  Retention retention_;
  mutable absl::Mutex mutex_;
  std::function<std::chrono::nanoseconds()> wall_now_ ABSL_GUARDED_BY(mutex_);
  uint64_t next_seq_ ABSL_GUARDED_BY(mutex_) = 1;
  std::deque<Retained> retained_ ABSL_GUARDED_BY(mutex_);
  std::vector<Subscription*> subscribers_ ABSL_GUARDED_BY(mutex_);
};

}  // namespace behaviorlib
