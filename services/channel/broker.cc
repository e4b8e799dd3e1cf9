#include "channel/broker.h"

#include <google/protobuf/descriptor.h>
#include <google/protobuf/timestamp.pb.h>
#include <prometheus/counter.h>
#include <prometheus/family.h>
#include <prometheus/gauge.h>
#include <prometheus/registry.h>

#include <algorithm>
#include <chrono>
#include <cstddef>
#include <deque>
#include <optional>
#include <utility>
#include <vector>

#include "absl/container/inlined_vector.h"
#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "channel/topic.h"

namespace behaviorlib::channel {
namespace {

using Sample = std::shared_ptr<const v1::SubscribeResponse>;

grpc::Status toGrpc(const absl::Status& status) {
  return grpc::Status(static_cast<grpc::StatusCode>(status.code()), std::string(status.message()));
}

google::protobuf::Timestamp wallNow() {
  const int64_t ns = std::chrono::duration_cast<std::chrono::nanoseconds>(
                         std::chrono::system_clock::now().time_since_epoch())
                         .count();
  google::protobuf::Timestamp t;
  t.set_seconds(ns / 1'000'000'000);
  t.set_nanos(static_cast<int32_t>(ns % 1'000'000'000));
  return t;
}

grpc::Status shuttingDownStatus() {
  return grpc::Status(grpc::StatusCode::UNAVAILABLE, "the channel broker is shutting down");
}

}  // namespace

// ---------------------------------------------------------------------------
// Metrics

struct Broker::Metrics {
  explicit Metrics(prometheus::Registry& registry)
      : samples_in(prometheus::BuildCounter()
                       .Name("behaviorlib_channel_samples_in_total")
                       .Help("Samples accepted from publishers, per topic.")
                       .Register(registry)),
        samples_out(prometheus::BuildCounter()
                        .Name("behaviorlib_channel_samples_out_total")
                        .Help("Samples written to subscribers, per topic.")
                        .Register(registry)),
        dropped(prometheus::BuildCounter()
                    .Name("behaviorlib_channel_dropped_samples_total")
                    .Help("Samples lost by slow subscriptions (queue overflow or replaced in "
                          "latest-only mode), per topic.")
                    .Register(registry)),
        rejected(prometheus::BuildCounter()
                     .Name("behaviorlib_channel_rejected_samples_total")
                     .Help("Published samples refused, per reason.")
                     .Register(registry)),
        subscribers(prometheus::BuildGauge()
                        .Name("behaviorlib_channel_subscribers")
                        .Help("Current subscriptions, per topic.")
                        .Register(registry)) {
    for (absl::string_view reason :
         {reject_reason::kInvalidTopic, reject_reason::kMissingSample, reject_reason::kUnknownType,
          reject_reason::kMalformedSample, reject_reason::kTypeMismatch}) {
      rejected_by_reason.emplace(std::string(reason),
                                 &rejected.Add({{"reason", std::string(reason)}}));
    }
  }

  prometheus::Family<prometheus::Counter>& samples_in;
  prometheus::Family<prometheus::Counter>& samples_out;
  prometheus::Family<prometheus::Counter>& dropped;
  prometheus::Family<prometheus::Counter>& rejected;
  prometheus::Family<prometheus::Gauge>& subscribers;
  // Filled in the constructor, read-only afterwards.
  std::map<std::string, prometheus::Counter*, std::less<>> rejected_by_reason;
};

// ---------------------------------------------------------------------------
// Topic

struct Broker::Topic {
  Topic(std::string topic_name, Metrics& metrics)
      : name(std::move(topic_name)),
        samples_in(metrics.samples_in.Add({{"topic", name}})),
        samples_out(metrics.samples_out.Add({{"topic", name}})),
        dropped(metrics.dropped.Add({{"topic", name}})),
        subscriber_gauge(metrics.subscribers.Add({{"topic", name}})) {}

  void removeMetrics(Metrics& metrics) {
    metrics.samples_in.Remove(&samples_in);
    metrics.samples_out.Remove(&samples_out);
    metrics.dropped.Remove(&dropped);
    metrics.subscribers.Remove(&subscriber_gauge);
  }

  const std::string name;
  // Label instances resolved once: the per-sample path only increments.
  prometheus::Counter& samples_in;
  prometheus::Counter& samples_out;
  prometheus::Counter& dropped;
  prometheus::Gauge& subscriber_gauge;

  std::mutex mutex;
  // Guarded by mutex. `type` is fixed by the first sample.
  const google::protobuf::Descriptor* type = nullptr;
  Sample latest;
  uint64_t seq = 0;  // also the number of samples published
  std::vector<std::shared_ptr<SubscribeReactor>> subscribers;
};

// ---------------------------------------------------------------------------
// Subscribe: one reactor per stream with its own buffer. Writes go out one at
// a time; the thread that finds the reactor idle starts the next one (a
// publisher, or gRPC's callback thread in OnWriteDone). Every operation on
// the stream (initial metadata, a write, Finish) is started only while no
// other one is in flight, decided under mutex_.

class Broker::SubscribeReactor final : public grpc::ServerWriteReactor<v1::SubscribeResponse> {
 public:
  SubscribeReactor(grpc::CallbackServerContext* context, bool latest_only, std::size_t queue_size)
      : context_(context), latest_only_(latest_only), queue_size_(queue_size) {}

  void setOwner(Broker* broker, std::shared_ptr<SubscribeReactor> self) {
    broker_ = broker;
    self_ = std::move(self);
  }

  // Called with topic->mutex held, before the reactor is visible to
  // publishers; the initial metadata is the first operation on the stream.
  void attach(std::shared_ptr<Topic> topic) {
    std::lock_guard lock(mutex_);
    topic_ = std::move(topic);
    busy_ = true;
  }

  // Tells the client that it is registered (see kSubscribedMetadataKey).
  void sendSubscribedMetadata() {
    context_->AddInitialMetadata(kSubscribedMetadataKey, "1");
    StartSendInitialMetadata();
  }

  // Buffers a sample. Called with the topic's mutex held, so samples are
  // buffered in topic_seq order. Never blocks on the stream. Returns true
  // when the stream is idle: the caller must then call pump() once it has
  // released the topic's mutex.
  bool offer(const Sample& sample) {
    std::lock_guard lock(mutex_);
    if (finish_status_.has_value()) return false;
    // In QUEUE mode the sample being written counts against queue_size (it
    // is not delivered yet), but one new sample is always kept.
    const std::size_t capacity =
        latest_only_ ? 1 : std::max<std::size_t>(1, queue_size_ - (writing_sample_ ? 1 : 0));
    while (pending_.size() >= capacity) {
      pending_.pop_front();
      ++dropped_;
      topic_->dropped.Increment();
    }
    pending_.push_back(sample);
    return !busy_;
  }

  // Starts the next operation if none is in flight.
  void pump() {
    std::unique_lock lock(mutex_);
    if (busy_ || finished_) return;
    if (finish_status_.has_value()) {
      finished_ = true;
      const grpc::Status status = *finish_status_;
      lock.unlock();
      Finish(status);
      return;
    }
    if (pending_.empty()) return;
    Sample next = std::move(pending_.front());
    pending_.pop_front();
    busy_ = true;
    writing_sample_ = true;
    const uint64_t dropped = dropped_;
    lock.unlock();
    // busy_ gives this thread sole use of current_ until OnWriteDone; the
    // copy happens outside the lock so publishers never wait for it.
    current_.CopyFrom(*next);
    current_.set_dropped_count(dropped);
    StartWrite(&current_);
  }

  // Ends the stream with `status` once the write in flight (if any) is done.
  // The first requested status wins.
  void requestFinish(grpc::Status status) {
    {
      std::lock_guard lock(mutex_);
      if (!finish_status_.has_value()) finish_status_ = std::move(status);
      pending_.clear();
    }
    pump();
  }

  void OnSendInitialMetadataDone(bool ok) override { operationDone(ok); }

  void OnWriteDone(bool ok) override {
    if (ok) topic_->samples_out.Increment();
    operationDone(ok);
  }

  void OnCancel() override {
    requestFinish(grpc::Status(grpc::StatusCode::CANCELLED, "subscription cancelled"));
  }

  void OnDone() override {
    std::shared_ptr<Topic> topic;
    {
      std::lock_guard lock(mutex_);
      topic = topic_;
    }
    if (topic) broker_->removeSubscriber(topic, this);
    // `self` may be the last reference: nothing touches members after this.
    std::shared_ptr<SubscribeReactor> self = std::move(self_);
  }

 private:
  void operationDone(bool ok) {
    {
      std::lock_guard lock(mutex_);
      busy_ = false;
      writing_sample_ = false;
      if (!ok && !finish_status_.has_value()) {
        // The stream is broken (client gone); it must still be finished.
        finish_status_ = grpc::Status(grpc::StatusCode::CANCELLED, "subscriber stream broken");
        pending_.clear();
      }
    }
    pump();
  }

  grpc::CallbackServerContext* const context_;
  const bool latest_only_;
  const std::size_t queue_size_;
  Broker* broker_ = nullptr;
  // Keeps the reactor alive until OnDone, while publishers may hold
  // references taken under the topic's mutex.
  std::shared_ptr<SubscribeReactor> self_;

  std::mutex mutex_;
  std::shared_ptr<Topic> topic_;  // null when the request was refused
  std::deque<Sample> pending_;
  uint64_t dropped_ = 0;
  bool busy_ = false;            // an operation is in flight
  bool writing_sample_ = false;  // ... and it is a sample write
  std::optional<grpc::Status> finish_status_;
  bool finished_ = false;  // Finish was called
  // The message of the write in flight (owned by whoever set busy_).
  v1::SubscribeResponse current_;
};

// ---------------------------------------------------------------------------
// Publish: one read at a time; each sample is validated and fanned out on
// gRPC's callback thread, which never waits for subscribers.

class Broker::PublishReactor final : public grpc::ServerReadReactor<v1::PublishRequest> {
 public:
  PublishReactor(Broker* broker, v1::PublishResponse* response)
      : broker_(broker), response_(response) {}

  void start() {
    std::lock_guard lock(mutex_);
    if (!finished_) StartRead(&request_);
  }

  void requestFinish(const grpc::Status& status) {
    std::lock_guard lock(mutex_);
    finishLocked(status);
  }

  void OnReadDone(bool ok) override {
    if (!ok) {
      // The client half-closed (or the call ended): report what was taken.
      requestFinish(grpc::Status::OK);
      return;
    }
    const grpc::Status status = broker_->publish(*this, request_);
    std::lock_guard lock(mutex_);
    if (!status.ok()) {
      finishLocked(status);
      return;
    }
    ++accepted_;
    if (!finished_) StartRead(&request_);
  }

  void OnDone() override {
    broker_->removePublisher(this);
    delete this;
  }

  // The topic of the previous sample on this stream (a stream usually
  // publishes one topic), so that the common case skips the topic map and
  // name validation. Only used from OnReadDone, one read at a time.
  std::shared_ptr<Topic> cached_topic;

 private:
  void finishLocked(const grpc::Status& status) {
    if (finished_) return;
    finished_ = true;
    response_->set_accepted_count(accepted_);
    Finish(status);
  }

  Broker* const broker_;
  v1::PublishResponse* const response_;
  v1::PublishRequest request_;  // used by one read at a time
  std::mutex mutex_;
  uint64_t accepted_ = 0;
  bool finished_ = false;
};

// ---------------------------------------------------------------------------
// Broker

Broker::Broker(prometheus::Registry& registry) : metrics_(std::make_unique<Metrics>(registry)) {}

Broker::~Broker() = default;

void Broker::countRejected(absl::string_view reason) {
  auto it = metrics_->rejected_by_reason.find(reason);
  if (it != metrics_->rejected_by_reason.end()) it->second->Increment();
}

std::shared_ptr<Broker::Topic> Broker::topicLocked(const std::string& name) {
  auto it = topics_.find(name);
  if (it != topics_.end()) return it->second;
  auto topic = std::make_shared<Topic>(name, *metrics_);
  topics_.emplace(name, topic);
  return topic;
}

grpc::ServerReadReactor<v1::PublishRequest>* Broker::Publish(
    grpc::CallbackServerContext* /*context*/, v1::PublishResponse* response) {
  auto* reactor = new PublishReactor(this, response);
  bool refuse = false;
  {
    std::lock_guard lock(mutex_);
    refuse = shutting_down_;
    publishers_.insert(reactor);
  }
  if (refuse) {
    reactor->requestFinish(shuttingDownStatus());
  } else {
    reactor->start();
  }
  return reactor;
}

grpc::Status Broker::publish(PublishReactor& publisher, v1::PublishRequest& request) {
  std::shared_ptr<Topic> topic = publisher.cached_topic;
  if (!topic || topic->name != request.topic()) {
    topic.reset();
    if (absl::Status status = validateTopicName(request.topic()); !status.ok()) {
      countRejected(reject_reason::kInvalidTopic);
      return toGrpc(status);
    }
  }
  const google::protobuf::Descriptor* type = nullptr;
  absl::string_view reason;
  if (absl::Status status = checkSample(request.topic(), request.sample(), &type, &reason);
      !status.ok()) {
    countRejected(reason);
    return toGrpc(status);
  }

  auto sample = std::make_shared<v1::SubscribeResponse>();
  sample->set_topic(request.topic());
  sample->mutable_sample()->Swap(request.mutable_sample());
  *sample->mutable_receive_time() = wallNow();

  std::unique_lock<std::mutex> topic_lock;
  if (topic) {
    topic_lock = std::unique_lock(topic->mutex);
  } else {
    std::lock_guard lock(mutex_);
    if (shutting_down_) return shuttingDownStatus();
    topic = topicLocked(request.topic());
    // Locked before mutex_ is released, so that removeSubscriber cannot drop
    // a topic that so far only had waiting subscribers under our feet.
    topic_lock = std::unique_lock(topic->mutex);
  }
  if (topic->type != nullptr && topic->type != type) {
    const std::string carried = topic->type->full_name();
    topic_lock.unlock();
    countRejected(reject_reason::kTypeMismatch);
    return grpc::Status(
        grpc::StatusCode::INVALID_ARGUMENT,
        absl::StrCat("topic '", topic->name, "' carries ", carried, "; got ", type->full_name()));
  }
  topic->type = type;
  sample->set_topic_seq(++topic->seq);
  topic->latest = sample;
  absl::InlinedVector<std::shared_ptr<SubscribeReactor>, 8> idle;
  for (const auto& subscriber : topic->subscribers) {
    if (subscriber->offer(topic->latest)) idle.push_back(subscriber);
  }
  topic_lock.unlock();
  topic->samples_in.Increment();
  publisher.cached_topic = std::move(topic);
  for (const auto& subscriber : idle) subscriber->pump();
  return grpc::Status::OK;
}

void Broker::removePublisher(PublishReactor* publisher) {
  std::lock_guard lock(mutex_);
  publishers_.erase(publisher);
}

grpc::ServerWriteReactor<v1::SubscribeResponse>* Broker::Subscribe(
    grpc::CallbackServerContext* context, const v1::SubscribeRequest* request) {
  bool latest_only = true;
  std::size_t queue_size = 1;
  grpc::Status invalid = grpc::Status::OK;
  if (absl::Status status = validateTopicName(request->topic()); !status.ok()) {
    invalid = toGrpc(status);
  } else if (request->mode() == v1::DELIVERY_MODE_QUEUE) {
    latest_only = false;
    queue_size = request->queue_size() == 0 ? kDefaultQueueSize : request->queue_size();
    if (queue_size > kMaxQueueSize) {
      invalid = grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                             absl::StrCat("queue_size ", request->queue_size(), " for topic '",
                                          request->topic(), "' is out of range: use 1..",
                                          kMaxQueueSize, " (0 means ", kDefaultQueueSize, ")"));
    }
  } else if (request->mode() != v1::DELIVERY_MODE_LATEST &&
             request->mode() != v1::DELIVERY_MODE_UNSPECIFIED) {
    invalid = grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                           absl::StrCat("unknown delivery mode ", request->mode(), " for topic '",
                                        request->topic(), "'"));
  }

  auto reactor = std::make_shared<SubscribeReactor>(context, latest_only, queue_size);
  reactor->setOwner(this, reactor);
  if (!invalid.ok()) {
    reactor->requestFinish(invalid);
    return reactor.get();
  }

  bool registered = false;
  {
    std::lock_guard lock(mutex_);
    if (!shutting_down_) {
      std::shared_ptr<Topic> topic = topicLocked(request->topic());
      std::lock_guard topic_lock(topic->mutex);
      reactor->attach(topic);
      topic->subscribers.push_back(reactor);
      topic->subscriber_gauge.Set(static_cast<double>(topic->subscribers.size()));
      if (request->send_latest_first() && topic->latest) reactor->offer(topic->latest);
      registered = true;
    }
  }
  if (!registered) {
    reactor->requestFinish(shuttingDownStatus());
  } else {
    reactor->sendSubscribedMetadata();
  }
  return reactor.get();
}

void Broker::removeSubscriber(const std::shared_ptr<Topic>& topic,
                              const SubscribeReactor* subscriber) {
  std::lock_guard lock(mutex_);
  std::lock_guard topic_lock(topic->mutex);
  auto& subs = topic->subscribers;
  subs.erase(std::remove_if(subs.begin(), subs.end(),
                            [subscriber](const auto& s) { return s.get() == subscriber; }),
             subs.end());
  topic->subscriber_gauge.Set(static_cast<double>(subs.size()));
  if (topic->seq == 0 && subs.empty()) {
    // Only ever had waiting subscribers: forget it rather than keep a topic
    // (and its metric series) for every name someone once asked for.
    auto it = topics_.find(topic->name);
    if (it != topics_.end() && it->second == topic) {
      topics_.erase(it);
      topic->removeMetrics(*metrics_);
    }
  }
}

grpc::ServerUnaryReactor* Broker::GetLatest(grpc::CallbackServerContext* context,
                                            const v1::GetLatestRequest* request,
                                            v1::GetLatestResponse* response) {
  grpc::ServerUnaryReactor* reactor = context->DefaultReactor();
  if (absl::Status status = validateTopicName(request->topic()); !status.ok()) {
    reactor->Finish(toGrpc(status));
    return reactor;
  }
  Sample latest;
  {
    std::lock_guard lock(mutex_);
    auto it = topics_.find(request->topic());
    if (it != topics_.end()) {
      std::lock_guard topic_lock(it->second->mutex);
      latest = it->second->latest;
    }
  }
  if (!latest) {
    reactor->Finish(grpc::Status(
        grpc::StatusCode::NOT_FOUND,
        absl::StrCat("nothing has been published on topic '", request->topic(), "' yet")));
    return reactor;
  }
  *response->mutable_sample() = *latest;
  reactor->Finish(grpc::Status::OK);
  return reactor;
}

grpc::ServerUnaryReactor* Broker::ListTopics(grpc::CallbackServerContext* context,
                                             const v1::ListTopicsRequest* request,
                                             v1::ListTopicsResponse* response) {
  const std::string& prefix = request->prefix();
  {
    std::lock_guard lock(mutex_);
    for (auto it = topics_.lower_bound(prefix);
         it != topics_.end() && absl::StartsWith(it->first, prefix); ++it) {
      Topic& topic = *it->second;
      std::lock_guard topic_lock(topic.mutex);
      v1::TopicInfo* info = response->add_topics();
      info->set_name(topic.name);
      if (topic.type != nullptr) info->set_type(topic.type->full_name());
      info->set_published_count(topic.seq);
      info->set_subscriber_count(static_cast<uint32_t>(topic.subscribers.size()));
      if (topic.latest) *info->mutable_last_receive_time() = topic.latest->receive_time();
    }
  }
  grpc::ServerUnaryReactor* reactor = context->DefaultReactor();
  reactor->Finish(grpc::Status::OK);
  return reactor;
}

void Broker::shutdown() {
  std::vector<std::shared_ptr<SubscribeReactor>> subscribers;
  {
    std::lock_guard lock(mutex_);
    shutting_down_ = true;
    for (auto& [name, topic] : topics_) {
      std::lock_guard topic_lock(topic->mutex);
      subscribers.insert(subscribers.end(), topic->subscribers.begin(), topic->subscribers.end());
    }
    // Finish never runs a reaction inline (OnDone, which needs mutex_, is
    // dispatched to gRPC's threads), so this is safe under the lock, which
    // keeps the reactors alive meanwhile.
    for (PublishReactor* publisher : publishers_) publisher->requestFinish(shuttingDownStatus());
  }
  for (const auto& subscriber : subscribers) subscriber->requestFinish(shuttingDownStatus());
}

}  // namespace behaviorlib::channel
