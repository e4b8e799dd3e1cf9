#include "behaviorlib/channel/channel_client.h"

#include <google/protobuf/message.h>
#include <grpcpp/grpcpp.h>

#include <algorithm>
#include <atomic>
#include <map>
#include <optional>
#include <thread>
#include <utility>

#include "absl/base/thread_annotations.h"
#include "absl/container/flat_hash_map.h"
#include "absl/strings/match.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/synchronization/mutex.h"
#include "absl/time/time.h"
#include "behaviorlib/channel/shm_ring.h"
#include "behaviorlib/channel/topic.h"
#include "behaviorlib/error_details.h"
#include "behaviorlib/server_kit/transport_security.h"
#include "behaviorlib/v1/channel.grpc.pb.h"

namespace behaviorlib::channel {
namespace {

constexpr std::chrono::milliseconds kInitialBackoff(100);
constexpr std::chrono::milliseconds kMaxBackoff(2000);
// A ring reader's longest sleep without news: a safety net only, since the
// writer and the stream's end wake it.
constexpr int64_t kRingWaitNs = 2'000'000'000;

// With the broker's details.
absl::Status toAbsl(const grpc::Status& status) { return errors::fromGrpc(status); }

// gRPC's own reconnection backoff (1 s growing to 120 s by default) would
// hold a broker restart back far longer than our subscriptions' 100 ms..2 s
// retry loop; align the two.
grpc::ChannelArguments channelArguments() {
  grpc::ChannelArguments args;
  args.SetInt(GRPC_ARG_INITIAL_RECONNECT_BACKOFF_MS, static_cast<int>(kInitialBackoff.count()));
  // gRPC gives each connection attempt at least this long (its "minimum
  // connect timeout"); a refused attempt is still retried after the initial
  // backoff. At 100 ms, a server slow to send its HTTP/2 settings on a loaded
  // machine failed the call.
  args.SetInt(GRPC_ARG_MIN_RECONNECT_BACKOFF_MS, 5000);
  args.SetInt(GRPC_ARG_MAX_RECONNECT_BACKOFF_MS, static_cast<int>(kMaxBackoff.count()));
  return args;
}

}  // namespace

// Wakes ChannelClient::waitDelivered (Mutex::Await on a new generation) when
// a subscription processed a sample or its connection changed.
struct ProgressSignal {
  void notify() {
    absl::MutexLock lock(&mutex);
    ++generation;
  }
  uint64_t current() {
    absl::MutexLock lock(&mutex);
    return generation;
  }
  // Whether a notify() came after `seen`, within `timeout`.
  bool awaitAfter(uint64_t seen, absl::Duration timeout) {
    absl::MutexLock lock(&mutex);
    const auto moved = [this, seen]()
                           ABSL_EXCLUSIVE_LOCKS_REQUIRED(mutex) { return generation != seen; };
    return mutex.AwaitWithTimeout(absl::Condition(&moved), timeout);
  }
  absl::Mutex mutex;
  uint64_t generation ABSL_GUARDED_BY(mutex) = 0;
};

// ---------------------------------------------------------------------------
// Subscription

class Subscription::Impl {
 public:
  Impl(std::shared_ptr<v1::DataChannel::Stub> stub, v1::SubscribeRequest request,
       std::function<void(const v1::SubscribeResponse&)> on_sample,
       std::shared_ptr<ProgressSignal> progress)
      : stub_(std::move(stub)),
        request_(std::move(request)),
        on_sample_(std::move(on_sample)),
        progress_(std::move(progress)) {}

  ~Impl() { stop(); }

  // A subscription refused before it started (e.g. invalid topic name).
  void fail(absl::Status status) {
    absl::MutexLock lock(&mutex_);
    status_ = std::move(status);
  }

  void start() {
    thread_ = std::thread([this] { run(); });
  }

  void stop() {
    {
      absl::MutexLock lock(&mutex_);
      stopping_ = true;
      if (context_ != nullptr) context_->TryCancel();
    }
    if (thread_.joinable()) thread_.join();
  }

  bool connected() const {
    absl::MutexLock lock(&mutex_);
    return connected_;
  }

  bool waitConnected(std::chrono::milliseconds timeout) const {
    absl::MutexLock lock(&mutex_);
    return mutex_.AwaitWithTimeout(absl::Condition(&connected_), absl::FromChrono(timeout));
  }

  uint64_t connectCount() const {
    absl::MutexLock lock(&mutex_);
    return connect_count_;
  }

  uint64_t receivedCount() const { return received_.load(); }
  uint64_t processedSeq() const { return processed_seq_.load(); }
  bool rateLimited() const { return request_.max_rate_hz() > 0; }
  const std::string& topic() const { return request_.topic(); }

  absl::Status status() const {
    absl::MutexLock lock(&mutex_);
    return status_;
  }

 private:
  void run() {
    std::chrono::milliseconds backoff = kInitialBackoff;
    // Cleared for good when the broker's ring cannot be opened here (the
    // broker is on another host, or in another container).
    bool use_ring = request_.shared_memory();
    while (true) {
      grpc::ClientContext context;
      {
        absl::MutexLock lock(&mutex_);
        if (stopping_) return;
        context_ = &context;
      }
      v1::SubscribeRequest request = request_;
      request.set_shared_memory(use_ring);
      if (use_ring) request.set_shm_domain(ShmRing::domain());
      std::unique_ptr<grpc::ClientReader<v1::SubscribeResponse>> reader =
          stub_->Subscribe(&context, request);
      // The broker sends its initial metadata once the subscription is
      // registered; a refused or failed call carries none of ours.
      reader->WaitForInitialMetadata();
      const auto& metadata = context.GetServerInitialMetadata();
      std::unique_ptr<ShmRing> ring;
      uint64_t ring_first = 0;
      if (auto it = metadata.find(kSubscribedMetadataKey); it != metadata.end()) {
        if (auto r = metadata.find(kShmRingMetadataKey); r != metadata.end()) {
          auto f = metadata.find(kShmFirstMetadataKey);
          absl::StatusOr<std::unique_ptr<ShmRing>> opened =
              ShmRing::open(std::string(r->second.data(), r->second.size()));
          if (f != metadata.end() && opened.ok() &&
              absl::SimpleAtoi(absl::string_view(f->second.data(), f->second.size()),
                               &ring_first)) {
            ring = std::move(*opened);
          } else {
            // Not sharing the broker's memory: subscribe again, on the stream.
            use_ring = false;
            context.TryCancel();
            reader->Finish();
            absl::MutexLock lock(&mutex_);
            context_ = nullptr;
            continue;
          }
        }
        // Samples published before the registration never come (unless the
        // latest is sent first): delivered() must not wait for them.
        uint64_t registered_seq = 0;
        if (absl::SimpleAtoi(absl::string_view(it->second.data(), it->second.size()),
                             &registered_seq)) {
          processed_seq_.store(std::max(processed_seq_.load(), registered_seq));
        }
        {
          absl::MutexLock lock(&mutex_);
          connected_ = true;
          ++connect_count_;
          backoff = kInitialBackoff;
        }
        progress_->notify();
      }
      if (ring) {
        readRing(*reader, context, std::move(ring), ring_first);
      } else {
        v1::SubscribeResponse response;
        while (reader->Read(&response)) deliver(response);
      }
      const grpc::Status status = reader->Finish();
      progress_->notify();  // before connected_ goes: a waiter may look early
      absl::MutexLock lock(&mutex_);
      context_ = nullptr;
      connected_ = false;
      status_ = toAbsl(status);
      // A request the broker itself refuses will be refused again.
      if (stopping_ || status.error_code() == grpc::StatusCode::INVALID_ARGUMENT) return;
      // Until stopped, at most backoff.
      mutex_.AwaitWithTimeout(absl::Condition(&stopping_), absl::FromChrono(backoff));
      if (stopping_) return;
      backoff = std::min(backoff * 2, kMaxBackoff);
    }
  }

  void deliver(const v1::SubscribeResponse& response) {
    received_.fetch_add(1);
    on_sample_(response);
    processed_seq_.store(std::max(processed_seq_.load(), response.topic_seq()));
    progress_->notify();
  }

  // Reads the samples from the broker's shared-memory ring (decision 20)
  // while the stream, which carries none, stays up. Returns with the stream
  // ended or cancelled.
  void readRing(grpc::ClientReader<v1::SubscribeResponse>& reader, grpc::ClientContext& context,
                std::unique_ptr<ShmRing> first_ring, uint64_t next) {
    std::shared_ptr<ShmRing> ring(std::move(first_ring));
    {
      absl::MutexLock lock(&mutex_);
      ring_ = ring;
    }
    std::atomic<bool> stream_done{false};
    // The stream ends when the broker goes away or the subscription is
    // stopped (its context cancelled); either must wake the reader.
    std::thread watcher([&] {
      v1::SubscribeResponse ignored;
      while (reader.Read(&ignored)) {
      }
      stream_done.store(true);
      absl::MutexLock lock(&mutex_);
      if (ring_) ring_->wake();
    });
    const bool latest_only = request_.mode() != v1::DELIVERY_MODE_QUEUE || rateLimited();
    // A rate-limited reader reads the newest sample at most this often.
    const auto interval =
        rateLimited() ? absl::Seconds(1.0 / request_.max_rate_hz()) : absl::ZeroDuration();
    std::string bytes;
    uint64_t dropped = 0;
    v1::SubscribeResponse response;
    bool reading = true;
    while (reading && !stream_done.load()) {
      const uint32_t token = ring->notifyToken();
      switch (ring->read(&next, latest_only, &bytes, &dropped)) {
        case ShmRing::Read::kSample:
          if (response.ParseFromString(bytes)) {
            response.set_dropped_count(dropped);
            deliver(response);
          }
          if (interval > absl::ZeroDuration()) {
            // Until stopped, at most the interval; then the newest sample.
            absl::MutexLock lock(&mutex_);
            mutex_.AwaitWithTimeout(absl::Condition(&stopping_), interval);
          }
          break;
        case ShmRing::Read::kEmpty:
          if (!stream_done.load()) ring->wait(token, kRingWaitNs);
          break;
        case ShmRing::Read::kSuperseded: {
          absl::StatusOr<std::unique_ptr<ShmRing>> successor = ShmRing::open(ring->successor());
          if (!successor.ok()) {
            reading = false;
            break;
          }
          ring = std::move(*successor);
          absl::MutexLock lock(&mutex_);
          ring_ = ring;
          break;
        }
        case ShmRing::Read::kClosed:
          reading = false;
          break;
      }
    }
    context.TryCancel();
    watcher.join();
    absl::MutexLock lock(&mutex_);
    ring_.reset();
  }

  const std::shared_ptr<v1::DataChannel::Stub> stub_;
  const v1::SubscribeRequest request_;
  const std::function<void(const v1::SubscribeResponse&)> on_sample_;
  const std::shared_ptr<ProgressSignal> progress_;
  std::thread thread_;
  std::atomic<uint64_t> received_{0};
  std::atomic<uint64_t> processed_seq_{0};

  // waitConnected waits on mutex_ (Mutex::Await) for connected_.
  mutable absl::Mutex mutex_;
  grpc::ClientContext* context_ ABSL_GUARDED_BY(mutex_) = nullptr;  // of the stream in progress
  std::shared_ptr<ShmRing> ring_ ABSL_GUARDED_BY(mutex_);           // the ring being read, if any
  bool stopping_ ABSL_GUARDED_BY(mutex_) = false;
  bool connected_ ABSL_GUARDED_BY(mutex_) = false;
  uint64_t connect_count_ ABSL_GUARDED_BY(mutex_) = 0;
  absl::Status status_ ABSL_GUARDED_BY(mutex_);
};

Subscription::Subscription(std::shared_ptr<Impl> impl) : impl_(std::move(impl)) {}
Subscription::~Subscription() { impl_->stop(); }
bool Subscription::connected() const { return impl_->connected(); }
bool Subscription::waitConnected(std::chrono::milliseconds timeout) const {
  return impl_->waitConnected(timeout);
}
uint64_t Subscription::connectCount() const { return impl_->connectCount(); }
uint64_t Subscription::receivedCount() const { return impl_->receivedCount(); }
const std::string& Subscription::topic() const { return impl_->topic(); }
uint64_t Subscription::processedSeq() const { return impl_->processedSeq(); }
absl::Status Subscription::status() const { return impl_->status(); }

// ---------------------------------------------------------------------------
// InterestWatch

class InterestWatch::Impl {
 public:
  Impl(std::shared_ptr<v1::DataChannel::Stub> stub, std::string prefix,
       std::function<void()> on_change)
      : stub_(std::move(stub)), prefix_(std::move(prefix)), on_change_(std::move(on_change)) {
    thread_ = std::thread([this] { run(); });
  }

  ~Impl() { stop(); }

  void stop() {
    {
      absl::MutexLock lock(&mutex_);
      stopping_ = true;
      if (context_ != nullptr) context_->TryCancel();
    }
    if (thread_.joinable()) thread_.join();
  }

  bool wanted(const std::string& topic) const {
    if (!absl::StartsWith(topic, prefix_)) return true;  // not gated
    absl::MutexLock lock(&mutex_);
    return !known_ || wanted_.contains(topic);
  }

  bool known() const {
    absl::MutexLock lock(&mutex_);
    return known_;
  }

  double maxRateHz(const std::string& topic) const {
    absl::MutexLock lock(&mutex_);
    if (!known_) return 0;
    auto it = wanted_.find(topic);
    return it == wanted_.end() ? 0 : it->second;
  }

  std::vector<std::string> wantedTopics() const {
    std::vector<std::string> topics;
    {
      absl::MutexLock lock(&mutex_);
      if (known_) {
        for (const auto& [topic, rate] : wanted_) topics.push_back(topic);
      }
    }
    std::sort(topics.begin(), topics.end());
    return topics;
  }

 private:
  void run() {
    std::chrono::milliseconds backoff = kInitialBackoff;
    while (true) {
      grpc::ClientContext context;
      {
        absl::MutexLock lock(&mutex_);
        if (stopping_) return;
        context_ = &context;
      }
      v1::WatchInterestRequest request;
      request.set_prefix(prefix_);
      auto reader = stub_->WatchInterest(&context, request);
      v1::WatchInterestResponse response;
      while (reader->Read(&response)) {
        {
          absl::MutexLock lock(&mutex_);
          known_ = true;
          wanted_.clear();
          for (int i = 0; i < response.wanted_topics_size(); ++i) {
            // A broker before max_rate_hz sends no rates: every sample.
            wanted_[response.wanted_topics(i)] =
                i < response.max_rate_hz_size() ? response.max_rate_hz(i) : 0.0;
          }
        }
        backoff = kInitialBackoff;
        on_change_();
      }
      reader->Finish().IgnoreError();
      bool was_known = false;
      {
        absl::MutexLock lock(&mutex_);
        context_ = nullptr;
        was_known = known_;
        known_ = false;  // everything wanted until the broker answers again
      }
      if (was_known) on_change_();
      absl::MutexLock lock(&mutex_);
      // Until stopped, at most backoff.
      mutex_.AwaitWithTimeout(absl::Condition(&stopping_), absl::FromChrono(backoff));
      if (stopping_) return;
      backoff = std::min(backoff * 2, kMaxBackoff);
    }
  }

  const std::shared_ptr<v1::DataChannel::Stub> stub_;
  const std::string prefix_;
  const std::function<void()> on_change_;
  std::thread thread_;

  mutable absl::Mutex mutex_;
  grpc::ClientContext* context_ ABSL_GUARDED_BY(mutex_) = nullptr;
  bool stopping_ ABSL_GUARDED_BY(mutex_) = false;
  bool known_ ABSL_GUARDED_BY(mutex_) = false;
  // Each wanted topic and the rate it is wanted at (0: every sample).
  absl::flat_hash_map<std::string, double> wanted_ ABSL_GUARDED_BY(mutex_);
};

InterestWatch::InterestWatch(std::shared_ptr<Impl> impl) : impl_(std::move(impl)) {}
InterestWatch::~InterestWatch() { impl_->stop(); }
bool InterestWatch::wanted(const std::string& topic) const { return impl_->wanted(topic); }
bool InterestWatch::known() const { return impl_->known(); }
double InterestWatch::maxRateHz(const std::string& topic) const { return impl_->maxRateHz(topic); }
std::vector<std::string> InterestWatch::wantedTopics() const { return impl_->wantedTopics(); }

// ---------------------------------------------------------------------------
// ChannelClient

class ChannelClient::Impl {
 public:
  explicit Impl(std::string address)
      : address_(std::move(address)),
        channel_(behaviorlib::server_kit::makeChannel(address_, channelArguments())),
        stub_(v1::DataChannel::NewStub(channel_)) {}

  ~Impl() {
    absl::MutexLock lock(&publish_mutex_);
    if (writer_) closeLocked().IgnoreError();
  }

  absl::Status publish(const std::string& topic, const google::protobuf::Message& sample) {
    if (absl::Status status = validateTopicName(topic); !status.ok()) return status;
    v1::PublishRequest request;
    request.set_topic(topic);
    request.mutable_sample()->PackFrom(sample);
    return write(request);
  }

  absl::Status publishAll(const std::vector<ChannelClient::TopicSample>& samples) {
    if (samples.empty()) return absl::OkStatus();
    v1::PublishRequest request;
    if (absl::Status status = packBatch(samples, request); !status.ok()) return status;
    absl::MutexLock lock(&publish_mutex_);
    return writeLocked(request);
  }

  absl::Status publishAllAndSync(const std::vector<ChannelClient::TopicSample>& samples) {
    if (samples.empty()) return sync();
    v1::PublishRequest request;
    if (absl::Status status = packBatch(samples, request); !status.ok()) return status;
    request.set_sync(true);
    absl::MutexLock lock(&publish_mutex_);
    if (absl::Status status = writeLocked(request); !status.ok()) return status;
    return answerLocked(nullptr);
  }

  static absl::Status packBatch(const std::vector<ChannelClient::TopicSample>& samples,
                                v1::PublishRequest& request) {
    for (std::size_t i = 0; i < samples.size(); ++i) {
      const auto& [topic, sample] = samples[i];
      if (absl::Status status = validateTopicName(topic); !status.ok()) return status;
      v1::PublishRequest* part = i == 0 ? &request : request.add_more();
      part->set_topic(topic);
      part->mutable_sample()->PackFrom(*sample);
    }
    return absl::OkStatus();
  }

  absl::Status write(const v1::PublishRequest& request) {
    absl::MutexLock lock(&publish_mutex_);
    return writeLocked(request);
  }

  // Writes one message on the publish stream.
  absl::Status writeLocked(const v1::PublishRequest& request)
      ABSL_EXCLUSIVE_LOCKS_REQUIRED(publish_mutex_) {
    while (true) {
      const bool fresh = !writer_;
      if (fresh) openLocked();
      grpc::WriteOptions options;
      if (buffer_until_sync_.load(std::memory_order_relaxed) && !request.sync()) {
        options.set_buffer_hint();
      }
      if (writer_->Write(request, options)) {
        unsynced_ = true;
        return absl::OkStatus();
      }
      absl::Status status = closeLocked();
      // A stream that worked before and broke because the broker went away
      // (restart) deserves one retry on a new stream; anything else, or a
      // fresh stream failing, is reported.
      const bool broker_gone = status.ok() || status.code() == absl::StatusCode::kUnavailable;
      if (fresh || !broker_gone) return status.ok() ? closedByBroker() : status;
    }
  }

  absl::StatusOr<uint64_t> flush() {
    absl::MutexLock lock(&publish_mutex_);
    if (!writer_) return 0;
    uint64_t accepted = 0;
    if (absl::Status status = askLocked(&accepted); !status.ok()) return status;
    if (absl::Status status = closeLocked(); !status.ok()) return status;
    return accepted;
  }

  absl::Status sync() {
    absl::MutexLock lock(&publish_mutex_);
    if (!writer_ || !unsynced_) return absl::OkStatus();
    return askLocked(nullptr);
  }

  bool delivered(const std::function<uint64_t(const std::string&)>& topic_seq) const {
    absl::MutexLock lock(&subscriptions_mutex_);
    for (const auto& weak : subscriptions_) {
      const std::shared_ptr<Subscription::Impl> sub = weak.lock();
      // A rate-limited one promises no particular sample.
      if (!sub || !sub->connected() || sub->rateLimited()) continue;
      if (sub->processedSeq() < topic_seq(sub->topic())) return false;
    }
    return true;
  }

  std::vector<std::string> awaitedTopics() const {
    std::vector<std::string> topics;
    {
      absl::MutexLock lock(&subscriptions_mutex_);
      for (const auto& weak : subscriptions_) {
        const std::shared_ptr<Subscription::Impl> sub = weak.lock();
        if (sub && !sub->rateLimited()) topics.push_back(sub->topic());
      }
    }
    std::sort(topics.begin(), topics.end());
    topics.erase(std::unique(topics.begin(), topics.end()), topics.end());
    return topics;
  }

  std::map<std::string, uint64_t> acceptedSeqs() const {
    absl::MutexLock lock(&accepted_mutex_);
    return accepted_seqs_;
  }

  bool waitDelivered(const std::function<uint64_t(const std::string&)>& topic_seq,
                     std::chrono::milliseconds timeout) const {
    const auto deadline = std::chrono::steady_clock::now() + timeout;
    while (true) {
      const uint64_t generation = progress_->current();
      if (delivered(topic_seq)) return true;
      if (!progress_->awaitAfter(generation,
                                 absl::FromChrono(deadline - std::chrono::steady_clock::now()))) {
        return false;
      }
    }
  }

  absl::StatusOr<v1::SubscribeResponse> getLatest(const std::string& topic,
                                                  std::chrono::milliseconds timeout) {
    grpc::ClientContext context;
    context.set_deadline(std::chrono::system_clock::now() + timeout);
    v1::GetLatestRequest request;
    request.set_topic(topic);
    v1::GetLatestResponse response;
    grpc::Status status = stub_->GetLatest(&context, request, &response);
    if (!status.ok()) return toAbsl(status);
    return std::move(*response.mutable_sample());
  }

  absl::StatusOr<std::vector<v1::TopicInfo>> listTopics(const std::string& prefix,
                                                        std::chrono::milliseconds timeout) {
    // Every page, within one deadline. The broker caps its topics, so the
    // pages are few; the bound only guards against a broker that never
    // ends its token chain.
    constexpr int kPageSize = 1000;
    constexpr int kMaxPages = 1000;
    const auto deadline = std::chrono::system_clock::now() + timeout;
    v1::ListTopicsRequest request;
    request.set_prefix(prefix);
    request.set_page_size(kPageSize);
    std::vector<v1::TopicInfo> topics;
    for (int page = 0; page < kMaxPages; ++page) {
      grpc::ClientContext context;
      context.set_deadline(deadline);
      v1::ListTopicsResponse response;
      grpc::Status status = stub_->ListTopics(&context, request, &response);
      if (!status.ok()) return toAbsl(status);
      topics.insert(topics.end(), response.topics().begin(), response.topics().end());
      if (response.next_page_token().empty()) return topics;
      request.set_page_token(response.next_page_token());
    }
    return absl::DataLossError("ListTopics: the broker's pages did not end after " +
                               std::to_string(kMaxPages) + " pages");
  }

  std::unique_ptr<Subscription> subscribe(
      const std::string& topic, SubscribeOptions options,
      std::function<void(const v1::SubscribeResponse&)> on_sample) {
    v1::SubscribeRequest request;
    request.set_topic(topic);
    request.set_mode(options.mode);
    request.set_queue_size(options.queue_size);
    request.set_send_latest_first(options.send_latest_first);
    request.set_shared_memory(options.shared_memory);
    request.set_max_rate_hz(options.max_rate_hz);
    auto impl = std::make_shared<Subscription::Impl>(stub_, std::move(request),
                                                     std::move(on_sample), progress_);
    if (absl::Status status = validateTopicName(topic); !status.ok()) {
      impl->fail(std::move(status));
    } else {
      impl->start();
      absl::MutexLock lock(&subscriptions_mutex_);
      std::erase_if(subscriptions_, [](const auto& weak) { return weak.expired(); });
      subscriptions_.push_back(impl);
    }
    return std::make_unique<Subscription>(std::move(impl));
  }

  void bufferUntilSync(bool buffer) { buffer_until_sync_.store(buffer); }

  void gatePublishing(const std::string& prefix) {
    absl::MutexLock lock(&publish_mutex_);
    gated_prefix_ = prefix;
    if (writer_) closeLocked().IgnoreError();
  }

  std::unique_ptr<InterestWatch> watchInterest(const std::string& prefix,
                                               std::function<void()> on_change) {
    return std::make_unique<InterestWatch>(
        std::make_shared<InterestWatch::Impl>(stub_, prefix, std::move(on_change)));
  }

  const std::string address_;

 private:
  void openLocked() ABSL_EXCLUSIVE_LOCKS_REQUIRED(publish_mutex_) {
    publish_context_ = std::make_unique<grpc::ClientContext>();
    if (gated_prefix_) publish_context_->AddMetadata(kGatedPrefixMetadataKey, *gated_prefix_);
    writer_ = stub_->PublishAcked(publish_context_.get());
  }

  // Asks the broker what the stream has taken so far (PublishRequest.sync):
  // one round trip, the stream stays open. A refusal or a broker gone ends
  // the stream, and its status is returned.
  absl::Status askLocked(uint64_t* accepted) ABSL_EXCLUSIVE_LOCKS_REQUIRED(publish_mutex_) {
    v1::PublishRequest marker;
    marker.set_sync(true);
    if (!writer_->Write(marker)) return closedLocked();
    return answerLocked(accepted);
  }

  // Reads the answer to a sync request just written.
  absl::Status answerLocked(uint64_t* accepted) ABSL_EXCLUSIVE_LOCKS_REQUIRED(publish_mutex_) {
    v1::PublishResponse answer;
    if (!writer_->Read(&answer)) return closedLocked();
    if (accepted != nullptr) *accepted = answer.accepted_count();
    {
      absl::MutexLock lock(&accepted_mutex_);
      for (const auto& [topic, seq] : answer.topic_seqs()) {
        uint64_t& known = accepted_seqs_[topic];
        known = std::max(known, seq);
      }
    }
    unsynced_ = false;
    return absl::OkStatus();
  }

  // The stream broke: closed, and why.
  absl::Status closedLocked() ABSL_EXCLUSIVE_LOCKS_REQUIRED(publish_mutex_) {
    absl::Status status = closeLocked();
    return status.ok() ? closedByBroker() : status;
  }

  absl::Status closedByBroker() const {
    return absl::UnavailableError(
        absl::StrCat("publish stream to ", address_, " was closed by the broker"));
  }

  absl::Status closeLocked() ABSL_EXCLUSIVE_LOCKS_REQUIRED(publish_mutex_) {
    writer_->WritesDone();
    v1::PublishResponse unread;
    while (writer_->Read(&unread)) {
    }
    const grpc::Status status = writer_->Finish();
    if (!status.ok()) {
      absl::MutexLock lock(&accepted_mutex_);
      accepted_seqs_.clear();  // a broker restart numbers topics anew
    }
    writer_.reset();
    publish_context_.reset();
    unsynced_ = false;
    return toAbsl(status);
  }

  const std::shared_ptr<grpc::Channel> channel_;
  const std::shared_ptr<v1::DataChannel::Stub> stub_;

  std::atomic<bool> buffer_until_sync_{false};
  absl::Mutex publish_mutex_;  // guards the publish stream below
  std::unique_ptr<grpc::ClientContext> publish_context_ ABSL_GUARDED_BY(publish_mutex_);
  std::unique_ptr<grpc::ClientReaderWriter<v1::PublishRequest, v1::PublishResponse>> writer_
      ABSL_GUARDED_BY(publish_mutex_);
  std::optional<std::string> gated_prefix_ ABSL_GUARDED_BY(publish_mutex_);
  // Written on the stream since it opened.
  bool unsynced_ ABSL_GUARDED_BY(publish_mutex_) = false;
  mutable absl::Mutex accepted_mutex_;
  // PublishResponse.topic_seqs, merged.
  std::map<std::string, uint64_t> accepted_seqs_ ABSL_GUARDED_BY(accepted_mutex_);

  const std::shared_ptr<ProgressSignal> progress_ = std::make_shared<ProgressSignal>();
  mutable absl::Mutex subscriptions_mutex_;
  // For delivered().
  std::vector<std::weak_ptr<Subscription::Impl>> subscriptions_
      ABSL_GUARDED_BY(subscriptions_mutex_);
};

ChannelClient::ChannelClient(const std::string& address) : impl_(std::make_unique<Impl>(address)) {}
ChannelClient::~ChannelClient() = default;

const std::string& ChannelClient::address() const { return impl_->address_; }

absl::Status ChannelClient::publishAll(const std::vector<TopicSample>& samples) {
  return impl_->publishAll(samples);
}

absl::Status ChannelClient::publish(const std::string& topic,
                                    const google::protobuf::Message& sample) {
  return impl_->publish(topic, sample);
}

absl::StatusOr<uint64_t> ChannelClient::flush() { return impl_->flush(); }

absl::Status ChannelClient::publishAllAndSync(const std::vector<TopicSample>& samples) {
  return impl_->publishAllAndSync(samples);
}

absl::Status ChannelClient::sync() { return impl_->sync(); }

void ChannelClient::bufferUntilSync(bool buffer) { impl_->bufferUntilSync(buffer); }

bool ChannelClient::delivered(
    const std::function<uint64_t(const std::string& topic)>& topic_seq) const {
  return impl_->delivered(topic_seq);
}

std::vector<std::string> ChannelClient::awaitedTopics() const { return impl_->awaitedTopics(); }

std::map<std::string, uint64_t> ChannelClient::acceptedSeqs() const {
  return impl_->acceptedSeqs();
}

bool ChannelClient::waitDelivered(
    const std::function<uint64_t(const std::string& topic)>& topic_seq,
    std::chrono::milliseconds timeout) const {
  return impl_->waitDelivered(topic_seq, timeout);
}

absl::StatusOr<v1::SubscribeResponse> ChannelClient::getLatest(const std::string& topic,
                                                               std::chrono::milliseconds timeout) {
  return impl_->getLatest(topic, timeout);
}

absl::StatusOr<std::vector<v1::TopicInfo>> ChannelClient::listTopics(
    const std::string& prefix, std::chrono::milliseconds timeout) {
  return impl_->listTopics(prefix, timeout);
}

std::unique_ptr<Subscription> ChannelClient::subscribe(
    const std::string& topic, SubscribeOptions options,
    std::function<void(const v1::SubscribeResponse&)> on_sample) {
  return impl_->subscribe(topic, options, std::move(on_sample));
}

void ChannelClient::gatePublishing(const std::string& prefix) { impl_->gatePublishing(prefix); }

std::unique_ptr<InterestWatch> ChannelClient::watchInterest(const std::string& prefix,
                                                            std::function<void()> on_change) {
  return impl_->watchInterest(prefix, std::move(on_change));
}

}  // namespace behaviorlib::channel
