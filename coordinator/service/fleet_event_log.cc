#include "coordinator/service/fleet_event_log.h"

#include <algorithm>
#include <chrono>
#include <utility>

#include "behaviorlib/event_log.h"

namespace behaviorlib::coordinator {

namespace {

// Wake slots whose callback runs on this thread: a callback that cancels its
// own subscription already holds the slot's mutex and must not wait for
// itself (the same scheme as behaviorlib::EventLog).
thread_local std::vector<const void*> t_running_wakes;

bool runningOnThisThread(const void* slot) {
  return std::find(t_running_wakes.begin(), t_running_wakes.end(), slot) != t_running_wakes.end();
}

bool contains(const std::vector<std::string>& list, const std::string& value) {
  return std::find(list.begin(), list.end(), value) != list.end();
}

void setNow(google::protobuf::Timestamp* timestamp) {
  const auto since_epoch = std::chrono::duration_cast<std::chrono::nanoseconds>(
      std::chrono::system_clock::now().time_since_epoch());
  const auto seconds = std::chrono::floor<std::chrono::seconds>(since_epoch);
  timestamp->set_seconds(seconds.count());
  timestamp->set_nanos(static_cast<int32_t>((since_epoch - seconds).count()));
}

// The event of a stored record, sharing its ownership.
FleetEventPtr eventOf(const FleetEventRecordPtr& record) {
  return FleetEventPtr(record, &record->event());
}

}  // namespace

const std::string& FleetEventRecord::wire() const {
  std::call_once(serialized_, [this] { event_.SerializeToString(&wire_); });
  return wire_;
}

bool matchesFilter(const v1::FleetEvent& event, const std::vector<std::string>& robot_ids,
                   const std::vector<std::string>& behaviors) {
  if (event.has_behavior_event()) {
    const auto& e = event.behavior_event();
    return (robot_ids.empty() || contains(robot_ids, e.robot_id())) &&
           (behaviors.empty() || contains(behaviors, e.behavior()));
  }
  if (event.has_system_state_changed()) {
    return behaviors.empty() &&
           (robot_ids.empty() ||
            contains(robot_ids, event.system_state_changed().system().robot_id()));
  }
  return robot_ids.empty() && behaviors.empty();
}

// The wake callback lives apart from the subscription, so an appender that is
// about to call it keeps it alive even if the subscription is destroyed
// meanwhile. `mutex` is held while the callback runs and by cancel(), so no
// wake runs once cancel() has returned.
struct FleetSubscription::WakeSlot {
  std::mutex mutex;
  std::function<void()> wake;
  bool cancelled = false;

  void fire() {
    if (runningOnThisThread(this)) {
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

FleetSubscription::~FleetSubscription() { cancel(); }

FleetEventPtr FleetSubscription::pop() {
  std::vector<FleetEventRecordPtr> one = popRecordsUpTo(1);
  return one.empty() ? nullptr : eventOf(one.front());
}

std::vector<FleetEventPtr> FleetSubscription::popUpTo(size_t max) {
  std::vector<FleetEventPtr> out;
  for (const FleetEventRecordPtr& record : popRecordsUpTo(max)) out.push_back(eventOf(record));
  return out;
}

std::vector<FleetEventRecordPtr> FleetSubscription::popRecordsUpTo(size_t max, size_t max_bytes) {
  std::lock_guard lock(mutex_);
  std::vector<FleetEventRecordPtr> out;
  size_t bytes = 0;
  while (out.size() < max && !queue_.empty()) {
    if (max_bytes != static_cast<size_t>(-1)) {
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

bool FleetSubscription::overflowed() const {
  std::lock_guard lock(mutex_);
  return overflowed_;
}

uint64_t FleetSubscription::lastPoppedSeq() const {
  std::lock_guard lock(mutex_);
  return last_popped_seq_;
}

void FleetSubscription::cancel() {
  {
    std::lock_guard lock(mutex_);
    cancelled_ = true;
  }
  if (FleetEventLog* log = log_.exchange(nullptr)) log->unsubscribe(this);
  if (wake_) wake_->cancel();
}

bool FleetSubscription::deliver(const FleetEventRecordPtr& record) {
  if (!matchesFilter(record->event(), robot_ids_, behaviors_)) return false;
  std::lock_guard lock(mutex_);
  if (cancelled_ || overflowed_) return false;
  if (queue_.size() - replay_left_ >= limit_) {
    // Keep what is queued so the reader drains it and resumes after the last
    // event it got; wake it once so it notices even when idle.
    overflowed_ = true;
    return true;
  }
  const bool was_empty = queue_.empty();
  queue_.push_back(record);
  return was_empty;
}

FleetEventLog::FleetEventLog(FleetEventLogOptions options) : options_(std::move(options)) {
  if (options_.incarnation.empty()) options_.incarnation = newIncarnationId();
  options_.capacity = std::max<size_t>(1, options_.capacity);
}

FleetEventLog::~FleetEventLog() {
  std::lock_guard lock(mutex_);
  for (FleetSubscription* subscription : subscribers_) subscription->log_.store(nullptr);
  subscribers_.clear();
}

FleetEventPtr FleetEventLog::append(v1::FleetEvent event) {
  std::vector<v1::FleetEvent> one;
  one.push_back(std::move(event));
  return appendEvents(std::move(one));
}

void FleetEventLog::appendAll(std::vector<v1::FleetEvent> events) {
  if (!events.empty()) appendEvents(std::move(events));
}

FleetEventPtr FleetEventLog::appendEvents(std::vector<v1::FleetEvent> events) {
  std::vector<std::shared_ptr<FleetSubscription::WakeSlot>> to_wake;
  FleetEventRecordPtr stored;
  {
    std::lock_guard lock(mutex_);
    for (v1::FleetEvent& event : events) {
      event.set_incarnation(options_.incarnation);
      // Under the lock so that wall_time never goes backwards as seq grows.
      setNow(event.mutable_wall_time());
      event.set_seq(next_seq_++);
      stored = std::make_shared<const FleetEventRecord>(std::move(event));
      retained_.push_back(stored);
      while (retained_.size() > options_.capacity) retained_.pop_front();
      for (FleetSubscription* subscription : subscribers_) {
        if (subscription->deliver(stored)) to_wake.push_back(subscription->wake_);
      }
    }
  }
  // A subscriber's queue goes from empty to not empty once per batch.
  for (const auto& slot : to_wake) slot->fire();
  return stored ? eventOf(stored) : nullptr;
}

std::unique_ptr<FleetSubscription> FleetEventLog::subscribe(const FleetSubscribeOptions& options,
                                                            std::function<void()> wake) {
  std::unique_ptr<FleetSubscription> subscription(new FleetSubscription());
  subscription->robot_ids_ = options.robot_ids;
  subscription->behaviors_ = options.behaviors;
  subscription->limit_ = std::max<size_t>(1, options_.subscriber_queue_limit);
  subscription->wake_ = std::make_shared<FleetSubscription::WakeSlot>();
  subscription->wake_->wake = std::move(wake);

  v1::WatchEventsStart& start = subscription->start_;
  start.set_incarnation(options_.incarnation);
  const bool incarnation_changed =
      !options.incarnation.empty() && options.incarnation != options_.incarnation;
  start.set_incarnation_changed(incarnation_changed);
  // A since_seq of another run says nothing about this one.
  const uint64_t since_seq = incarnation_changed ? 0 : options.since_seq;

  std::lock_guard lock(mutex_);
  const uint64_t latest_seq = next_seq_ - 1;
  const uint64_t oldest_retained_seq = retained_.empty() ? 0 : retained_.front()->event().seq();
  start.set_oldest_retained_seq(oldest_retained_seq);
  start.set_latest_seq(latest_seq);
  // Retained seqs are consecutive (eviction pops the front only), so the gap
  // between since_seq and the oldest retained event is exactly what was lost.
  uint64_t dropped = 0;
  if (!retained_.empty()) {
    if (since_seq + 1 < oldest_retained_seq) dropped = oldest_retained_seq - since_seq - 1;
  } else if (latest_seq > since_seq) {
    dropped = latest_seq - since_seq;
  }
  start.set_events_dropped(dropped > 0);
  start.set_dropped_count(dropped);

  auto first = std::partition_point(
      retained_.begin(), retained_.end(),
      [&](const FleetEventRecordPtr& r) { return r->event().seq() <= since_seq; });
  for (auto it = first; it != retained_.end(); ++it) {
    if (matchesFilter((*it)->event(), subscription->robot_ids_, subscription->behaviors_)) {
      subscription->queue_.push_back(*it);
    }
  }
  subscription->replay_left_ = subscription->queue_.size();
  subscription->last_popped_seq_ = std::min(since_seq, latest_seq);
  subscription->log_.store(this);
  subscribers_.push_back(subscription.get());
  return subscription;
}

uint64_t FleetEventLog::latestSeq() const {
  std::lock_guard lock(mutex_);
  return next_seq_ - 1;
}

size_t FleetEventLog::retainedCount() const {
  std::lock_guard lock(mutex_);
  return retained_.size();
}

void FleetEventLog::unsubscribe(FleetSubscription* subscription) {
  std::lock_guard lock(mutex_);
  subscribers_.erase(std::remove(subscribers_.begin(), subscribers_.end(), subscription),
                     subscribers_.end());
}

}  // namespace behaviorlib::coordinator
