#include "behaviorlib/channel/broker.h"

#include <google/protobuf/descriptor.h>
#include <google/protobuf/timestamp.pb.h>
#include <grpcpp/alarm.h>
#include <prometheus/counter.h>
#include <prometheus/family.h>
#include <prometheus/gauge.h>
#include <prometheus/registry.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstddef>
#include <deque>
#include <optional>
#include <utility>
#include <vector>

#include "absl/base/thread_annotations.h"
#include "absl/container/flat_hash_map.h"
#include "absl/container/inlined_vector.h"
#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/synchronization/mutex.h"
#include "absl/time/time.h"
#include "behaviorlib/channel/shm_ring.h"
#include "behaviorlib/channel/topic.h"
#include "behaviorlib/error_details.h"
#include "behaviorlib/server_kit/access_policy.h"
#include "behaviorlib/server_kit/pagination.h"
#include "behaviorlib/server_kit/reactor_order.h"

namespace behaviorlib::channel {
namespace {

using Sample = std::shared_ptr<const v1::SubscribeResponse>;

// How a server stream ends, kept under its reactor's mutex: the status
// asked for first, and whether Finish has been called.
struct StreamEnd {
  std::optional<grpc::Status> status;
  bool finished = false;

  bool asked() const { return status.has_value(); }
  // The first status asked for wins.
  void ask(grpc::Status s) {
    if (!status) status = std::move(s);
  }
  // A write that failed (the client is gone) ends the stream with
  // CANCELLED naming it: it must still be finished.
  void writeDone(bool ok, const char* stream) {
    if (!ok) ask(grpc::Status(grpc::StatusCode::CANCELLED, std::string(stream) + " broken"));
  }
  // With no operation in flight: the status to Finish with, once.
  std::optional<grpc::Status> due() {
    if (finished || !status) return std::nullopt;
    finished = true;
    return status;
  }
};

// With its details; a topic name or sample refused (INVALID_ARGUMENT) is
// INVALID_REQUEST.
grpc::Status toGrpc(const absl::Status& status) {
  if (status.code() == absl::StatusCode::kInvalidArgument) {
    return errors::toGrpc(errors::withDefaultReason(status, v1::INVALID_REQUEST));
  }
  return errors::toGrpc(status);
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

// How long a GetLatest keeps a gated topic wanted, and how long one waits
// for a gated topic's next sample.
constexpr std::chrono::seconds kTransientInterest(2);
constexpr std::chrono::seconds kMaxGetLatestWait(1);

// SubscribeRequest.max_rate_hz: at most this (a sample every 10 us).
constexpr double kMaxRateHz = 100'000;

// Ring sizing (decision 20): a slot holds twice the sample that sized it
// (at least 256 bytes), and a ring at most kMaxRingBytes, however many
// samples its subscribers' queues would keep.
constexpr std::size_t kMinSlotBytes = 256;
constexpr std::size_t kMaxRingBytes = 32u << 20;
constexpr uint32_t kMinRingSlots = 4;
// Names the next ring; one count for the process, so that two brokers in
// one process (tests build them in-process) never name the same ring.
std::atomic<uint64_t> rings_made{0};

// Whether a peer runs on this host, so that it probably shares our /dev/shm
// (for a client that does not name its shm_domain).
bool localPeer(const std::string& peer) {
  return absl::StartsWith(peer, "ipv4:127.") || absl::StartsWith(peer, "ipv6:[::1]") ||
         absl::StartsWith(peer, "unix:");
}

grpc::Status shuttingDownStatus() {
  return errors::grpcError(grpc::StatusCode::UNAVAILABLE, v1::SHUTTING_DOWN,
                           "the channel broker is shutting down");
}

}  // namespace

// ---------------------------------------------------------------------------
// Metrics

namespace {
prometheus::Family<prometheus::Counter>& counters(prometheus::Registry& registry, const char* name,
                                                  const char* help) {
  return prometheus::BuildCounter().Name(name).Help(help).Register(registry);
}
prometheus::Family<prometheus::Gauge>& gauges(prometheus::Registry& registry, const char* name,
                                              const char* help) {
  return prometheus::BuildGauge().Name(name).Help(help).Register(registry);
}
}  // namespace

struct Broker::Metrics {
  explicit Metrics(prometheus::Registry& registry)
      : samples_in(counters(registry, "behaviorlib_channel_samples_in_total",
                            "Samples accepted from publishers, per topic.")),
        samples_out(counters(registry, "behaviorlib_channel_samples_out_total",
                             "Samples written to subscribers, per topic.")),
        dropped(counters(registry, "behaviorlib_channel_dropped_samples_total",
                         "Samples lost by slow subscriptions (queue overflow or replaced in "
                         "latest-only mode), per topic.")),
        rejected(counters(registry, "behaviorlib_channel_rejected_samples_total",
                          "Published samples refused, per reason.")),
        subscribers(gauges(registry, "behaviorlib_channel_subscribers",
                           "Current subscriptions, per topic.")),
        shm_samples(counters(registry, "behaviorlib_channel_shm_samples_total",
                             "Samples written once to a topic's shared-memory ring, from which "
                             "every subscriber on this host reads them, per topic.")),
        rings(gauges(registry, "behaviorlib_channel_shm_ring_bytes",
                     "Shared memory held by the topics' rings.")
                  .Add({})) {
    for (absl::string_view reason :
         {reject_reason::kInvalidTopic, reject_reason::kMissingSample, reject_reason::kUnknownType,
          reject_reason::kMalformedSample, reject_reason::kTypeMismatch,
          reject_reason::kTooManyTopics, reject_reason::kNotPermitted}) {
      rejected_by_reason.emplace(std::string(reason),
                                 &rejected.Add({{"reason", std::string(reason)}}));
    }
  }

  prometheus::Family<prometheus::Counter>& samples_in;
  prometheus::Family<prometheus::Counter>& samples_out;
  prometheus::Family<prometheus::Counter>& dropped;
  prometheus::Family<prometheus::Counter>& rejected;
  prometheus::Family<prometheus::Gauge>& subscribers;
  prometheus::Family<prometheus::Counter>& shm_samples;
  prometheus::Gauge& rings;
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
        subscriber_gauge(metrics.subscribers.Add({{"topic", name}})),
        shm_samples(metrics.shm_samples.Add({{"topic", name}})) {}

  void removeMetrics(Metrics& metrics) {
    metrics.samples_in.Remove(&samples_in);
    metrics.samples_out.Remove(&samples_out);
    metrics.dropped.Remove(&dropped);
    metrics.subscribers.Remove(&subscriber_gauge);
    metrics.shm_samples.Remove(&shm_samples);
  }

  const std::string name;
  // Label instances resolved once: the per-sample path only increments.
  prometheus::Counter& samples_in;
  prometheus::Counter& samples_out;
  prometheus::Counter& dropped;
  prometheus::Gauge& subscriber_gauge;
  prometheus::Counter& shm_samples;

  absl::Mutex mutex;
  // Guarded by mutex. `type` is fixed by the first sample.
  const google::protobuf::Descriptor* type ABSL_GUARDED_BY(mutex) = nullptr;
  Sample latest ABSL_GUARDED_BY(mutex);
  uint64_t seq ABSL_GUARDED_BY(mutex) = 0;  // also the number of samples published
  std::vector<std::shared_ptr<SubscribeReactor>> subscribers ABSL_GUARDED_BY(mutex);
  // Until when a GetLatest keeps the topic wanted (WatchInterest).
  std::chrono::steady_clock::time_point wanted_until ABSL_GUARDED_BY(mutex) = {};
  // Its last publisher gates it by interest (kGatedPrefixMetadataKey).
  bool gated ABSL_GUARDED_BY(mutex) = false;
  // GetLatest calls waiting for the topic's next sample (a gated topic).
  struct WaitingGet {
    grpc::ServerUnaryReactor* reactor;
    v1::GetLatestResponse* response;
    std::chrono::steady_clock::time_point deadline;
  };
  std::vector<WaitingGet> waiting ABSL_GUARDED_BY(mutex);
  // The shared-memory ring of the subscribers on this host, while there is
  // one; written by publish() under `mutex`.
  std::unique_ptr<ShmRing> ring ABSL_GUARDED_BY(mutex);
  uint32_t shm_subscribers ABSL_GUARDED_BY(mutex) = 0;
  std::string ring_scratch ABSL_GUARDED_BY(mutex);  // a sample's bytes, reused

  // Another host wants it (Broker::setRemoteWanted).
  bool remote_wanted ABSL_GUARDED_BY(mutex) = false;

  // Caller holds mutex. Wanted here or by another host.
  bool wantedLocked(std::chrono::steady_clock::time_point now) const
      ABSL_EXCLUSIVE_LOCKS_REQUIRED(mutex) {
    return localWantedLocked(now) || remote_wanted;
  }
  // Wanted by this host's subscribers or GetLatest callers.
  bool localWantedLocked(std::chrono::steady_clock::time_point now) const
      ABSL_EXCLUSIVE_LOCKS_REQUIRED(mutex) {
    return !subscribers.empty() || wanted_until > now;
  }
  // The rate it is wanted at (WatchInterestResponse.max_rate_hz): the
  // highest of its subscribers' max_rate_hz, 0 (every sample) when one of
  // them, a GetLatest caller or another host wants every sample. Defined
  // after SubscribeReactor.
  double wantedRateLocked(std::chrono::steady_clock::time_point now) const
      ABSL_EXCLUSIVE_LOCKS_REQUIRED(mutex);
};

// ---------------------------------------------------------------------------
// WatchInterest: one reactor per stream; only the newest wanted set waits to
// be written, one write at a time (as a LATEST subscription).

class Broker::InterestReactor final
    : public server_kit::Ordered<grpc::ServerWriteReactor<v1::WatchInterestResponse>> {
 public:
  InterestReactor(Broker* broker, std::string prefix)
      : broker_(broker), prefix_(std::move(prefix)) {}

  void setSelf(std::shared_ptr<InterestReactor> self) { self_ = std::move(self); }
  const std::string& prefix() const { return prefix_; }

  // Called with the broker's mutex held: replaces the unsent set when
  // `wanted` differs from the last one offered. True when the caller must
  // pump() after releasing the mutex.
  // Each wanted topic with the rate it is wanted at (0: every sample).
  using Wanted = std::vector<std::pair<std::string, double>>;
  bool offer(Wanted wanted) {
    absl::MutexLock lock(&mutex_);
    if (end_.asked() || (offered_once_ && wanted == last_offered_)) return false;
    offered_once_ = true;
    last_offered_ = wanted;
    pending_ = std::move(wanted);
    return !busy_;
  }

  void pump() {
    absl::ReleasableMutexLock lock(&mutex_);
    if (busy_ || end_.finished) return;
    if (std::optional<grpc::Status> status = end_.due()) {
      lock.Release();
      Finish(*status);
      return;
    }
    if (!pending_) return;
    current_.Clear();
    for (auto& [name, rate] : *pending_) {
      current_.add_wanted_topics(std::move(name));
      current_.add_max_rate_hz(rate);
    }
    pending_.reset();
    busy_ = true;
    lock.Release();
    StartWrite(&current_);
  }

  void requestFinish(grpc::Status status) {
    {
      absl::MutexLock lock(&mutex_);
      end_.ask(std::move(status));
      pending_.reset();
    }
    pump();
  }

  void OnWriteDone(bool ok) override {
    ordered();
    {
      absl::MutexLock lock(&mutex_);
      busy_ = false;
      end_.writeDone(ok, "interest stream");
    }
    pump();
  }

  void OnCancel() override {
    ordered();
    requestFinish(grpc::Status(grpc::StatusCode::CANCELLED, "interest watch cancelled"));
  }

  void OnDone() override {
    ordered();
    broker_->removeInterestWatcher(this);
    std::shared_ptr<InterestReactor> self = std::move(self_);
  }

 private:
  Broker* const broker_;
  const std::string prefix_;
  std::shared_ptr<InterestReactor> self_;  // alive until OnDone
  absl::Mutex mutex_;
  bool offered_once_ ABSL_GUARDED_BY(mutex_) = false;
  Wanted last_offered_ ABSL_GUARDED_BY(mutex_);
  std::optional<Wanted> pending_ ABSL_GUARDED_BY(mutex_);
  bool busy_ ABSL_GUARDED_BY(mutex_) = false;
  StreamEnd end_ ABSL_GUARDED_BY(mutex_);
  v1::WatchInterestResponse current_;  // owned by whoever set busy_
};

// ---------------------------------------------------------------------------
// Subscribe: one reactor per stream with its own buffer. Writes go out one at
// a time; the thread that finds the reactor idle starts the next one (a
// publisher, or gRPC's callback thread in OnWriteDone). Every operation on
// the stream (initial metadata, a write, Finish) is started only while no
// other one is in flight, decided under mutex_.

class Broker::SubscribeReactor final
    : public server_kit::Ordered<grpc::ServerWriteReactor<v1::SubscribeResponse>> {
 public:
  // `max_rate_hz` > 0: the newest sample at most that often (wall time).
  SubscribeReactor(grpc::CallbackServerContext* context, bool latest_only, std::size_t queue_size,
                   double max_rate_hz)
      : context_(context),
        latest_only_(latest_only || max_rate_hz > 0),
        queue_size_(queue_size),
        max_rate_hz_(max_rate_hz),
        min_interval_(max_rate_hz > 0 ? std::chrono::duration_cast<std::chrono::nanoseconds>(
                                            std::chrono::duration<double>(1.0 / max_rate_hz))
                                      : std::chrono::nanoseconds(0)) {}

  // SubscribeRequest.max_rate_hz (0: every sample).
  double maxRateHz() const { return max_rate_hz_; }

  // How many samples the subscription keeps: what its ring must hold.
  uint32_t keeps() const {
    return latest_only_ ? kMinRingSlots
                        : std::max(kMinRingSlots, static_cast<uint32_t>(queue_size_));
  }
  // Served through the topic's shared-memory ring: no sample is written to
  // the stream. Set before the reactor is visible to publishers.
  void useRing() { ring_ = true; }
  bool usesRing() const { return ring_; }

  void setOwner(Broker* broker, std::shared_ptr<SubscribeReactor> self) {
    broker_ = broker;
    weak_self_ = self;
    self_ = std::move(self);
  }

  // Called with topic->mutex held, before the reactor is visible to
  // publishers; the initial metadata is the first operation on the stream.
  void attach(std::shared_ptr<Topic> topic) {
    absl::MutexLock lock(&mutex_);
    topic_ = std::move(topic);
    busy_ = true;
  }

  // Tells the client that it is registered (see kSubscribedMetadataKey).
  // With a ring, also its name and the first sample number to read there.
  void sendSubscribedMetadata(uint64_t topic_seq, const std::string& ring, uint64_t ring_first) {
    context_->AddInitialMetadata(kSubscribedMetadataKey, std::to_string(topic_seq));
    if (ring_) {
      context_->AddInitialMetadata(kShmRingMetadataKey, ring);
      context_->AddInitialMetadata(kShmFirstMetadataKey, std::to_string(ring_first));
    }
    StartSendInitialMetadata();
  }

  // Buffers a sample. Called with the topic's mutex held, so samples are
  // buffered in topic_seq order. Never blocks on the stream. Returns true
  // when the stream is idle: the caller must then call pump() once it has
  // released the topic's mutex.
  bool offer(const Sample& sample) {
    if (ring_) return false;
    absl::MutexLock lock(&mutex_);
    if (end_.asked()) return false;
    // In QUEUE mode the sample being written counts against queue_size (it
    // is not delivered yet), but one new sample is always kept.
    const std::size_t capacity =
        latest_only_ ? 1 : std::max<std::size_t>(1, queue_size_ - (writing_sample_ ? 1 : 0));
    while (pending_.size() >= capacity) {
      pending_.pop_front();
      // A rate-limited subscription skips samples by request, not by loss.
      if (max_rate_hz_ > 0) continue;
      ++dropped_;
      topic_->dropped.Increment();
    }
    pending_.push_back(sample);
    return !busy_;
  }

  // Starts the next operation if none is in flight.
  void pump() {
    absl::ReleasableMutexLock lock(&mutex_);
    if (busy_ || end_.finished) return;
    if (std::optional<grpc::Status> status = end_.due()) {
      lock.Release();
      Finish(*status);
      return;
    }
    if (pending_.empty()) return;
    if (max_rate_hz_ > 0) {
      // Not before the interval since the last write started: the newest
      // sample waits for the alarm (replaced meanwhile by any newer one).
      const auto now = std::chrono::steady_clock::now();
      if (now < next_write_) {
        armLocked(next_write_ - now);
        return;
      }
      next_write_ = now + min_interval_;
    }
    Sample next = std::move(pending_.front());
    pending_.pop_front();
    busy_ = true;
    writing_sample_ = true;
    const uint64_t dropped = dropped_;
    lock.Release();
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
      absl::MutexLock lock(&mutex_);
      end_.ask(std::move(status));
      pending_.clear();
    }
    pump();
  }

  void OnSendInitialMetadataDone(bool ok) override {
    ordered();
    operationDone(ok);
  }

  void OnWriteDone(bool ok) override {
    ordered();
    if (ok) topic_->samples_out.Increment();
    operationDone(ok);
  }

  void OnCancel() override {
    ordered();
    requestFinish(grpc::Status(grpc::StatusCode::CANCELLED, "subscription cancelled"));
  }

  void OnDone() override {
    ordered();
    std::shared_ptr<Topic> topic;
    {
      absl::MutexLock lock(&mutex_);
      topic = topic_;
    }
    if (topic) broker_->removeSubscriber(topic, this);
    // `self` may be the last reference: nothing touches members after this.
    std::shared_ptr<SubscribeReactor> self = std::move(self_);
  }

 private:
  // Pumps again after `delay`, unless an alarm is set already. The alarm
  // holds no reference: a reactor destroyed first cancels it.
  void armLocked(std::chrono::steady_clock::duration delay) ABSL_EXCLUSIVE_LOCKS_REQUIRED(mutex_) {
    if (alarm_armed_) return;
    alarm_armed_ = true;
    alarm_ = std::make_unique<grpc::Alarm>();
    alarm_->Set(std::chrono::system_clock::now() +
                    std::chrono::duration_cast<std::chrono::system_clock::duration>(delay),
                [weak = weak_self_](bool fired) {
                  if (!fired) return;
                  std::shared_ptr<SubscribeReactor> self = weak.lock();
                  if (!self) return;
                  {
                    absl::MutexLock lock(&self->mutex_);
                    self->alarm_armed_ = false;
                  }
                  self->pump();
                });
  }

  void operationDone(bool ok) {
    {
      absl::MutexLock lock(&mutex_);
      busy_ = false;
      writing_sample_ = false;
      if (!ok) {
        end_.writeDone(ok, "subscriber stream");
        pending_.clear();
      }
    }
    pump();
  }

  grpc::CallbackServerContext* const context_;
  const bool latest_only_;
  const std::size_t queue_size_;
  const double max_rate_hz_;
  const std::chrono::nanoseconds min_interval_;
  bool ring_ = false;
  Broker* broker_ = nullptr;
  std::weak_ptr<SubscribeReactor> weak_self_;  // for the alarm
  // Keeps the reactor alive until OnDone, while publishers may hold
  // references taken under the topic's mutex.
  std::shared_ptr<SubscribeReactor> self_;

  absl::Mutex mutex_;
  // Null when the request was refused. Set by attach() before any operation
  // on the stream starts; OnWriteDone reads it without mutex_.
  std::shared_ptr<Topic> topic_;
  std::deque<Sample> pending_ ABSL_GUARDED_BY(mutex_);
  uint64_t dropped_ ABSL_GUARDED_BY(mutex_) = 0;
  bool busy_ ABSL_GUARDED_BY(mutex_) = false;            // an operation is in flight
  bool writing_sample_ ABSL_GUARDED_BY(mutex_) = false;  // ... and it is a sample write
  StreamEnd end_ ABSL_GUARDED_BY(mutex_);
  // A rate-limited subscription's next write, and the alarm that pumps then.
  std::chrono::steady_clock::time_point next_write_ ABSL_GUARDED_BY(mutex_) = {};
  bool alarm_armed_ ABSL_GUARDED_BY(mutex_) = false;
  std::unique_ptr<grpc::Alarm> alarm_ ABSL_GUARDED_BY(mutex_);
  // The message of the write in flight (owned by whoever set busy_).
  v1::SubscribeResponse current_;
};

double Broker::Topic::wantedRateLocked(std::chrono::steady_clock::time_point now) const {
  if (remote_wanted || wanted_until > now) return 0;
  double rate = 0;
  for (const auto& subscriber : subscribers) {
    if (subscriber->maxRateHz() <= 0) return 0;
    rate = std::max(rate, subscriber->maxRateHz());
  }
  return rate;
}

// ---------------------------------------------------------------------------
// Publish and PublishAcked: one read at a time; each sample is validated and
// fanned out on gRPC's callback thread, which never waits for subscribers.

// What both kinds of publish stream keep: the gating prefix, the samples
// taken and the last topic_seq of each topic.
class Broker::Publisher {
 public:
  Publisher(Broker* broker, grpc::CallbackServerContext* context)
      : broker_(broker), scope_(server_kit::robotScopeOf(*context)) {
    const auto& metadata = context->client_metadata();
    auto it = metadata.find(kGatedPrefixMetadataKey);
    if (it != metadata.end()) gated_prefix_ = std::string(it->second.data(), it->second.size());
  }
  virtual ~Publisher() = default;

  // Who publishes: a caller bound to a robot publishes only its topics.
  const server_kit::RobotScope& scope() const { return scope_; }

  // Whether its samples come from another host (the link): they are never
  // handed back to the link.
  virtual bool remote() const { return false; }

  // Ends the stream with `status` (the first requested status wins).
  virtual void requestFinish(const grpc::Status& status) = 0;

  // Whether this stream's publisher gates `topic` by interest (it said so
  // in its metadata, kGatedPrefixMetadataKey).
  bool gates(absl::string_view topic) const {
    return gated_prefix_.has_value() && absl::StartsWith(topic, *gated_prefix_);
  }

  // The topic of the previous sample on this stream (a stream usually
  // publishes one topic), so that the common case skips the topic map and
  // name validation, and that sample's topic_seq. Only used from
  // OnReadDone, one read at a time.
  std::shared_ptr<Topic> cached_topic;
  uint64_t published_seq = 0;

 protected:
  // Publishes the request's sample and those of its batch, in order,
  // stopping at the first refused one.
  grpc::Status takeAll(v1::PublishRequest& request) {
    grpc::Status status = take(request);
    for (v1::PublishRequest& next : *request.mutable_more()) {
      if (!status.ok()) break;
      if (!next.more().empty()) {
        status = errors::grpcError(grpc::StatusCode::INVALID_ARGUMENT, v1::INVALID_REQUEST,
                                   "a sample in a batch ('more') has a batch of its own");
        break;
      }
      status = take(next);
    }
    return status;
  }

  // What was taken so far. Caller holds mutex_.
  void reportLocked(v1::PublishResponse* response) const ABSL_EXCLUSIVE_LOCKS_REQUIRED(mutex_) {
    response->set_accepted_count(accepted_);
    for (const auto& [key, topic_seq] : published_seqs_) {
      (*response->mutable_topic_seqs())[topic_seq.first->name] = topic_seq.second;
    }
  }

  // A publisher without a stream (RemotePublisher).
  explicit Publisher(Broker* broker) : broker_(broker) {}

  Broker* const broker_;
  absl::Mutex mutex_;

 private:
  grpc::Status take(v1::PublishRequest& request) {
    const grpc::Status status = broker_->publish(*this, request);
    if (!status.ok()) return status;
    absl::MutexLock lock(&mutex_);
    ++accepted_;
    published_seqs_[cached_topic.get()] = {cached_topic, published_seq};
    return status;
  }

  std::optional<std::string> gated_prefix_;
  const server_kit::RobotScope scope_;  // resolved once, at the stream's start
  uint64_t accepted_ ABSL_GUARDED_BY(mutex_) = 0;
  // The last seq published on each topic (PublishResponse.topic_seqs).
  absl::flat_hash_map<const Topic*, std::pair<std::shared_ptr<Topic>, uint64_t>> published_seqs_
      ABSL_GUARDED_BY(mutex_);
};

// The samples of other hosts, as the link hands them over. One at a time
// (Broker::remote_publish_mutex_), so the topic cache needs no lock.
class Broker::RemotePublisher final : public Broker::Publisher {
 public:
  explicit RemotePublisher(Broker* broker) : Publisher(broker) {}
  bool remote() const override { return true; }
  void requestFinish(const grpc::Status& /*status*/) override {}
};

class Broker::PublishReactor final
    : public server_kit::Ordered<grpc::ServerReadReactor<v1::PublishRequest>>,
      public Broker::Publisher {
 public:
  PublishReactor(Broker* broker, grpc::CallbackServerContext* context,
                 v1::PublishResponse* response)
      : Publisher(broker, context), response_(response) {}

  void start() {
    absl::MutexLock lock(&mutex_);
    if (!finished_) StartRead(&request_);
  }

  void requestFinish(const grpc::Status& status) override {
    absl::MutexLock lock(&mutex_);
    finishLocked(status);
  }

  void OnReadDone(bool ok) override {
    ordered();
    if (!ok) {
      // The client half-closed (or the call ended): report what was taken.
      requestFinish(grpc::Status::OK);
      return;
    }
    const grpc::Status status = takeAll(request_);
    absl::MutexLock lock(&mutex_);
    if (!status.ok()) {
      finishLocked(status);
      return;
    }
    if (!finished_) StartRead(&request_);
  }

  void OnDone() override {
    ordered();
    broker_->removePublisher(this);
    delete this;
  }

 private:
  void finishLocked(const grpc::Status& status) ABSL_EXCLUSIVE_LOCKS_REQUIRED(mutex_) {
    if (finished_) return;
    finished_ = true;
    reportLocked(response_);
    Finish(status);
  }

  v1::PublishResponse* const response_;
  v1::PublishRequest request_;  // used by one read at a time
  bool finished_ ABSL_GUARDED_BY(mutex_) = false;
};

// PublishAcked: as Publish, and every request marked `sync` is answered, in
// order, once the samples before it are taken; the deterministic mode's
// barrier then costs one round trip instead of a stream closed and opened.
class Broker::AckedPublishReactor final
    : public server_kit::Ordered<grpc::ServerBidiReactor<v1::PublishRequest, v1::PublishResponse>>,
      public Broker::Publisher {
 public:
  AckedPublishReactor(Broker* broker, grpc::CallbackServerContext* context)
      : Publisher(broker, context) {}

  void start() {
    absl::MutexLock lock(&mutex_);
    if (!end_.asked()) StartRead(&request_);
  }

  void requestFinish(const grpc::Status& status) override {
    absl::MutexLock lock(&mutex_);
    end_.ask(status);
    pumpLocked();
  }

  void OnReadDone(bool ok) override {
    ordered();
    if (!ok) {
      // The client half-closed (or the call ended): answer what was asked,
      // then end.
      absl::MutexLock lock(&mutex_);
      end_.ask(grpc::Status::OK);
      pumpLocked();
      return;
    }
    grpc::Status status = grpc::Status::OK;
    if (request_.has_sample() || !request_.topic().empty() || !request_.more().empty()) {
      status = takeAll(request_);
    }
    absl::MutexLock lock(&mutex_);
    if (!status.ok()) {
      end_.ask(status);
      acks_.clear();  // the client learns of the refusal from the stream's end
      pumpLocked();
      return;
    }
    if (request_.sync()) {
      acks_.emplace_back();
      reportLocked(&acks_.back());
    }
    if (!end_.asked()) StartRead(&request_);
    pumpLocked();
  }

  void OnWriteDone(bool ok) override {
    ordered();
    absl::MutexLock lock(&mutex_);
    writing_ = false;
    end_.writeDone(ok, "publisher stream");
    pumpLocked();
  }

  void OnDone() override {
    ordered();
    broker_->removePublisher(this);
    delete this;
  }

 private:
  // Writes the next answer, or finishes once nothing is in flight.
  void pumpLocked() ABSL_EXCLUSIVE_LOCKS_REQUIRED(mutex_) {
    if (writing_ || end_.finished) return;
    if (!acks_.empty() && (!end_.asked() || end_.status->ok())) {
      current_ = std::move(acks_.front());
      acks_.pop_front();
      writing_ = true;
      StartWrite(&current_);
      return;
    }
    // A read may still be pending: it then completes, not ok.
    if (std::optional<grpc::Status> status = end_.due()) Finish(*status);
  }

  v1::PublishRequest request_;  // used by one read at a time
  std::deque<v1::PublishResponse> acks_ ABSL_GUARDED_BY(mutex_);
  v1::PublishResponse current_ ABSL_GUARDED_BY(mutex_);  // the answer being written
  bool writing_ ABSL_GUARDED_BY(mutex_) = false;
  StreamEnd end_ ABSL_GUARDED_BY(mutex_);
};

// ---------------------------------------------------------------------------
// Broker

Broker::Broker(prometheus::Registry& registry, BrokerOptions options)
    : options_(options), metrics_(std::make_unique<Metrics>(registry)) {
  // Rings a killed broker left behind (they are named after its pid).
  if (options_.shared_memory) ShmRing::removeStale();
  housekeeper_ = std::thread([this] { housekeep(); });
}

Broker::~Broker() {
  {
    absl::MutexLock lock(&mutex_);
    shutting_down_ = true;
    for (auto& [name, topic] : topics_) {
      absl::MutexLock topic_lock(&topic->mutex);
      dropRingLocked(*topic);
    }
  }  // the housekeeper's Await sees shutting_down_ at this unlock
  housekeeper_.join();
}

void Broker::countRejected(absl::string_view reason) {
  auto it = metrics_->rejected_by_reason.find(reason);
  if (it != metrics_->rejected_by_reason.end()) it->second->Increment();
}

bool Broker::ensureRingLocked(Topic& topic, uint32_t slots, std::size_t bytes)
    ABSL_EXCLUSIVE_LOCKS_REQUIRED(topic.mutex) {
  const std::size_t want_bytes = std::max(kMinSlotBytes, (2 * bytes + 63) & ~std::size_t{63});
  if (topic.ring && topic.ring->slotBytes() >= bytes &&
      (topic.ring->slotCount() >= slots ||
       topic.ring->slotCount() * topic.ring->slotBytes() >= kMaxRingBytes / 2)) {
    return true;
  }
  std::size_t slot_bytes = want_bytes;
  uint32_t slot_count = slots;
  if (topic.ring) {
    slot_bytes = std::max<std::size_t>(slot_bytes, topic.ring->slotBytes());
    slot_count = std::max(slot_count, topic.ring->slotCount());
  }
  const auto fitting = static_cast<uint32_t>(
      std::max<std::size_t>(kMinRingSlots, kMaxRingBytes / std::max<std::size_t>(slot_bytes, 1)));
  slot_count = std::min(slot_count, fitting);
  auto made = ShmRing::create(ShmRing::nameFor(getpid(), ++rings_made), slot_count, slot_bytes);
  if (!made.ok()) {
    // Subscribers that asked for a ring get the stream instead; readers of
    // the old ring see it closed and subscribe again.
    dropRingLocked(topic);
    return false;
  }
  if (topic.ring) {
    metrics_->rings.Decrement(
        static_cast<double>(topic.ring->slotCount() * topic.ring->slotBytes()));
    topic.ring->supersede((*made)->name());
    topic.ring->unlink();
  }
  topic.ring = std::move(*made);
  metrics_->rings.Increment(static_cast<double>(slot_count * slot_bytes));
  return true;
}

void Broker::writeRingLocked(Topic& topic, const v1::SubscribeResponse& sample)
    ABSL_EXCLUSIVE_LOCKS_REQUIRED(topic.mutex) {
  topic.ring_scratch.clear();
  sample.AppendToString(&topic.ring_scratch);
  if (!topic.ring->fits(topic.ring_scratch.size()) &&
      !ensureRingLocked(topic, topic.ring->slotCount(), topic.ring_scratch.size())) {
    return;
  }
  topic.ring->write(sample.topic_seq(), topic.ring_scratch);
  topic.shm_samples.Increment();
}

void Broker::dropRingLocked(Topic& topic) ABSL_EXCLUSIVE_LOCKS_REQUIRED(topic.mutex) {
  if (!topic.ring) return;
  metrics_->rings.Decrement(static_cast<double>(topic.ring->slotCount() * topic.ring->slotBytes()));
  topic.ring->close();
  topic.ring->unlink();
  topic.ring.reset();
}

grpc::Status Broker::tooManyTopics(const std::string& name) const {
  return errors::grpcError(grpc::StatusCode::RESOURCE_EXHAUSTED, v1::LIMIT_EXCEEDED,
                           absl::StrCat("the broker keeps ", options_.max_topics,
                                        " topics, the most allowed: no new topic '", name, "'"),
                           {{"limit", std::to_string(options_.max_topics)}});
}

std::shared_ptr<Broker::Topic> Broker::topicLocked(const std::string& name) {
  auto it = topics_.find(name);
  if (it != topics_.end()) return it->second;
  if (topics_.size() >= options_.max_topics) return nullptr;
  auto topic = std::make_shared<Topic>(name, *metrics_);
  if (remote_wanted_.count(name) != 0) {
    absl::MutexLock topic_lock(&topic->mutex);
    topic->remote_wanted = true;
  }
  topics_.emplace(name, topic);
  return topic;
}

namespace {

// Starts a publish stream's reactor, or ends it at once when the broker is
// shutting down.
template <class Reactor>
Reactor* startPublisher(Reactor* reactor, bool registered) {
  if (registered) {
    reactor->start();
  } else {
    reactor->requestFinish(shuttingDownStatus());
  }
  return reactor;
}

}  // namespace

grpc::ServerReadReactor<v1::PublishRequest>* Broker::Publish(grpc::CallbackServerContext* context,
                                                             v1::PublishResponse* response) {
  auto* reactor = new PublishReactor(this, context, response);
  return startPublisher(reactor, addPublisher(reactor));
}

grpc::ServerBidiReactor<v1::PublishRequest, v1::PublishResponse>* Broker::PublishAcked(
    grpc::CallbackServerContext* context) {
  auto* reactor = new AckedPublishReactor(this, context);
  return startPublisher(reactor, addPublisher(reactor));
}

bool Broker::addPublisher(Publisher* publisher) {
  absl::MutexLock lock(&mutex_);
  publishers_.insert(publisher);
  return !shutting_down_;
}

grpc::Status Broker::publish(Publisher& publisher, v1::PublishRequest& request) {
  std::shared_ptr<Topic> topic = publisher.cached_topic;
  if (!topic || topic->name != request.topic()) {
    topic.reset();
    if (absl::Status status = validateTopicName(request.topic()); !status.ok()) {
      countRejected(reject_reason::kInvalidTopic);
      return toGrpc(status);
    }
    if (absl::Status status = publisher.scope().permitsTopic(
            request.topic(),
            std::string_view(kSharedRobotsPrefix.data(), kSharedRobotsPrefix.size()));
        !status.ok()) {
      countRejected(reject_reason::kNotPermitted);
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

  if (topic) {
    topic->mutex.Lock();
  } else {
    absl::MutexLock lock(&mutex_);
    if (shutting_down_) return shuttingDownStatus();
    topic = topicLocked(request.topic());
    if (!topic) {
      countRejected(reject_reason::kTooManyTopics);
      return tooManyTopics(request.topic());
    }
    // Locked before mutex_ is released, so that removeSubscriber cannot drop
    // a topic that so far only had waiting subscribers under our feet.
    topic->mutex.Lock();
  }
  if (topic->type != nullptr && topic->type != type) {
    const std::string carried = topic->type->full_name();
    topic->mutex.Unlock();
    countRejected(reject_reason::kTypeMismatch);
    return errors::grpcError(
        grpc::StatusCode::INVALID_ARGUMENT, v1::INVALID_REQUEST,
        absl::StrCat("topic '", topic->name, "' carries ", carried, "; got ", type->full_name()));
  }
  topic->type = type;
  topic->gated = publisher.gates(topic->name);
  sample->set_topic_seq(++topic->seq);
  // A gated topic nobody wants keeps no sample (it would grow stale); this
  // one (its first, say) still made the topic and its type known.
  const bool keep = !topic->gated || topic->wantedLocked(std::chrono::steady_clock::now());
  topic->latest = keep ? sample : nullptr;
  BrokerLink* const link = topic->remote_wanted && !publisher.remote() ? link_.load() : nullptr;
  if (topic->ring) writeRingLocked(*topic, *sample);
  absl::InlinedVector<std::shared_ptr<SubscribeReactor>, 8> idle;
  for (const auto& subscriber : topic->subscribers) {
    if (subscriber->offer(topic->latest)) idle.push_back(subscriber);
  }
  std::vector<Topic::WaitingGet> answered;
  answered.swap(topic->waiting);
  // Under the topic's mutex, so that attachLink(nullptr) can wait for it.
  if (link != nullptr) link->localSample(topic->name, *sample);
  topic->mutex.Unlock();
  topic->samples_in.Increment();
  publisher.published_seq = sample->topic_seq();
  publisher.cached_topic = std::move(topic);
  for (const auto& subscriber : idle) subscriber->pump();
  for (auto& get : answered) {
    *get.response->mutable_sample() = *sample;
    get.reactor->Finish(grpc::Status::OK);
  }
  return grpc::Status::OK;
}

void Broker::removePublisher(Publisher* publisher) {
  absl::MutexLock lock(&mutex_);
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
      invalid = errors::grpcError(grpc::StatusCode::INVALID_ARGUMENT, v1::INVALID_REQUEST,
                                  absl::StrCat("queue_size ", request->queue_size(), " for topic '",
                                               request->topic(), "' is out of range: use 1..",
                                               kMaxQueueSize, " (0 means ", kDefaultQueueSize, ")"),
                                  {{"limit", std::to_string(kMaxQueueSize)}});
    }
  } else if (request->mode() != v1::DELIVERY_MODE_LATEST &&
             request->mode() != v1::DELIVERY_MODE_UNSPECIFIED) {
    invalid = errors::grpcError(grpc::StatusCode::INVALID_ARGUMENT, v1::INVALID_REQUEST,
                                absl::StrCat("unknown delivery mode ", request->mode(),
                                             " for topic '", request->topic(), "'"));
  }
  const double max_rate_hz = request->max_rate_hz();
  if (invalid.ok() && !(max_rate_hz >= 0 && max_rate_hz <= kMaxRateHz)) {
    invalid = errors::grpcError(
        grpc::StatusCode::INVALID_ARGUMENT, v1::INVALID_REQUEST,
        absl::StrCat("max_rate_hz ", max_rate_hz, " for topic '", request->topic(),
                     "' is out of range: use 0 (every sample) up to ", kMaxRateHz),
        {{"field", "max_rate_hz"}, {"limit", absl::StrCat(kMaxRateHz)}});
  }

  auto reactor = std::make_shared<SubscribeReactor>(context, latest_only, queue_size,
                                                    invalid.ok() ? max_rate_hz : 0);
  reactor->setOwner(this, reactor);
  const bool wants_ring =
      request->shared_memory() && options_.shared_memory &&
      (request->shm_domain().empty() ? localPeer(context->peer())
                                     : request->shm_domain() == ShmRing::domain());
  if (!invalid.ok()) {
    reactor->requestFinish(invalid);
    return reactor.get();
  }

  bool registered = false;
  uint64_t registered_seq = 0;
  std::string ring_name;
  uint64_t ring_first = 0;
  InterestReactors watchers;
  bool too_many = false;
  {
    absl::MutexLock lock(&mutex_);
    std::shared_ptr<Topic> topic = shutting_down_ ? nullptr : topicLocked(request->topic());
    too_many = !shutting_down_ && !topic;
    if (topic) {
      bool changed = false;
      {
        absl::MutexLock topic_lock(&topic->mutex);
        const auto now = std::chrono::steady_clock::now();
        const bool was_wanted = !topic->subscribers.empty();
        const double was_rate = topic->wantedRateLocked(now);
        reactor->attach(topic);
        const std::size_t latest_bytes = topic->latest ? topic->latest->ByteSizeLong() : 0;
        if (wants_ring && ensureRingLocked(*topic, reactor->keeps(), latest_bytes)) {
          reactor->useRing();
          ++topic->shm_subscribers;
          ring_name = topic->ring->name();
          ring_first = topic->seq + 1;
          if (topic->latest && topic->ring->written() < topic->latest->topic_seq()) {
            writeRingLocked(*topic, *topic->latest);
          }
          if (request->send_latest_first() && topic->latest && topic->ring) {
            ring_first = topic->latest->topic_seq();
          }
        }
        topic->subscribers.push_back(reactor);
        topic->subscriber_gauge.Set(static_cast<double>(topic->subscribers.size()));
        changed = !was_wanted || topic->wantedRateLocked(now) != was_rate;
        registered_seq = topic->seq;
        if (request->send_latest_first() && topic->latest) reactor->offer(topic->latest);
      }
      if (changed) interestChangedLocked(&watchers);
      registered = true;
    }
  }
  for (const auto& watcher : watchers) watcher->pump();
  if (too_many) {
    reactor->requestFinish(tooManyTopics(request->topic()));
  } else if (!registered) {
    reactor->requestFinish(shuttingDownStatus());
  } else {
    reactor->sendSubscribedMetadata(registered_seq, ring_name, ring_first);
  }
  return reactor.get();
}

void Broker::removeSubscriber(const std::shared_ptr<Topic>& topic,
                              const SubscribeReactor* subscriber) {
  InterestReactors watchers;
  {
    absl::MutexLock lock(&mutex_);
    bool last = false;
    bool changed = false;
    {
      absl::MutexLock topic_lock(&topic->mutex);
      const auto now = std::chrono::steady_clock::now();
      const double was_rate = topic->wantedRateLocked(now);
      auto& subs = topic->subscribers;
      subs.erase(std::remove_if(subs.begin(), subs.end(),
                                [subscriber](const auto& s) { return s.get() == subscriber; }),
                 subs.end());
      topic->subscriber_gauge.Set(static_cast<double>(subs.size()));
      if (subscriber->usesRing() && topic->shm_subscribers > 0 && --topic->shm_subscribers == 0) {
        dropRingLocked(*topic);
      }
      last = subs.empty();
      changed = last || topic->wantedRateLocked(now) != was_rate;
      if (last) forgetIfUnwantedLocked(*topic, now);
      if (topic->seq == 0 && last && topic->waiting.empty()) {
        // Only ever had waiting subscribers: forget it rather than keep a
        // topic (and its metric series) for every name someone once asked
        // for.
        auto it = topics_.find(topic->name);
        if (it != topics_.end() && it->second == topic) {
          topics_.erase(it);
          topic->removeMetrics(*metrics_);
        }
      }
    }
    if (changed) interestChangedLocked(&watchers);
  }
  for (const auto& watcher : watchers) watcher->pump();
}

void Broker::forgetIfUnwantedLocked(Topic& topic, std::chrono::steady_clock::time_point now)
    ABSL_EXCLUSIVE_LOCKS_REQUIRED(topic.mutex) {
  if (topic.latest && topic.gated && !topic.wantedLocked(now)) topic.latest.reset();
}

void Broker::interestChangedLocked(InterestReactors* idle) {
  const auto now = std::chrono::steady_clock::now();
  localInterestChangedLocked(now);
  for (const auto& watcher : interest_watchers_) {
    std::map<std::string, double> wanted;  // the rate of each (0: every sample)
    const std::string& prefix = watcher->prefix();
    for (auto it = topics_.lower_bound(prefix);
         it != topics_.end() && absl::StartsWith(it->first, prefix); ++it) {
      absl::MutexLock topic_lock(&it->second->mutex);
      if (it->second->wantedLocked(now)) wanted[it->first] = it->second->wantedRateLocked(now);
    }
    // Another host may want a topic nothing has published here yet (its
    // link takes every sample).
    for (auto it = remote_wanted_.lower_bound(prefix);
         it != remote_wanted_.end() && absl::StartsWith(*it, prefix); ++it) {
      wanted[*it] = 0;
    }
    if (watcher->offer({wanted.begin(), wanted.end()})) idle->push_back(watcher);
  }
}

void Broker::localInterestChangedLocked(std::chrono::steady_clock::time_point now) {
  BrokerLink* const link = link_.load();
  if (link == nullptr) return;
  std::vector<std::string> wanted;
  for (const auto& [name, topic] : topics_) {
    absl::MutexLock topic_lock(&topic->mutex);
    if (topic->localWantedLocked(now)) wanted.push_back(name);
  }
  if (wanted == local_wanted_) return;
  local_wanted_ = wanted;
  link->localInterestChanged(std::move(wanted));
}

void Broker::attachLink(BrokerLink* link) {
  absl::MutexLock lock(&mutex_);
  link_.store(link);
  local_wanted_.clear();
  if (link != nullptr) {
    localInterestChangedLocked(std::chrono::steady_clock::now());
    return;
  }
  // A publish that took the old link calls it under its topic's mutex:
  // taking each one once waits for those calls.
  for (auto& [name, topic] : topics_) absl::MutexLock topic_lock(&topic->mutex);
}

void Broker::setRemoteWanted(std::vector<std::string> topics) {
  InterestReactors watchers;
  {
    absl::MutexLock lock(&mutex_);
    std::set<std::string, std::less<>> wanted(std::make_move_iterator(topics.begin()),
                                              std::make_move_iterator(topics.end()));
    if (wanted == remote_wanted_ || shutting_down_) return;
    const auto now = std::chrono::steady_clock::now();
    for (auto& [name, topic] : topics_) {
      absl::MutexLock topic_lock(&topic->mutex);
      topic->remote_wanted = wanted.count(name) != 0;
      forgetIfUnwantedLocked(*topic, now);
    }
    remote_wanted_ = std::move(wanted);
    interestChangedLocked(&watchers);
  }
  for (const auto& watcher : watchers) watcher->pump();
}

grpc::Status Broker::publishRemote(const std::string& topic, google::protobuf::Any sample) {
  v1::PublishRequest request;
  request.set_topic(topic);
  *request.mutable_sample() = std::move(sample);
  absl::MutexLock lock(&remote_publish_mutex_);
  if (!remote_publisher_) remote_publisher_ = std::make_unique<RemotePublisher>(this);
  return publish(*remote_publisher_, request);
}

void Broker::removeInterestWatcher(const InterestReactor* watcher) {
  absl::MutexLock lock(&mutex_);
  interest_watchers_.erase(std::remove_if(interest_watchers_.begin(), interest_watchers_.end(),
                                          [watcher](const auto& w) { return w.get() == watcher; }),
                           interest_watchers_.end());
}

grpc::ServerWriteReactor<v1::WatchInterestResponse>* Broker::WatchInterest(
    grpc::CallbackServerContext* /*context*/, const v1::WatchInterestRequest* request) {
  auto reactor = std::make_shared<InterestReactor>(this, request->prefix());
  reactor->setSelf(reactor);
  bool refused = false;
  {
    absl::MutexLock lock(&mutex_);
    refused = shutting_down_;
    if (!refused) {
      interest_watchers_.push_back(reactor);
      InterestReactors ignored;  // the new watcher is pumped below
      interestChangedLocked(&ignored);
    }
  }
  if (refused) {
    reactor->requestFinish(shuttingDownStatus());
  } else {
    reactor->pump();
  }
  return reactor.get();
}

void Broker::housekeep() {
  std::vector<Topic::WaitingGet> left;
  {
    absl::MutexLock lock(&mutex_);
    while (!shutting_down_) {
      const auto now = std::chrono::steady_clock::now();
      auto next = std::chrono::steady_clock::time_point::max();
      std::vector<std::pair<Topic::WaitingGet, std::string>> expired;  // and its topic
      bool interest_changed = false;
      // Topics only ever asked for across the link (GetLatest), never
      // published: forgotten, as a subscriber's waiting topic is.
      std::vector<std::shared_ptr<Topic>> unasked;
      for (auto it = timed_topics_.begin(); it != timed_topics_.end();) {
        const std::shared_ptr<Topic> keep = *it;  // outlives topic_lock
        Topic& topic = *keep;
        absl::MutexLock topic_lock(&topic.mutex);
        auto& waiting = topic.waiting;
        for (auto w = waiting.begin(); w != waiting.end();) {
          if (w->deadline <= now) {
            expired.emplace_back(*w, topic.name);
            w = waiting.erase(w);
          } else {
            next = std::min(next, w->deadline);
            ++w;
          }
        }
        if (topic.wanted_until != std::chrono::steady_clock::time_point{} &&
            topic.wanted_until <= now) {
          topic.wanted_until = {};
          // Unwanted now, or wanted only at its subscribers' rates.
          interest_changed = true;
          if (topic.subscribers.empty()) {
            forgetIfUnwantedLocked(topic, now);
            if (topic.seq == 0 && waiting.empty()) unasked.push_back(keep);
          }
        } else if (topic.wanted_until != std::chrono::steady_clock::time_point{}) {
          next = std::min(next, topic.wanted_until);
        }
        const bool timed =
            !waiting.empty() || topic.wanted_until != std::chrono::steady_clock::time_point{};
        it = timed ? std::next(it) : timed_topics_.erase(it);
      }
      for (const auto& topic : unasked) {
        auto found = topics_.find(topic->name);
        if (found == topics_.end() || found->second != topic) continue;
        absl::MutexLock topic_lock(&topic->mutex);
        if (topic->seq == 0 && topic->subscribers.empty() && topic->waiting.empty()) {
          topics_.erase(found);
          topic->removeMetrics(*metrics_);
        }
      }
      InterestReactors watchers;
      if (interest_changed) interestChangedLocked(&watchers);
      if (!expired.empty() || !watchers.empty()) {
        mutex_.Unlock();
        for (const auto& watcher : watchers) watcher->pump();
        for (auto& [get, topic_name] : expired) {
          get.reactor->Finish(errors::grpcError(
              grpc::StatusCode::NOT_FOUND, v1::TOPIC_EMPTY,
              "no sample on the gated topic within the wait: its publisher did not resume it",
              {{"topic", topic_name}}));
        }
        mutex_.Lock();
        continue;
      }
      // Until the next deadline, a new timed topic, or the shutdown.
      const uint64_t seen = housekeeping_wakes_;
      const auto woken = [this, seen]() ABSL_EXCLUSIVE_LOCKS_REQUIRED(mutex_) {
        return shutting_down_ || housekeeping_wakes_ != seen;
      };
      if (next == std::chrono::steady_clock::time_point::max()) {
        mutex_.Await(absl::Condition(&woken));
      } else {
        mutex_.AwaitWithTimeout(absl::Condition(&woken),
                                absl::FromChrono(next - std::chrono::steady_clock::now()));
      }
    }
    // Shutting down: answer whoever still waits.
    for (const auto& topic : timed_topics_) {
      absl::MutexLock topic_lock(&topic->mutex);
      left.insert(left.end(), topic->waiting.begin(), topic->waiting.end());
      topic->waiting.clear();
    }
    timed_topics_.clear();
  }
  for (auto& get : left) get.reactor->Finish(shuttingDownStatus());
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
  InterestReactors watchers;
  bool waits = false;
  {
    absl::MutexLock lock(&mutex_);
    auto it = topics_.find(request->topic());
    bool gated = false;
    if (it != topics_.end() && !shutting_down_) {
      absl::MutexLock topic_lock(&it->second->mutex);
      // With a link, another host may publish it: asking makes it wanted
      // there too, and the call waits for the sample to arrive.
      gated = it->second->gated || (link_.load() != nullptr && !it->second->latest);
    } else if (!shutting_down_ && link_.load() != nullptr) {
      std::shared_ptr<Topic> made = topicLocked(request->topic());
      if (made) it = topics_.find(request->topic());
      gated = made != nullptr;
    }
    if (gated) {
      // A gated topic is wanted for a while after a GetLatest, so that its
      // publisher (re)starts it; without a sample the call waits for one.
      std::shared_ptr<Topic> topic = it->second;
      const auto now = std::chrono::steady_clock::now();
      bool was_wanted = false;
      {
        absl::MutexLock topic_lock(&topic->mutex);
        // Wanted already, and at every sample (a GetLatest wants the newest).
        was_wanted = topic->localWantedLocked(now) && topic->wantedRateLocked(now) == 0;
        topic->wanted_until = now + kTransientInterest;
        latest = topic->latest;
        if (!latest) {
          const auto left = std::max<std::chrono::system_clock::duration>(
              context->deadline() - std::chrono::system_clock::now(),
              std::chrono::system_clock::duration::zero());
          const auto wait = std::min<std::chrono::system_clock::duration>(kMaxGetLatestWait, left);
          topic->waiting.push_back(
              {reactor, response,
               now + std::chrono::duration_cast<std::chrono::steady_clock::duration>(wait)});
          waits = true;
        }
      }
      timed_topics_.insert(topic);
      ++housekeeping_wakes_;
      if (!was_wanted) interestChangedLocked(&watchers);
    } else if (it != topics_.end()) {
      absl::MutexLock topic_lock(&it->second->mutex);
      latest = it->second->latest;
    }
  }
  for (const auto& watcher : watchers) watcher->pump();
  if (waits) return reactor;
  if (!latest) {
    reactor->Finish(errors::grpcError(
        grpc::StatusCode::NOT_FOUND, v1::TOPIC_EMPTY,
        absl::StrCat("nothing has been published on topic '", request->topic(), "' yet"),
        {{"topic", request->topic()}}));
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
    absl::MutexLock lock(&mutex_);
    for (auto it = topics_.lower_bound(prefix);
         it != topics_.end() && absl::StartsWith(it->first, prefix); ++it) {
      Topic& topic = *it->second;
      absl::MutexLock topic_lock(&topic.mutex);
      v1::TopicInfo* info = response->add_topics();
      info->set_name(topic.name);
      if (topic.type != nullptr) info->set_type(topic.type->full_name());
      info->set_published_count(topic.seq);
      info->set_subscriber_count(static_cast<uint32_t>(topic.subscribers.size()));
      if (topic.latest) *info->mutable_last_receive_time() = topic.latest->receive_time();
    }
  }
  const grpc::Status paged = server_kit::paginate<v1::TopicInfo>(
      response->mutable_topics(), [](const v1::TopicInfo& t) { return t.name(); }, *request,
      response->mutable_next_page_token());
  grpc::ServerUnaryReactor* reactor = context->DefaultReactor();
  reactor->Finish(paged);
  return reactor;
}

void Broker::shutdown() {
  std::vector<std::shared_ptr<SubscribeReactor>> subscribers;
  InterestReactors watchers;
  {
    absl::MutexLock lock(&mutex_);
    shutting_down_ = true;
    for (auto& [name, topic] : topics_) {
      absl::MutexLock topic_lock(&topic->mutex);
      subscribers.insert(subscribers.end(), topic->subscribers.begin(), topic->subscribers.end());
      dropRingLocked(*topic);
    }
    // Finish never runs a reaction inline (OnDone, which needs mutex_, is
    // dispatched to gRPC's threads), so this is safe under the lock, which
    // keeps the reactors alive meanwhile.
    for (Publisher* publisher : publishers_) publisher->requestFinish(shuttingDownStatus());
    watchers = interest_watchers_;
  }
  // The housekeeper answers the waiting GetLatest calls (it saw shutting_down_).
  for (const auto& subscriber : subscribers) subscriber->requestFinish(shuttingDownStatus());
  for (const auto& watcher : watchers) watcher->requestFinish(shuttingDownStatus());
}

}  // namespace behaviorlib::channel
