#include "simulator/service/publish_queue.h"

#include <utility>
#include <vector>

namespace behaviorlib::sim {

PublishQueue::PublishQueue(ChannelRoutes& client, PublishQueueLimits limits, bool flushed_by_caller)
    : client_(client),
      limits_(limits),
      flushed_by_caller_(flushed_by_caller),
      thread_([this] { run(); }) {}

PublishQueue::~PublishQueue() {
  {
    std::lock_guard lock(mutex_);
    stopping_ = true;
  }
  cv_.notify_all();
  if (thread_.joinable()) thread_.join();
}

void PublishQueue::push(std::string topic, std::unique_ptr<google::protobuf::Message> sample) {
  std::deque<Entry> evicted;  // freed outside the lock
  std::unique_ptr<google::protobuf::Message> replaced;
  {
    std::lock_guard lock(mutex_);
    if (interest_ != nullptr && !interest_->wanted(topic) && !seen_topics_.insert(topic).second) {
      Newest& newest = newest_[topic];
      replaced = std::exchange(newest.sample, std::move(sample));
      newest.published = false;
      newest.sent_while_wanted = false;
      ++gated_;
      return;
    }
    if (interest_ != nullptr && throttleLocked(topic, sample, &replaced)) {
      ++gated_;
      return;
    }
    // Queued while wanted: the broker keeps it and its subscribers get it, so
    // a topic found wanted by the next interestChanged() needs no re-send (a
    // re-send would repeat it, or even follow it with an older sample).
    if (interest_ != nullptr) newest_[topic].sent_while_wanted = interest_->wanted(topic);
    queueLocked(std::move(topic), std::move(sample), &evicted);
  }
  if (!flushed_by_caller_) cv_.notify_one();
}

bool PublishQueue::throttleLocked(const std::string& topic,
                                  std::unique_ptr<google::protobuf::Message>& sample,
                                  std::unique_ptr<google::protobuf::Message>* replaced) {
  const double rate = interest_->maxRateHz(topic);
  if (rate <= 0 || !interest_->wanted(topic)) return false;
  Newest& newest = newest_[topic];
  const auto now = std::chrono::steady_clock::now();
  if (now >= newest.next_send && !newest.throttled) {
    newest.next_send = now + std::chrono::duration_cast<std::chrono::steady_clock::duration>(
                                 std::chrono::duration<double>(1.0 / rate));
    return false;
  }
  *replaced = std::exchange(newest.sample, std::move(sample));
  newest.published = false;
  newest.sent_while_wanted = false;
  if (!newest.throttled) {
    newest.throttled = true;
    throttled_.insert(topic);
    cv_.notify_one();  // the thread waits for the interval's end now
  }
  return true;
}

std::chrono::steady_clock::time_point PublishQueue::releaseDueLocked(std::deque<Entry>* evicted) {
  const auto now = std::chrono::steady_clock::now();
  auto next = std::chrono::steady_clock::time_point::max();
  for (auto it = throttled_.begin(); it != throttled_.end();) {
    Newest& newest = newest_[*it];
    const bool wanted = interest_ != nullptr && interest_->wanted(*it);
    const double rate = wanted ? interest_->maxRateHz(*it) : 0;
    if (wanted && rate > 0 && now < newest.next_send) {
      next = std::min(next, newest.next_send);
      ++it;
      continue;
    }
    newest.throttled = false;
    if (wanted && newest.sample && !newest.published) {
      // Its interval passed, or every sample is wanted now: it goes.
      newest.sent_while_wanted = true;
      if (rate > 0) {
        newest.next_send = now + std::chrono::duration_cast<std::chrono::steady_clock::duration>(
                                     std::chrono::duration<double>(1.0 / rate));
      }
      queueLocked(*it, std::move(newest.sample), evicted);
      kicked_ = true;
    }
    // Unwanted meanwhile: it stays held as any gated sample.
    it = throttled_.erase(it);
  }
  return next;
}

void PublishQueue::queueLocked(std::string topic, std::unique_ptr<google::protobuf::Message> sample,
                               std::deque<Entry>* evicted) {
  const std::size_t bytes = sample->ByteSizeLong() + topic.size();
  while (!queue_.empty() &&
         (queue_.size() >= limits_.max_messages || queued_bytes_ + bytes > limits_.max_bytes)) {
    queued_bytes_ -= queue_.front().bytes;
    evicted->push_back(std::move(queue_.front()));
    queue_.pop_front();
    ++dropped_;
  }
  queue_.push_back({std::move(topic), std::move(sample), bytes});
  queued_bytes_ += bytes;
}

bool PublishQueue::waitDrained(std::chrono::milliseconds timeout) {
  std::unique_lock lock(mutex_);
  return drained_cv_.wait_for(lock, timeout,
                              [this] { return stopping_ || (queue_.empty() && !publishing_); });
}

void PublishQueue::setInterest(const ChannelRoutes* interest) {
  {
    std::lock_guard lock(mutex_);
    interest_ = interest;
  }
  interestChanged();
}

void PublishQueue::interestChanged() {
  std::deque<Entry> evicted;
  bool queued = false;
  {
    std::lock_guard lock(mutex_);
    std::unordered_set<std::string> wanted;
    for (auto& [topic, newest] : newest_) {
      if (interest_ != nullptr && !interest_->wanted(topic)) {
        newest.sent_while_wanted = false;  // the broker drops a stale sample nobody wants
        continue;
      }
      wanted.insert(topic);
      if (newest.throttled) continue;  // releaseDueLocked decides
      // Wanted again: the newest sample goes out at once (the broker kept
      // none while nobody wanted the topic), unless it was wanted already.
      if (wanted_.contains(topic) || !newest.sample || newest.sent_while_wanted) continue;
      std::unique_ptr<google::protobuf::Message> sample;
      if (newest.published) {
        sample.reset(newest.sample->New());
        sample->CopyFrom(*newest.sample);
      } else {
        sample = std::move(newest.sample);
      }
      queueLocked(topic, std::move(sample), &evicted);
      queued = true;
    }
    wanted_ = std::move(wanted);
    // A rate that went up, or away, lets a held sample go sooner.
    if (!throttled_.empty()) queued = true;
  }
  if (queued) {
    {
      std::lock_guard lock(mutex_);
      kicked_ = true;
    }
    cv_.notify_one();
  }
}

absl::Status PublishQueue::flush(bool sync) {
  std::vector<Entry> batch;
  std::deque<Entry> evicted;
  absl::Status first = absl::OkStatus();
  std::unique_lock lock(mutex_);
  // Not beside another batch: samples of a topic go out in order.
  drained_cv_.wait(lock, [this] { return stopping_ || !publishing_; });
  if (stopping_) return absl::CancelledError("the publish queue is stopping");
  releaseDueLocked(&evicted);
  do {
    takeBatchLocked(batch);
    const bool last = queue_.empty();
    if (batch.empty() && !(sync && last)) break;
    publishing_ = true;
    lock.unlock();
    absl::Status status = publishBatch(batch, sync && last);
    if (first.ok() && !status.ok()) first = std::move(status);
    lock.lock();
    publishing_ = false;
    keepNewestLocked(batch);
    lock.unlock();
    batch.clear();  // the samples not kept are freed outside the lock
    evicted.clear();
    lock.lock();
  } while (!queue_.empty());
  kicked_ = false;
  drained_cv_.notify_all();
  return first;
}

void PublishQueue::takeBatchLocked(std::vector<Entry>& batch) {
  // Everything queued goes in one batch (one write, one broker read),
  // bounded so that a message stays far below gRPC's 4 MiB limit; a larger
  // sample goes alone.
  std::size_t bytes = 0;
  while (!queue_.empty() && batch.size() < kMaxBatchSamples &&
         (batch.empty() || bytes + queue_.front().bytes <= kMaxBatchBytes)) {
    bytes += queue_.front().bytes;
    queued_bytes_ -= queue_.front().bytes;
    batch.push_back(std::move(queue_.front()));
    queue_.pop_front();
  }
}

absl::Status PublishQueue::publishBatch(const std::vector<Entry>& batch, bool sync) {
  std::vector<channel::ChannelClient::TopicSample> samples;
  samples.reserve(batch.size());
  for (const Entry& entry : batch) samples.push_back({entry.topic, entry.sample.get()});
  absl::Status status = client_.publishAll(samples, sync);
  if (status.ok()) {
    published_ += batch.size();
  } else {
    dropped_ += batch.size();
  }
  return status;
}

void PublishQueue::keepNewestLocked(std::vector<Entry>& batch) {
  if (interest_ == nullptr) return;
  // Each kept as its topic's newest unless a newer one is held already (in
  // order: a later sample of the same topic replaces an earlier one).
  for (Entry& entry : batch) {
    Newest& newest = newest_[entry.topic];
    if (newest.published || !newest.sample) {
      newest.sample = std::move(entry.sample);
      newest.published = true;
    }
  }
}

void PublishQueue::run() {
  std::vector<Entry> batch;
  std::deque<Entry> evicted;
  std::unique_lock lock(mutex_);
  while (true) {
    while (true) {
      const auto next = releaseDueLocked(&evicted);
      // Not beside flush(): samples of a topic go out in order. Flushed by
      // the caller, pushes do not wake this thread; what it is woken for (a
      // held sample released by interest or by its rate) goes out at once,
      // with whatever else is queued then, as when free running: the
      // stepping thread may be waiting for followers, or for time to start.
      if (stopping_ || (!queue_.empty() && !publishing_ && (!flushed_by_caller_ || kicked_))) {
        break;
      }
      if (next == std::chrono::steady_clock::time_point::max()) {
        cv_.wait(lock);
      } else {
        cv_.wait_until(lock, next);
      }
    }
    if (stopping_) return;
    if (!evicted.empty()) {
      lock.unlock();
      evicted.clear();
      lock.lock();
    }
    takeBatchLocked(batch);
    kicked_ = !queue_.empty() && kicked_;  // the rest too, in further batches
    publishing_ = true;
    lock.unlock();
    publishBatch(batch, false).IgnoreError();  // counted as dropped
    lock.lock();
    publishing_ = false;
    drained_cv_.notify_all();
    keepNewestLocked(batch);
    lock.unlock();
    batch.clear();  // the samples not kept are freed outside the lock
    lock.lock();
  }
}

}  // namespace behaviorlib::sim
