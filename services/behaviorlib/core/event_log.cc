#include "behaviorlib/event_log.h"

#include <algorithm>
#include <random>
#include <utility>

namespace behaviorlib {

namespace {

using std::chrono::nanoseconds;

// expires_at of an event whose activation is still running.
constexpr nanoseconds kNever = nanoseconds::max();

// Wake slots whose callback runs on this thread (innermost last). A callback
// that cancels or destroys its own subscription, or appends and so wakes it
// again, already holds the slot's mutex and must not wait for itself.
thread_local std::vector<const void*> t_running_wakes;

bool runningOnThisThread(const void* slot) {
  return std::find(t_running_wakes.begin(), t_running_wakes.end(), slot) != t_running_wakes.end();
}

// Saturates so that a huge retention means "forever" instead of overflowing.
nanoseconds addSaturating(nanoseconds now, nanoseconds retention) {
  if (retention > nanoseconds::zero() && now > kNever - retention) return kNever;
  return now + retention;
}

nanoseconds steadyNow() { return std::chrono::steady_clock::now().time_since_epoch(); }

void setTimestamp(google::protobuf::Timestamp* timestamp,
                  std::chrono::system_clock::time_point time) {
  const auto since_epoch = std::chrono::duration_cast<nanoseconds>(time.time_since_epoch());
  const auto seconds = std::chrono::floor<std::chrono::seconds>(since_epoch);
  timestamp->set_seconds(seconds.count());
  timestamp->set_nanos(static_cast<int32_t>((since_epoch - seconds).count()));
}

}  // namespace

// Appenders copy the shared_ptr under the log's lock and call fire() after
// releasing it, so the slot outlives a subscription destroyed in between.
// `mutex` is held while the callback runs and cancel() takes it, which is what
// guarantees that no wake starts or is still running (on another thread) once
// cancel() has returned.
struct EventSubscription::WakeSlot {
  std::mutex mutex;
  std::function<void()> wake;
  bool cancelled = false;  // Guarded by mutex.

  void fire() {
    if (runningOnThisThread(this)) {
      // Re-entered from our own callback: the outer frame holds the mutex.
      if (!cancelled && wake) wake();
      return;
    }
    std::lock_guard lock(mutex);
    if (cancelled || !wake) return;
    t_running_wakes.push_back(this);
    struct Pop {
      ~Pop() { t_running_wakes.pop_back(); }
    } pop;
    wake();
  }

  void cancel() {
    if (runningOnThisThread(this)) {
      cancelled = true;
      return;
    }
    std::lock_guard lock(mutex);
    cancelled = true;
  }
};

EventSubscription::~EventSubscription() { cancel(); }

EventPtr EventSubscription::pop() {
  std::lock_guard lock(mutex_);
  if (queue_.empty()) return nullptr;
  EventPtr event = std::move(queue_.front());
  queue_.pop_front();
  if (replay_left_ > 0) --replay_left_;
  last_popped_seq_ = event->seq();
  return event;
}

std::vector<EventPtr> EventSubscription::popUpTo(size_t max) {
  std::lock_guard lock(mutex_);
  std::vector<EventPtr> out;
  const size_t n = std::min(max, queue_.size());
  out.reserve(n);
  for (size_t i = 0; i < n; ++i) {
    out.push_back(std::move(queue_.front()));
    queue_.pop_front();
  }
  replay_left_ -= std::min(replay_left_, n);
  if (!out.empty()) last_popped_seq_ = out.back()->seq();
  return out;
}

bool EventSubscription::overflowed() const {
  std::lock_guard lock(mutex_);
  return overflowed_;
}

uint64_t EventSubscription::lastPoppedSeq() const {
  std::lock_guard lock(mutex_);
  return last_popped_seq_;
}

void EventSubscription::cancel() {
  {
    // Ignore deliveries racing with the unregistration below.
    std::lock_guard lock(mutex_);
    cancelled_ = true;
  }
  if (EventLog* log = log_.exchange(nullptr)) log->unsubscribe(this);
  if (wake_) wake_->cancel();
}

bool EventSubscription::deliver(const EventPtr& event) {
  if (!behaviors_.empty() &&
      std::find(behaviors_.begin(), behaviors_.end(), event->behavior()) == behaviors_.end()) {
    return false;
  }
  std::lock_guard lock(mutex_);
  if (cancelled_ || overflowed_) return false;
  if (queue_.size() - replay_left_ >= limit_) {
    // Keep what is queued so the reader can drain it and resume after the
    // last event it got; wake it once so it notices even if it is idle.
    overflowed_ = true;
    return true;
  }
  const bool was_empty = queue_.empty();
  queue_.push_back(event);
  return was_empty;
}

EventLog::EventLog(EventLogOptions options) : options_(std::move(options)), wall_now_(&steadyNow) {
  if (options_.incarnation.empty()) options_.incarnation = newIncarnationId();
}

EventLog::~EventLog() {
  std::lock_guard lock(mutex_);
  for (EventSubscription* subscription : subscribers_) subscription->log_.store(nullptr);
  subscribers_.clear();
}

EventPtr EventLog::append(v1::BehaviorEvent event) {
  event.set_incarnation(options_.incarnation);
  event.set_robot_id(options_.robot_id);
  event.set_system(options_.system);

  std::vector<std::shared_ptr<EventSubscription::WakeSlot>> to_wake;
  EventPtr stored;
  {
    std::lock_guard lock(mutex_);
    // Under the lock so that wall_time does not go backwards as seq increases.
    setTimestamp(event.mutable_wall_time(), std::chrono::system_clock::now());
    event.set_seq(next_seq_++);
    stored = std::make_shared<const v1::BehaviorEvent>(std::move(event));

    const nanoseconds now = wall_now_();
    nanoseconds expires_at = kNever;
    if (stored->activation_id().empty()) {
      // Belongs to no activation, so no `finished` would ever release it.
      expires_at = addSaturating(now, options_.retention);
    } else if (stored->has_finished()) {
      expires_at = addSaturating(now, options_.retention);
      for (Retained& retained : retained_) {
        // Events already counting down keep their expiry, so a duplicate
        // `finished` cannot extend it.
        if (retained.expires_at == kNever &&
            retained.event->activation_id() == stored->activation_id() &&
            retained.event->behavior() == stored->behavior()) {
          retained.expires_at = expires_at;
        }
      }
    }
    retained_.push_back({stored, expires_at});
    evictLocked(now);

    for (EventSubscription* subscription : subscribers_) {
      if (subscription->deliver(stored)) to_wake.push_back(subscription->wake_);
    }
  }
  // Outside the lock: a callback may pop, cancel or even append.
  for (const auto& slot : to_wake) slot->fire();
  return stored;
}

std::unique_ptr<EventSubscription> EventLog::subscribe(const SubscribeOptions& options,
                                                       std::function<void()> wake) {
  std::unique_ptr<EventSubscription> subscription(new EventSubscription());
  subscription->behaviors_ = options.behaviors;
  subscription->limit_ = std::max<size_t>(1, options_.subscriber_queue_limit);
  subscription->wake_ = std::make_shared<EventSubscription::WakeSlot>();
  subscription->wake_->wake = std::move(wake);

  v1::WatchEventsStart& start = subscription->start_;
  start.set_incarnation(options_.incarnation);
  const bool incarnation_changed =
      !options.incarnation.empty() && options.incarnation != options_.incarnation;
  start.set_incarnation_changed(incarnation_changed);
  // since_seq of another run says nothing about this one.
  const uint64_t since_seq = incarnation_changed ? 0 : options.since_seq;

  // Summary, replay and registration under one lock hold: an event appended
  // concurrently is either replayed or delivered live, never both or neither.
  std::lock_guard lock(mutex_);
  evictLocked(wall_now_());
  const uint64_t latest_seq = next_seq_ - 1;
  const uint64_t oldest_retained_seq = retained_.empty() ? 0 : retained_.front().event->seq();
  start.set_oldest_retained_seq(oldest_retained_seq);
  start.set_latest_seq(latest_seq);

  // Retained seqs are consecutive (eviction only pops the front), so the gap
  // between since_seq and the oldest retained event is exactly what was lost.
  uint64_t dropped = 0;
  if (!retained_.empty()) {
    if (since_seq + 1 < oldest_retained_seq) dropped = oldest_retained_seq - since_seq - 1;
  } else if (latest_seq > since_seq) {
    dropped = latest_seq - since_seq;
  }
  start.set_events_dropped(dropped > 0);
  start.set_dropped_count(dropped);

  auto first = std::partition_point(retained_.begin(), retained_.end(),
                                    [&](const Retained& r) { return r.event->seq() <= since_seq; });
  const auto& behaviors = subscription->behaviors_;
  for (auto it = first; it != retained_.end(); ++it) {
    if (behaviors.empty() ||
        std::find(behaviors.begin(), behaviors.end(), it->event->behavior()) != behaviors.end()) {
      subscription->queue_.push_back(it->event);
    }
  }
  subscription->replay_left_ = subscription->queue_.size();

  subscription->log_.store(this);
  subscribers_.push_back(subscription.get());
  return subscription;
}

uint64_t EventLog::latestSeq() const {
  std::lock_guard lock(mutex_);
  return next_seq_ - 1;
}

size_t EventLog::retainedCount() const {
  std::lock_guard lock(mutex_);
  // Count what evictLocked would leave now, without mutating in a const call.
  const nanoseconds now = wall_now_();
  size_t expired = 0;
  while (expired < retained_.size() && retained_[expired].expires_at <= now) ++expired;
  return retained_.size() - expired;
}

void EventLog::setWallClockForTesting(std::function<std::chrono::nanoseconds()> now) {
  std::lock_guard lock(mutex_);
  wall_now_ = std::move(now);
}

void EventLog::evictLocked(std::chrono::nanoseconds now) {
  // Only from the front, so that retained seqs stay consecutive: an expired
  // event behind a running activation's event waits for it.
  while (!retained_.empty() &&
         (retained_.size() > options_.capacity || retained_.front().expires_at <= now)) {
    retained_.pop_front();
  }
}

void EventLog::unsubscribe(EventSubscription* subscription) {
  std::lock_guard lock(mutex_);
  subscribers_.erase(std::remove(subscribers_.begin(), subscribers_.end(), subscription),
                     subscribers_.end());
}

std::string newIncarnationId() {
  std::random_device device;
  std::seed_seq seed{device(), device(), device(), device(),
                     device(), device(), device(), device()};
  std::mt19937_64 engine(seed);
  static constexpr char kHex[] = "0123456789abcdef";
  std::string id;
  id.reserve(32);
  for (int half = 0; half < 2; ++half) {
    const uint64_t value = engine();
    for (int shift = 60; shift >= 0; shift -= 4) id.push_back(kHex[(value >> shift) & 0xf]);
  }
  return id;
}

}  // namespace behaviorlib
