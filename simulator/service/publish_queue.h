#pragma once

// PublishQueue: samples waiting to go to the data channel, and the thread
// that publishes them, so that the physics never waits for the broker; what
// is queued when the thread comes round goes in one batch. The
// queue is bounded in messages and in bytes; when full, the oldest samples
// are dropped and counted.
//
//   PublishQueue queue(client, {.max_messages = 10000});
//   queue.push("robots/drone1/imu", std::make_unique<v1::Imu>(imu));  // any thread

#include <google/protobuf/message.h>

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstddef>
#include <cstdint>
#include <deque>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <unordered_map>
#include <unordered_set>

#include "absl/status/status.h"
#include "simulator/service/channel_routes.h"

namespace behaviorlib::sim {

struct PublishQueueLimits {
  std::size_t max_messages = 10000;
  std::size_t max_bytes = std::size_t{64} << 20;
};

class PublishQueue {
 public:
  /// `client` must outlive the queue. With `flushed_by_caller` (the
  /// deterministic mode), pushed samples go out when flush() is called, on
  /// the caller's thread: the stepping thread publishes a quantum and syncs
  /// in one round trip, with no hand-over to the queue's thread. That thread
  /// then publishes only what it is woken for: held samples released by
  /// interest (a new subscriber, a GetLatest) or by their rate.
  PublishQueue(ChannelRoutes& client, PublishQueueLimits limits, bool flushed_by_caller = false);
  /// Stops the thread; samples still queued are not published.
  ~PublishQueue();
  PublishQueue(const PublishQueue&) = delete;
  PublishQueue& operator=(const PublishQueue&) = delete;

  /// Queues a sample for `topic`. Thread-safe; never blocks on the broker.
  /// With an interest watch, a sample of a topic nobody wants is held
  /// instead (the newest per topic), except the topic's first, which makes
  /// the topic known to the broker. A topic whose readers want it only at a
  /// rate (ChannelRoutes::maxRateHz: a console drawing 10 times a second) is
  /// published at most that often: a sample that comes sooner is held, the
  /// newest replacing it, and goes out when the interval has passed.
  void push(std::string topic, std::unique_ptr<google::protobuf::Message> sample);

  /// Waits until every queued sample went to the broker, or `timeout`;
  /// false on timeout.
  bool waitDrained(std::chrono::milliseconds timeout);
  /// Publishes everything queued now, on this thread, in batches; with
  /// `sync`, the last batch carries ChannelRoutes' sync (the broker answers
  /// once it took everything: one round trip). The first error.
  absl::Status flush(bool sync);

  /// Gates publishing by `interest` (nullptr: publish everything). It must
  /// stay valid until replaced by nullptr.
  void setInterest(const ChannelRoutes* interest);
  /// Queues the held samples of the topics now wanted (call when the watch
  /// reports a change): a new subscriber gets the newest sample at once.
  void interestChanged();
  /// Samples held back because nobody wanted their topic or its readers
  /// wanted fewer (replaced by a newer one, or published later).
  uint64_t gatedCount() const { return gated_.load(); }

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
  // One batch from the front of the queue (bounded as below).
  void takeBatchLocked(std::vector<Entry>& batch);
  // After a batch went out: its samples as their topics' newest.
  void keepNewestLocked(std::vector<Entry>& batch);
  // Publishes `batch` (the lock not held); counts it.
  absl::Status publishBatch(const std::vector<Entry>& batch, bool sync);
  // One batch's bounds (ChannelClient::publishAll).
  static constexpr std::size_t kMaxBatchSamples = 256;
  static constexpr std::size_t kMaxBatchBytes = std::size_t{1} << 20;

  ChannelRoutes& client_;
  const PublishQueueLimits limits_;
  const bool flushed_by_caller_;
  std::mutex mutex_;
  std::condition_variable cv_;
  void queueLocked(std::string topic, std::unique_ptr<google::protobuf::Message> sample,
                   std::deque<Entry>* evicted);
  // Rate-limited topics (ChannelRoutes::maxRateHz): true when `sample` is
  // held for its topic's next interval instead of queued now.
  bool throttleLocked(const std::string& topic, std::unique_ptr<google::protobuf::Message>& sample,
                      std::unique_ptr<google::protobuf::Message>* replaced);
  // Queues the held samples whose interval has passed (or whose topic is
  // now wanted at every sample); returns the time of the next one due.
  std::chrono::steady_clock::time_point releaseDueLocked(std::deque<Entry>* evicted);

  std::deque<Entry> queue_;
  std::size_t queued_bytes_ = 0;
  bool publishing_ = false;  // a batch is being published (the thread or flush())
  // Flushed by the caller: the thread was woken to send released samples.
  bool kicked_ = false;
  std::condition_variable drained_cv_;
  const ChannelRoutes* interest_ = nullptr;
  std::unordered_set<std::string> seen_topics_;  // published at least once
  // With an interest watch: the newest sample of every topic, and whether it
  // went out already (a topic wanted again gets it, or a copy, at once).
  struct Newest {
    std::unique_ptr<google::protobuf::Message> sample;
    bool published = false;
    bool sent_while_wanted = false;  // the newest was queued while wanted
    // A rate-limited topic: when its next sample may go, and whether the
    // held sample waits for that (rather than for interest).
    std::chrono::steady_clock::time_point next_send{};
    bool throttled = false;
  };
  std::unordered_map<std::string, Newest> newest_;
  std::unordered_set<std::string> wanted_;     // at the last interestChanged()
  std::unordered_set<std::string> throttled_;  // topics with Newest::throttled
  std::atomic<uint64_t> gated_{0};
  bool stopping_ = false;
  std::atomic<uint64_t> published_{0};
  std::atomic<uint64_t> dropped_{0};
  std::thread thread_;  // last: started once the rest is ready
};

}  // namespace behaviorlib::sim
