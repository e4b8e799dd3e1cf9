#include "behaviorlib/channel/nats_link.h"

#include <google/protobuf/any.pb.h>
#include <nats/nats.h>
#include <prometheus/counter.h>
#include <prometheus/family.h>
#include <prometheus/gauge.h>
#include <prometheus/registry.h>

#include <algorithm>
#include <atomic>
#include <map>
#include <set>
#include <thread>
#include <utility>

#include "absl/base/thread_annotations.h"
#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "absl/synchronization/mutex.h"
#include "absl/time/time.h"
#include "behaviorlib/channel/topic.h"

namespace behaviorlib::channel {
namespace {

constexpr absl::string_view kSamplePrefix = "bl.t.";
constexpr absl::string_view kWantPrefix = "bl.want.";
constexpr char kWantWildcard[] = "bl.want.*";
constexpr char kHelloSubject[] = "bl.hello";

bool nameCharOk(char c) {
  return (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z') || (c >= '0' && c <= '9') || c == '_' ||
         c == '-';
}

absl::Status natsError(absl::string_view what, natsStatus status) {
  return absl::UnavailableError(absl::StrCat(what, ": ", natsStatus_GetText(status)));
}

}  // namespace

std::string topicSubject(absl::string_view topic) {
  std::string subject(kSamplePrefix);
  subject.reserve(kSamplePrefix.size() + topic.size());
  for (char c : topic) subject.push_back(c == '/' ? '.' : c == '.' ? '~' : c);
  return subject;
}

std::optional<std::string> subjectTopic(absl::string_view subject) {
  if (!absl::ConsumePrefix(&subject, kSamplePrefix)) return std::nullopt;
  std::string topic;
  topic.reserve(subject.size());
  for (char c : subject) topic.push_back(c == '.' ? '/' : c == '~' ? '.' : c);
  if (!validateTopicName(topic).ok()) return std::nullopt;
  return topic;
}

// ---------------------------------------------------------------------------

class NatsLink::Impl {
 public:
  Impl(Broker& broker, NatsLinkOptions options, prometheus::Registry& registry)
      : broker_(broker),
        options_(std::move(options)),
        samples_in_(prometheus::BuildCounter()
                        .Name("behaviorlib_channel_link_samples_in_total")
                        .Help("Samples received from other hosts over the link, per topic.")
                        .Register(registry)),
        samples_out_(prometheus::BuildCounter()
                         .Name("behaviorlib_channel_link_samples_out_total")
                         .Help("Samples sent to other hosts over the link, per topic.")
                         .Register(registry)),
        bytes_in_(prometheus::BuildCounter()
                      .Name("behaviorlib_channel_link_bytes_in_total")
                      .Help("Sample payload bytes received over the link.")
                      .Register(registry)
                      .Add({})),
        bytes_out_(prometheus::BuildCounter()
                       .Name("behaviorlib_channel_link_bytes_out_total")
                       .Help("Sample payload bytes sent over the link.")
                       .Register(registry)
                       .Add({})),
        dropped_(prometheus::BuildCounter()
                     .Name("behaviorlib_channel_link_dropped_samples_total")
                     .Help("Samples not sent: the link was down and its buffer full.")
                     .Register(registry)
                     .Add({})),
        rejected_(prometheus::BuildCounter()
                      .Name("behaviorlib_channel_link_rejected_samples_total")
                      .Help("Samples from other hosts refused (topic, type or bytes invalid).")
                      .Register(registry)
                      .Add({})),
        up_gauge_(prometheus::BuildGauge()
                      .Name("behaviorlib_channel_link_up")
                      .Help("1 while the link to the fleet's data engine (NATS) is connected.")
                      .Register(registry)
                      .Add({})),
        peers_gauge_(prometheus::BuildGauge()
                         .Name("behaviorlib_channel_link_peers")
                         .Help("Other brokers heard from within the announcement time to live.")
                         .Register(registry)
                         .Add({})),
        wants_gauge_(prometheus::BuildGauge()
                         .Name("behaviorlib_channel_link_wants_heard")
                         .Help("Wants heard from other brokers (one per broker and topic), set "
                               "once this broker sends those topics.")
                         .Register(registry)
                         .Add({})),
        disconnects_(prometheus::BuildCounter()
                         .Name("behaviorlib_channel_link_disconnects_total")
                         .Help("Times the link to the data engine was lost.")
                         .Register(registry)
                         .Add({})),
        thinned_count_(prometheus::BuildCounter()
                           .Name("behaviorlib_channel_link_thinned_samples_total")
                           .Help("Samples not sent because a newer one of their topic replaced "
                                 "them within the link's rate limit (max_rate_hz).")
                           .Register(registry)
                           .Add({})),
        frames_(prometheus::BuildCounter()
                    .Name("behaviorlib_channel_link_frames_total")
                    .Help("Sends of the rate-limited link (max_rate_hz): each carries the "
                          "newest sample of every topic that has one, in one write.")
                    .Register(registry)
                    .Add({})),
        interval_(options_.max_rate_hz > 0
                      ? std::chrono::duration_cast<std::chrono::steady_clock::duration>(
                            std::chrono::duration<double>(1.0 / options_.max_rate_hz))
                      : std::chrono::steady_clock::duration::zero()) {}

  ~Impl() {
    stopWorker();
    for (auto& [topic, sub] : imports_) closeSubscription(sub);
    imports_.clear();
    closeSubscription(want_sub_);
    closeSubscription(hello_sub_);
    if (conn_ != nullptr) natsConnection_Close(conn_);
    {
      // The handlers of closed subscriptions may still be running once, and
      // the connection's callbacks run on the library's thread.
      absl::MutexLock lock(&mutex_);
      mutex_.AwaitWithTimeout(absl::Condition(
                                  +[](int* open) { return *open == 0; }, &open_subscriptions_),
                              absl::Seconds(5));
      if (conn_ != nullptr) mutex_.AwaitWithTimeout(absl::Condition(&closed_), absl::Seconds(5));
    }
    if (conn_ != nullptr) natsConnection_Destroy(conn_);
    if (opts_ != nullptr) natsOptions_Destroy(opts_);
  }

  absl::Status connect() {
    natsStatus s = natsOptions_Create(&opts_);
    if (s != NATS_OK) return natsError("nats options", s);
    std::vector<std::string> urls = absl::StrSplit(options_.url, ',', absl::SkipEmpty());
    std::vector<const char*> url_ptrs;
    for (const auto& url : urls) url_ptrs.push_back(url.c_str());
    s = natsOptions_SetServers(opts_, url_ptrs.data(), static_cast<int>(url_ptrs.size()));
    if (s == NATS_OK) s = natsOptions_SetName(opts_, options_.name.c_str());
    if (s == NATS_OK) s = natsOptions_SetNoEcho(opts_, true);
    if (s == NATS_OK) s = natsOptions_SetAllowReconnect(opts_, true);
    if (s == NATS_OK) s = natsOptions_SetMaxReconnect(opts_, -1);
    if (s == NATS_OK) s = natsOptions_SetReconnectWait(opts_, 250);
    if (s == NATS_OK) s = natsOptions_SetReconnectJitter(opts_, 100, 100);
    if (s == NATS_OK) s = natsOptions_SetReconnectBufSize(opts_, options_.reconnect_buffer_bytes);
    if (s == NATS_OK) {
      s = natsOptions_SetPingInterval(opts_, static_cast<int64_t>(options_.ping_interval.count()));
    }
    if (s == NATS_OK) s = natsOptions_SetMaxPingsOut(opts_, options_.max_pings_out);
    if (s == NATS_OK) s = natsOptions_SetTimeout(opts_, 2000);
    if (s == NATS_OK) s = natsOptions_UseGlobalMessageDelivery(opts_, true);
    if (s == NATS_OK) s = natsOptions_SetDisconnectedCB(opts_, &Impl::onDisconnected, this);
    if (s == NATS_OK) s = natsOptions_SetReconnectedCB(opts_, &Impl::onReconnected, this);
    if (s == NATS_OK) s = natsOptions_SetClosedCB(opts_, &Impl::onClosed, this);
    if (s == NATS_OK)
      s = natsOptions_SetRetryOnFailedConnect(opts_, true, &Impl::onConnected, this);
    if (s == NATS_OK && !options_.tls_cert.empty()) {
      s = natsOptions_SetSecure(opts_, true);
      if (s == NATS_OK) s = natsOptions_LoadCATrustedCertificates(opts_, options_.tls_ca.c_str());
      if (s == NATS_OK) {
        s = natsOptions_LoadCertificatesChain(opts_, options_.tls_cert.c_str(),
                                              options_.tls_key.c_str());
      }
      if (s != NATS_OK) {
        return absl::InvalidArgumentError(
            absl::StrCat("the link's TLS files (", options_.tls_cert, ", ", options_.tls_key, ", ",
                         options_.tls_ca, ") cannot be loaded: ", natsStatus_GetText(s), " (",
                         nats_GetLastError(nullptr), ")"));
      }
    }
    if (s != NATS_OK) return natsError("nats options", s);
    // With RetryOnFailedConnect, a server that is not up yet answers
    // NATS_NOT_YET_CONNECTED and the client keeps trying in the background.
    s = natsConnection_Connect(&conn_, opts_);
    if (s == NATS_OK) {
      setUp(true);
    } else if (s != NATS_NOT_YET_CONNECTED) {
      return natsError(absl::StrCat("cannot connect to ", options_.url), s);
    }
    if (absl::Status status = subscribe(kWantWildcard, &Impl::onWant, &want_sub_); !status.ok()) {
      return status;
    }
    if (absl::Status status = subscribe(kHelloSubject, &Impl::onHello, &hello_sub_); !status.ok()) {
      return status;
    }
    worker_ = std::thread([this] { run(); });
    return absl::OkStatus();
  }

  void stopWorker() {
    {
      absl::MutexLock lock(&mutex_);
      stopping_ = true;
    }
    if (worker_.joinable()) worker_.join();
  }

  void localInterestChanged(std::vector<std::string> wanted) {
    wanted.erase(std::remove_if(wanted.begin(), wanted.end(),
                                [this](const std::string& t) { return isLocal(t); }),
                 wanted.end());
    absl::MutexLock lock(&mutex_);
    if (wanted == local_wanted_) return;
    local_wanted_ = std::move(wanted);
    local_changed_ = true;
  }

  void localSample(const std::string& topic, const v1::SubscribeResponse& sample) {
    if (isLocal(topic) || conn_ == nullptr) return;
    thread_local std::string bytes;
    bytes.clear();
    if (!sample.sample().SerializeToString(&bytes)) return;
    if (options_.max_rate_hz > 0) {
      // Held for the next frame (flushFrame); the worker is woken when the
      // first sample of a frame arrives.
      bool first = false;
      {
        absl::MutexLock lock(&thin_mutex_);
        std::optional<std::string>& held = held_[topic];
        if (held) thinned_count_.Increment();
        held = bytes;
        first = !frame_pending_;
        frame_pending_ = true;
      }
      if (first) {
        absl::MutexLock lock(&mutex_);
        thinned_pending_ = true;
      }
      return;
    }
    send(topic, bytes);
  }

 private:
  void send(const std::string& topic, const std::string& bytes) {
    const natsStatus s = natsConnection_Publish(conn_, topicSubject(topic).c_str(), bytes.data(),
                                                static_cast<int>(bytes.size()));
    if (s != NATS_OK) {
      dropped_.Increment();
      return;
    }
    topicCounter(samples_out_, &out_counters_, topic).Increment();
    bytes_out_.Increment(static_cast<double>(bytes.size()));
  }

  // Worker, with max_rate_hz: at most once per interval, sends one frame,
  // the newest held sample of every topic, published back to back so that
  // the client writes them together (on a radio, one segment and one
  // acknowledgement instead of one per sample). A frame goes at once when
  // the previous one is an interval old, else when it is. Returns when the
  // next frame is due (max: nothing held).
  std::chrono::steady_clock::time_point flushFrame() {
    std::vector<std::pair<std::string, std::string>> frame;
    {
      absl::MutexLock lock(&thin_mutex_);
      if (!frame_pending_) return std::chrono::steady_clock::time_point::max();
      const auto now = std::chrono::steady_clock::now();
      if (now - last_frame_ < interval_) return last_frame_ + interval_;
      last_frame_ = now;
      frame_pending_ = false;
      for (auto& [topic, held] : held_) {
        if (!held) continue;
        frame.emplace_back(topic, std::move(*held));
        held.reset();
      }
    }
    for (const auto& [topic, bytes] : frame) send(topic, bytes);
    if (!frame.empty()) frames_.Increment();
    return std::chrono::steady_clock::time_point::max();
  }

  // ---- NATS callbacks (the library's threads) ------------------------------
  static void onSample(natsConnection* /*nc*/, natsSubscription* /*sub*/, natsMsg* msg,
                       void* closure) {
    static_cast<Impl*>(closure)->takeSample(msg);
    natsMsg_Destroy(msg);
  }
  static void onWant(natsConnection* /*nc*/, natsSubscription* /*sub*/, natsMsg* msg,
                     void* closure) {
    static_cast<Impl*>(closure)->takeWant(msg);
    natsMsg_Destroy(msg);
  }
  static void onHello(natsConnection* /*nc*/, natsSubscription* /*sub*/, natsMsg* msg,
                      void* closure) {
    auto* self = static_cast<Impl*>(closure);
    absl::MutexLock lock(&self->mutex_);
    self->announce_now_ = true;
    natsMsg_Destroy(msg);
  }
  static void onSubscriptionComplete(void* closure) {
    auto* self = static_cast<Impl*>(closure);
    absl::MutexLock lock(&self->mutex_);
    --self->open_subscriptions_;
  }
  static void onConnected(natsConnection* /*nc*/, void* closure) {
    static_cast<Impl*>(closure)->setUp(true);
  }
  static void onReconnected(natsConnection* /*nc*/, void* closure) {
    static_cast<Impl*>(closure)->setUp(true);
  }
  static void onDisconnected(natsConnection* /*nc*/, void* closure) {
    auto* self = static_cast<Impl*>(closure);
    if (self->up_.exchange(false)) self->disconnects_.Increment();
    self->up_gauge_.Set(0);
  }
  static void onClosed(natsConnection* /*nc*/, void* closure) {
    auto* self = static_cast<Impl*>(closure);
    self->up_.store(false);
    self->up_gauge_.Set(0);
    absl::MutexLock lock(&self->mutex_);
    self->closed_ = true;  // the last callback of the connection
  }

  void setUp(bool up) {
    up_.store(up);
    up_gauge_.Set(up ? 1 : 0);
    if (!up) return;
    // (Re)connected: say what this host wants and ask the others for theirs.
    absl::MutexLock lock(&mutex_);
    announce_now_ = true;
    hello_now_ = true;
  }

  void takeSample(natsMsg* msg) {
    const std::optional<std::string> topic = subjectTopic(natsMsg_GetSubject(msg));
    google::protobuf::Any sample;
    const int length = natsMsg_GetDataLength(msg);
    if (!topic || isLocal(*topic) || !sample.ParseFromArray(natsMsg_GetData(msg), length)) {
      rejected_.Increment();
      return;
    }
    if (!broker_.publishRemote(*topic, std::move(sample)).ok()) {
      rejected_.Increment();
      return;
    }
    topicCounter(samples_in_, &in_counters_, *topic).Increment();
    bytes_in_.Increment(static_cast<double>(length));
  }

  void takeWant(natsMsg* msg) {
    absl::string_view subject = natsMsg_GetSubject(msg);
    if (!absl::ConsumePrefix(&subject, kWantPrefix) || subject == options_.name ||
        !validName(subject)) {
      return;
    }
    v1::WatchInterestResponse announced;
    if (!announced.ParseFromArray(natsMsg_GetData(msg), natsMsg_GetDataLength(msg))) return;
    std::vector<std::string> wanted;
    for (const std::string& topic : announced.wanted_topics()) {
      if (wanted.size() >= options_.max_wanted_per_peer) break;
      if (validateTopicName(topic).ok() && !isLocal(topic)) wanted.push_back(topic);
    }
    std::sort(wanted.begin(), wanted.end());
    absl::MutexLock lock(&mutex_);
    auto it = peers_.find(subject);
    if (it == peers_.end()) {
      if (peers_.size() >= options_.max_peers) return;
      it = peers_.emplace(std::string(subject), Peer{}).first;
      peers_changed_ = true;
    }
    it->second.heard = std::chrono::steady_clock::now();
    if (it->second.wanted != wanted) {
      it->second.wanted = std::move(wanted);
      peers_changed_ = true;
    }
  }

  // ---- the worker: imports, announcements, remote wants --------------------
  void run() {
    auto next_announce = std::chrono::steady_clock::now();
    absl::MutexLock lock(&mutex_);
    while (!stopping_) {
      const auto now = std::chrono::steady_clock::now();
      // Another broker whose announcements stopped (its host or its link
      // went) no longer wants anything.
      for (auto it = peers_.begin(); it != peers_.end();) {
        if (now - it->second.heard > options_.want_ttl) {
          it = peers_.erase(it);
          peers_changed_ = true;
        } else {
          ++it;
        }
      }
      const bool announce = local_changed_ || announce_now_ || now >= next_announce;
      const bool hello = hello_now_;
      std::optional<std::vector<std::string>> imports;
      if (local_changed_) imports = local_wanted_;
      std::optional<std::vector<std::string>> remote;
      std::size_t peers = 0;
      std::size_t wants = 0;
      if (peers_changed_) {
        std::set<std::string> all;
        for (const auto& [name, peer] : peers_) {
          all.insert(peer.wanted.begin(), peer.wanted.end());
          wants += peer.wanted.size();
        }
        remote.emplace(all.begin(), all.end());
        peers = peers_.size();
      }
      v1::WatchInterestResponse announcement;
      if (announce) {
        for (const auto& topic : local_wanted_) announcement.add_wanted_topics(topic);
      }
      local_changed_ = announce_now_ = hello_now_ = peers_changed_ = false;

      mutex_.Unlock();
      if (imports) updateImports(*imports);
      if (remote) {
        broker_.setRemoteWanted(std::move(*remote));
        // After the broker has them: a reader of these gauges may count on
        // the samples of what it sees wanted being sent.
        peers_gauge_.Set(static_cast<double>(peers));
        wants_gauge_.Set(static_cast<double>(wants));
      }
      if (announce) {
        const std::string bytes = announcement.SerializeAsString();
        (void)natsConnection_Publish(conn_, absl::StrCat(kWantPrefix, options_.name).c_str(),
                                     bytes.data(), static_cast<int>(bytes.size()));
        next_announce = std::chrono::steady_clock::now() + options_.announce_period;
      }
      if (hello) (void)natsConnection_Publish(conn_, kHelloSubject, "", 0);
      mutex_.Lock();

      auto wake = next_announce;
      for (const auto& [name, peer] : peers_) wake = std::min(wake, peer.heard + options_.want_ttl);
      if (options_.max_rate_hz > 0) {
        thinned_pending_ = false;
        mutex_.Unlock();
        const auto next_held = flushFrame();
        mutex_.Lock();
        wake = std::min(wake, next_held);
      }
      const auto wait = std::max(wake - std::chrono::steady_clock::now(),
                                 std::chrono::steady_clock::duration(std::chrono::milliseconds(1)));
      mutex_.AwaitWithTimeout(absl::Condition(this, &Impl::hasWorkLocked), absl::FromChrono(wait));
    }
  }

  bool hasWorkLocked() const ABSL_EXCLUSIVE_LOCKS_REQUIRED(mutex_) {
    return stopping_ || local_changed_ || announce_now_ || hello_now_ || peers_changed_ ||
           thinned_pending_;
  }

  // Worker thread only: subscribes on NATS to what this host wants.
  void updateImports(const std::vector<std::string>& wanted) {
    const std::set<std::string> want(wanted.begin(), wanted.end());
    for (auto it = imports_.begin(); it != imports_.end();) {
      if (want.count(it->first) == 0) {
        closeSubscription(it->second);
        it = imports_.erase(it);
      } else {
        ++it;
      }
    }
    for (const auto& topic : want) {
      if (imports_.count(topic) != 0) continue;
      natsSubscription* sub = nullptr;
      if (subscribe(topicSubject(topic).c_str(), &Impl::onSample, &sub).ok()) {
        imports_.emplace(topic, sub);
      }
    }
  }

  absl::Status subscribe(const char* subject, natsMsgHandler handler, natsSubscription** sub) {
    natsStatus s = natsConnection_Subscribe(sub, conn_, subject, handler, this);
    if (s != NATS_OK) return natsError(absl::StrCat("cannot subscribe to ", subject), s);
    {
      absl::MutexLock lock(&mutex_);
      ++open_subscriptions_;
    }
    s = natsSubscription_SetOnCompleteCB(*sub, &Impl::onSubscriptionComplete, this);
    if (s != NATS_OK) {
      absl::MutexLock lock(&mutex_);
      --open_subscriptions_;
    }
    return absl::OkStatus();
  }

  static void closeSubscription(natsSubscription*& sub) {
    if (sub == nullptr) return;
    (void)natsSubscription_Unsubscribe(sub);
    natsSubscription_Destroy(sub);
    sub = nullptr;
  }

  bool isLocal(absl::string_view topic) const {
    for (const auto& prefix : options_.local_prefixes) {
      if (absl::StartsWith(topic, prefix)) return true;
    }
    return false;
  }

  static bool validName(absl::string_view name) {
    return !name.empty() && name.size() <= 64 && std::all_of(name.begin(), name.end(), nameCharOk);
  }

  using Counters = std::map<std::string, prometheus::Counter*, std::less<>>;
  prometheus::Counter& topicCounter(prometheus::Family<prometheus::Counter>& family,
                                    Counters* counters, const std::string& topic) {
    absl::MutexLock lock(&counters_mutex_);
    auto it = counters->find(topic);
    if (it == counters->end()) {
      it = counters->emplace(topic, &family.Add({{"topic", topic}})).first;
    }
    return *it->second;
  }

  struct Peer {
    std::vector<std::string> wanted;
    std::chrono::steady_clock::time_point heard;
  };

  Broker& broker_;
  const NatsLinkOptions options_;
  prometheus::Family<prometheus::Counter>& samples_in_;
  prometheus::Family<prometheus::Counter>& samples_out_;
  prometheus::Counter& bytes_in_;
  prometheus::Counter& bytes_out_;
  prometheus::Counter& dropped_;
  prometheus::Counter& rejected_;
  prometheus::Gauge& up_gauge_;
  prometheus::Gauge& peers_gauge_;
  prometheus::Gauge& wants_gauge_;
  prometheus::Counter& disconnects_;
  prometheus::Counter& thinned_count_;
  prometheus::Counter& frames_;
  const std::chrono::steady_clock::duration interval_;

  // Set in connect(), before any callback or the worker; read-only after.
  natsOptions* opts_ = nullptr;
  natsConnection* conn_ = nullptr;
  natsSubscription* want_sub_ = nullptr;
  natsSubscription* hello_sub_ = nullptr;
  std::atomic<bool> up_{false};

  absl::Mutex mutex_;
  std::vector<std::string> local_wanted_ ABSL_GUARDED_BY(mutex_);
  bool local_changed_ ABSL_GUARDED_BY(mutex_) = false;
  bool announce_now_ ABSL_GUARDED_BY(mutex_) = false;
  bool hello_now_ ABSL_GUARDED_BY(mutex_) = false;
  bool peers_changed_ ABSL_GUARDED_BY(mutex_) = false;
  bool stopping_ ABSL_GUARDED_BY(mutex_) = false;
  bool thinned_pending_ ABSL_GUARDED_BY(mutex_) = false;  // a frame has begun
  bool closed_ ABSL_GUARDED_BY(mutex_) = false;
  std::map<std::string, Peer, std::less<>> peers_ ABSL_GUARDED_BY(mutex_);

  // --max-rate-hz: the newest sample of each topic waiting for the next
  // frame, and when the last frame went.
  absl::Mutex thin_mutex_;
  std::map<std::string, std::optional<std::string>, std::less<>> held_ ABSL_GUARDED_BY(thin_mutex_);
  bool frame_pending_ ABSL_GUARDED_BY(thin_mutex_) = false;  // a sample is held
  std::chrono::steady_clock::time_point last_frame_ ABSL_GUARDED_BY(thin_mutex_);
  int open_subscriptions_ ABSL_GUARDED_BY(mutex_) = 0;

  absl::Mutex counters_mutex_;
  Counters in_counters_ ABSL_GUARDED_BY(counters_mutex_);
  Counters out_counters_ ABSL_GUARDED_BY(counters_mutex_);

  std::map<std::string, natsSubscription*> imports_;  // the worker's (and the destructor's)
  std::thread worker_;
};

// ---------------------------------------------------------------------------

absl::StatusOr<std::unique_ptr<NatsLink>> NatsLink::start(Broker& broker, NatsLinkOptions options,
                                                          prometheus::Registry& registry) {
  if (options.url.empty()) return absl::InvalidArgumentError("the link needs a NATS server URL");
  if (options.name.empty() || options.name.size() > 64 ||
      !std::all_of(options.name.begin(), options.name.end(), nameCharOk)) {
    return absl::InvalidArgumentError(
        absl::StrCat("the link's name '", options.name,
                     "' must be 1 to 64 letters, digits, '_' or '-' (it names a NATS subject)"));
  }
  const int tls_files =
      !options.tls_cert.empty() + !options.tls_key.empty() + !options.tls_ca.empty();
  if (tls_files != 0 && tls_files != 3) {
    return absl::InvalidArgumentError(
        "the link's mutual TLS needs a certificate, its key and a CA, all three");
  }
  if (!(options.max_rate_hz >= 0 && options.max_rate_hz <= 10'000)) {
    return absl::InvalidArgumentError("the link's max rate must be within [0, 10000] Hz");
  }
  if (options.announce_period <= std::chrono::milliseconds(0) ||
      options.want_ttl <= options.announce_period) {
    return absl::InvalidArgumentError(
        "the link's announcement time to live must be longer than its period");
  }
  Broker* broker_ptr = &broker;
  auto impl = std::make_unique<Impl>(broker, std::move(options), registry);
  if (absl::Status status = impl->connect(); !status.ok()) return status;
  std::unique_ptr<NatsLink> link(new NatsLink(std::move(impl)));
  link->broker_ = broker_ptr;
  broker.attachLink(link.get());
  return link;
}

NatsLink::NatsLink(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}

NatsLink::~NatsLink() {
  // The worker stops first, so that it hands the broker nothing more; once
  // detached, the broker calls the link no more (attachLink waits for the
  // calls under way).
  impl_->stopWorker();
  if (broker_ != nullptr) {
    broker_->attachLink(nullptr);
    broker_->setRemoteWanted({});
  }
  impl_.reset();
}

void NatsLink::localInterestChanged(std::vector<std::string> wanted) {
  impl_->localInterestChanged(std::move(wanted));
}

void NatsLink::localSample(const std::string& topic, const v1::SubscribeResponse& sample) {
  impl_->localSample(topic, sample);
}

}  // namespace behaviorlib::channel
