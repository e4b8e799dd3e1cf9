#pragma once

// The common data channel broker: behaviorlib.v1.DataChannel over the gRPC
// callback API. Publishers stream typed samples onto named topics; each
// subscription gets its own bounded buffer, so a slow subscriber loses
// samples (counted in dropped_count) instead of slowing publishers or other
// subscribers. No thread is held per stream.
//
//   prometheus::Registry registry;
//   behaviorlib::channel::Broker broker(registry);
//   grpc::ServerBuilder builder;
//   builder.RegisterService(&broker);
//   auto server = builder.BuildAndStart();
//   ...
//   broker.shutdown();  // ends every stream, then
//   server->Shutdown();

#include <atomic>
#include <chrono>
#include <map>
#include <memory>
#include <set>
#include <string>
#include <thread>
#include <unordered_set>
#include <vector>

#include "absl/base/thread_annotations.h"
#include "absl/strings/string_view.h"
#include "absl/synchronization/mutex.h"
#include "behaviorlib/channel/topic.h"
#include "behaviorlib/v1/channel.grpc.pb.h"

namespace prometheus {
class Counter;
class Gauge;
template <typename T>
class Family;
class Registry;
}  // namespace prometheus

namespace behaviorlib::channel {

struct BrokerOptions {
  /// Offer delivery through shared-memory rings to subscribers on this host
  /// that ask for it (SubscribeRequest.shared_memory; decision 20).
  bool shared_memory = true;
  /// Topics the broker keeps; publishing or subscribing to a new topic
  /// beyond is RESOURCE_EXHAUSTED (a fleet has some tens per vehicle).
  std::size_t max_topics = 10'000;
};

/// Implements behaviorlib.v1.DataChannel. Thread-safe; register it on a
/// grpc::ServerBuilder. It must outlive the server it is registered on.
class Broker final : public v1::DataChannel::CallbackService {
 public:
  /// Metrics (behaviorlib_channel_*) are registered on `registry`, which must
  /// outlive the broker.
  explicit Broker(prometheus::Registry& registry, BrokerOptions options = {});
  ~Broker() override;
  Broker(const Broker&) = delete;
  Broker& operator=(const Broker&) = delete;

  grpc::ServerReadReactor<v1::PublishRequest>* Publish(grpc::CallbackServerContext* context,
                                                       v1::PublishResponse* response) override;
  grpc::ServerBidiReactor<v1::PublishRequest, v1::PublishResponse>* PublishAcked(
      grpc::CallbackServerContext* context) override;
  grpc::ServerWriteReactor<v1::SubscribeResponse>* Subscribe(
      grpc::CallbackServerContext* context, const v1::SubscribeRequest* request) override;
  grpc::ServerUnaryReactor* GetLatest(grpc::CallbackServerContext* context,
                                      const v1::GetLatestRequest* request,
                                      v1::GetLatestResponse* response) override;
  grpc::ServerUnaryReactor* ListTopics(grpc::CallbackServerContext* context,
                                       const v1::ListTopicsRequest* request,
                                       v1::ListTopicsResponse* response) override;
  grpc::ServerWriteReactor<v1::WatchInterestResponse>* WatchInterest(
      grpc::CallbackServerContext* context, const v1::WatchInterestRequest* request) override;

  /// Ends every Publish and Subscribe stream with UNAVAILABLE and refuses new
  /// ones, so that grpc::Server::Shutdown does not wait for clients that keep
  /// their streams open. Call it before shutting the server down.
  void shutdown();

 private:
  class Publisher;
  class PublishReactor;
  class AckedPublishReactor;
  class SubscribeReactor;
  class InterestReactor;
  struct Topic;
  struct Metrics;
  using InterestReactors = std::vector<std::shared_ptr<InterestReactor>>;

  // Validates and stores one sample; fans it out to the subscribers.
  grpc::Status publish(Publisher& publisher, v1::PublishRequest& request);
  // Registers a publish stream; false when the broker is shutting down.
  bool addPublisher(Publisher* publisher);
  // Caller holds mutex_.
  /// The topic, made if new; null when a new one would pass max_topics.
  std::shared_ptr<Topic> topicLocked(const std::string& name) ABSL_EXCLUSIVE_LOCKS_REQUIRED(mutex_);
  grpc::Status tooManyTopics(const std::string& name) const;
  void removeSubscriber(const std::shared_ptr<Topic>& topic, const SubscribeReactor* subscriber);
  void removePublisher(Publisher* publisher);
  void countRejected(absl::string_view reason);
  // Shared-memory rings. Callers hold the topic's mutex (annotated at the
  // definitions: Topic is incomplete here).
  // Makes the topic's ring hold at least `slots` samples of `bytes` each
  // (a new ring supersedes a smaller one); false when none can be made.
  bool ensureRingLocked(Topic& topic, uint32_t slots, std::size_t bytes);
  // Writes `sample` into the topic's ring (growing it when it does not fit).
  void writeRingLocked(Topic& topic, const v1::SubscribeResponse& sample);
  void dropRingLocked(Topic& topic);

  // Interest (WatchInterest). Callers hold mutex_.
  // Sends every watcher whose wanted set changed its new set; the watchers
  // to pump once mutex_ is released are appended to `idle`.
  void interestChangedLocked(InterestReactors* idle) ABSL_EXCLUSIVE_LOCKS_REQUIRED(mutex_);
  // A gated topic nobody wants any more forgets its latest sample. Callers
  // also hold the topic's mutex (annotated at the definition).
  void forgetIfUnwantedLocked(Topic& topic, std::chrono::steady_clock::time_point now)
      ABSL_EXCLUSIVE_LOCKS_REQUIRED(mutex_);
  void removeInterestWatcher(const InterestReactor* watcher);
  // Thread: expires GetLatest's transient interest and its waiting calls.
  void housekeep();

  const BrokerOptions options_;
  std::unique_ptr<Metrics> metrics_;
  std::atomic<uint64_t> rings_made_{0};  // names the next ring

  // Lock order: mutex_, then Topic::mutex, then a subscription's mutex.
  absl::Mutex mutex_;
  // Sorted, for ListTopics. A topic stays once something was published on
  // it; a topic that only had waiting subscribers goes away with them.
  std::map<std::string, std::shared_ptr<Topic>, std::less<>> topics_ ABSL_GUARDED_BY(mutex_);
  std::unordered_set<Publisher*> publishers_ ABSL_GUARDED_BY(mutex_);
  InterestReactors interest_watchers_ ABSL_GUARDED_BY(mutex_);
  // Topics with a transient interest or waiting GetLatest calls.
  std::set<std::shared_ptr<Topic>> timed_topics_ ABSL_GUARDED_BY(mutex_);
  absl::CondVar housekeeping_cv_;
  bool shutting_down_ ABSL_GUARDED_BY(mutex_) = false;
  std::thread housekeeper_;  // started last
};

}  // namespace behaviorlib::channel
