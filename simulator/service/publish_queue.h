#pragma once

// PublishQueue: samples waiting to go to the data channel, and the thread
// that publishes them, so that the physics never waits for the broker. The
// queue is bounded in messages and in bytes; when full, the oldest samples
// are dropped and counted.
//
//   PublishQueue queue(client, {.max_messages = 10000});
//   queue.push("robots/drone1/imu", std::make_unique<v1::Imu>(imu));  // any thread

#include <google/protobuf/message.h>

#include <atomic>
#include <condition_variable>
#include <cstddef>
#include <cstdint>
#include <deque>
#include <memory>
#include <mutex>
#include <string>
#include <thread>

#include "channel/channel_client.h"

namespace behaviorlib::sim {

struct PublishQueueLimits {
  std::size_t max_messages = 10000;
  std::size_t max_bytes = std::size_t{64} << 20;
};

class PublishQueue {
 public:
  /// `client` must outlive the queue.
  PublishQueue(channel::ChannelClient& client, PublishQueueLimits limits);
  /// Stops the thread; samples still queued are not published.
  ~PublishQueue();
  PublishQueue(const PublishQueue&) = delete;
  PublishQueue& operator=(const PublishQueue&) = delete;

  /// Queues a sample for `topic`. Thread-safe; never blocks on the broker.
  void push(std::string topic, std::unique_ptr<google::protobuf::Message> sample);

  uint64_t publishedCount() const { return published_.load(); }
  /// Dropped because the queue was full or the broker refused them.
  uint64_t droppedCount() const { return dropped_.load(); }

 private:
  struct Entry {
    std::string topic;
    std::unique_ptr<google::protobuf::Message> sample;
    std::size_t bytes;
  };
  void run();

  channel::ChannelClient& client_;
  const PublishQueueLimits limits_;
  std::mutex mutex_;
  std::condition_variable cv_;
  std::deque<Entry> queue_;
  std::size_t queued_bytes_ = 0;
  bool stopping_ = false;
  std::atomic<uint64_t> published_{0};
  std::atomic<uint64_t> dropped_{0};
  std::thread thread_;  // last: started once the rest is ready
};

}  // namespace behaviorlib::sim
