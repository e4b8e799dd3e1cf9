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

/// The broker's link to the other hosts of a fleet (decision 39): what
/// crosses hosts travels on a data engine (NatsLink), not on gRPC streams to
/// one broker. The broker tells the link which topics this host wants and
/// hands it the samples that local publishers put on topics another host
/// wants; the link hands the broker the other hosts' wants and samples
/// (Broker::setRemoteWanted, Broker::publishRemote). Called on the
/// broker's threads (localInterestChanged with the broker's mutex held,
/// localSample with the topic's): an
/// implementation only records and returns, and never calls back into the
/// broker from inside.
class BrokerLink {
 public:
  virtual ~BrokerLink() = default;
  /// The topics this host's subscribers and GetLatest callers want (not the
  /// ones only other hosts want), sorted, each time the set changes.
  virtual void localInterestChanged(std::vector<std::string> wanted) = 0;
  /// A sample that a publisher on this host put on a topic another host
  /// wants (never a sample that came from the link).
  virtual void localSample(const std::string& topic, const v1::SubscribeResponse& sample) = 0;
};

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

  /// Attaches the link to the fleet's other hosts. Call it once, before the
  /// server starts; `link` must outlive the broker's use of it (detach with
  /// nullptr before destroying it).
  void attachLink(BrokerLink* link);
  /// The topics that other hosts want (the union of their announcements).
  /// They count as wanted here: WatchInterest reports them, so a gating
  /// publisher resumes them, and their samples go to the link.
  void setRemoteWanted(std::vector<std::string> topics);
  /// A sample from another host: delivered to this host's subscribers as if
  /// published here, but never handed back to the link. Checked like any
  /// sample (topic name, type, the topic's type); the status says why one
  /// was refused.
  grpc::Status publishRemote(const std::string& topic, google::protobuf::Any sample);

  /// Ends every Publish and Subscribe stream with UNAVAILABLE and refuses new
  /// ones, so that grpc::Server::Shutdown does not wait for clients that keep
  /// their streams open. Call it before shutting the server down.
  void shutdown();

 private:
  class Publisher;
  class RemotePublisher;
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

  // The topics this host wants (not counting remote wants); tells the link
  // when the set changed. Caller holds mutex_.
  void localInterestChangedLocked(std::chrono::steady_clock::time_point now)
      ABSL_EXCLUSIVE_LOCKS_REQUIRED(mutex_);
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

  // Lock order: mutex_, then Topic::mutex, then a subscription's mutex.
  absl::Mutex mutex_;
  // Sorted, for ListTopics. A topic stays once something was published on
  // it; a topic that only had waiting subscribers goes away with them.
  std::map<std::string, std::shared_ptr<Topic>, std::less<>> topics_ ABSL_GUARDED_BY(mutex_);
  std::unordered_set<Publisher*> publishers_ ABSL_GUARDED_BY(mutex_);
  InterestReactors interest_watchers_ ABSL_GUARDED_BY(mutex_);
  // Topics with a transient interest or waiting GetLatest calls.
  std::set<std::shared_ptr<Topic>> timed_topics_ ABSL_GUARDED_BY(mutex_);
  // The housekeeper waits on mutex_ (Mutex::Await) for its next deadline,
  // a new timed topic (a count of them) or the shutdown.
  uint64_t housekeeping_wakes_ ABSL_GUARDED_BY(mutex_) = 0;
  bool shutting_down_ ABSL_GUARDED_BY(mutex_) = false;
  // The link to other hosts (null: this host only) and what it carries.
  std::atomic<BrokerLink*> link_{nullptr};
  std::set<std::string, std::less<>> remote_wanted_ ABSL_GUARDED_BY(mutex_);
  std::vector<std::string> local_wanted_ ABSL_GUARDED_BY(mutex_);
  absl::Mutex remote_publish_mutex_;  // one sample from the link at a time
  std::unique_ptr<RemotePublisher> remote_publisher_ ABSL_GUARDED_BY(remote_publish_mutex_);
  std::thread housekeeper_;  // started last
};

}  // namespace behaviorlib::channel
