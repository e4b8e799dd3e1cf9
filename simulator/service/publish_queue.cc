#include "simulator/service/publish_queue.h"

namespace behaviorlib::sim {

PublishQueue::PublishQueue(channel::ChannelClient& client, PublishQueueLimits limits)
    : client_(client), limits_(limits), thread_([this] { run(); }) {}

PublishQueue::~PublishQueue() {
  {
    std::lock_guard lock(mutex_);
    stopping_ = true;
  }
  cv_.notify_all();
  if (thread_.joinable()) thread_.join();
}

void PublishQueue::push(std::string topic, std::unique_ptr<google::protobuf::Message> sample) {
  const std::size_t bytes = sample->ByteSizeLong() + topic.size();
  std::deque<Entry> evicted;  // freed outside the lock
  {
    std::lock_guard lock(mutex_);
    while (!queue_.empty() &&
           (queue_.size() >= limits_.max_messages || queued_bytes_ + bytes > limits_.max_bytes)) {
      queued_bytes_ -= queue_.front().bytes;
      evicted.push_back(std::move(queue_.front()));
      queue_.pop_front();
      ++dropped_;
    }
    queue_.push_back({std::move(topic), std::move(sample), bytes});
    queued_bytes_ += bytes;
  }
  cv_.notify_one();
}

void PublishQueue::run() {
  std::unique_lock lock(mutex_);
  while (true) {
    cv_.wait(lock, [this] { return stopping_ || !queue_.empty(); });
    if (stopping_) return;
    Entry entry = std::move(queue_.front());
    queue_.pop_front();
    queued_bytes_ -= entry.bytes;
    lock.unlock();
    if (client_.publish(entry.topic, *entry.sample).ok()) {
      ++published_;
    } else {
      ++dropped_;
    }
    entry.sample.reset();
    lock.lock();
  }
}

}  // namespace behaviorlib::sim
