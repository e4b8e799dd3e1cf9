#pragma once

// Client of the common data channel (behaviorlib.v1.DataChannel).
//
//   behaviorlib::channel::ChannelClient channel("127.0.0.1:50051");
//
//   // Publish: one stream per client, opened on first use.
//   behaviorlib::v1::PoseStamped pose = ...;
//   absl::Status s = channel.publish("robots/drone1/pose", pose);
//
//   // Subscribe: a background reader that reconnects until destroyed.
//   auto sub = channel.subscribeTyped<behaviorlib::v1::PoseStamped>(
//       "robots/drone1/pose", {.mode = behaviorlib::v1::DELIVERY_MODE_LATEST},
//       [](const behaviorlib::v1::PoseStamped& p) { ... });
//   sub.reset();  // cancels the stream and joins the reader
//
//   // The newest sample, or NOT_FOUND.
//   absl::StatusOr<behaviorlib::v1::SubscribeResponse> latest =
//       channel.getLatest("robots/drone1/pose");

#include <chrono>
#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "behaviorlib/v1/channel.pb.h"

namespace google::protobuf {
class Message;
}  // namespace google::protobuf

namespace behaviorlib::channel {

/// How a subscription is buffered by the broker (see SubscribeRequest).
struct SubscribeOptions {
  /// LATEST keeps only the newest undelivered sample; QUEUE keeps up to
  /// queue_size and drops the oldest.
  v1::DeliveryMode mode = v1::DELIVERY_MODE_LATEST;
  /// Queue length for QUEUE mode, 1..10000; 0 means the broker default (100).
  uint32_t queue_size = 0;
  /// Deliver the sample already on the topic first (also after every
  /// reconnection).
  bool send_latest_first = false;
  /// Read the samples from the broker's shared-memory ring when the broker
  /// offers one (it runs on this host): one copy for every subscriber on the
  /// host instead of a stream each (decision 20). Otherwise, or when the
  /// ring cannot be opened here, samples come on the stream.
  bool shared_memory = true;
  /// At most this many samples a second of wall time, the newest each time
  /// and always the last (SubscribeRequest.max_rate_hz); 0: every sample.
  /// An observer's rate: the broker and a gating publisher then carry only
  /// that much for this reader. A rate-limited subscription is not waited
  /// for by delivered().
  double max_rate_hz = 0;
};

/// A running subscription, made by ChannelClient::subscribe. Its reader
/// thread calls the callback for every sample and reconnects (with backoff
/// from 100 ms to 2 s) whenever the stream ends, until the Subscription is
/// destroyed. It only gives up when the broker refuses the request itself
/// (INVALID_ARGUMENT, e.g. a bad topic name): see status().
class Subscription {
 public:
  class Impl;
  explicit Subscription(std::shared_ptr<Impl> impl);
  /// Cancels the stream and joins the reader thread (promptly). Must not be
  /// called from inside the callback.
  ~Subscription();
  Subscription(const Subscription&) = delete;
  Subscription& operator=(const Subscription&) = delete;

  /// True while a stream is established and registered at the broker (from
  /// then on every published sample reaches this subscription).
  bool connected() const;
  /// Waits until connected() (true) or `timeout` passes (false).
  bool waitConnected(std::chrono::milliseconds timeout) const;
  /// Streams established so far (1 after the first connection; grows with
  /// every reconnection).
  uint64_t connectCount() const;
  /// Samples delivered to the callback so far.
  uint64_t receivedCount() const;
  /// The topic subscribed to.
  const std::string& topic() const;
  /// The topic_seq of the newest sample whose callback has returned (0
  /// before the first).
  uint64_t processedSeq() const;
  /// Why the last stream ended (OK while the first one is running). When
  /// the broker refused the request (INVALID_ARGUMENT), the subscription has
  /// stopped for good.
  absl::Status status() const;

 private:
  std::shared_ptr<Impl> impl_;
};

/// Which topics under a prefix someone wants (DataChannel.WatchInterest),
/// for a publisher that publishes only those: made by
/// ChannelClient::watchInterest, its reader thread reconnects like a
/// Subscription's. Until the broker's first answer, and whenever the stream
/// is down, every topic counts as wanted (the publisher then publishes
/// everything, as without a watch). Thread-safe.
class InterestWatch {
 public:
  class Impl;
  explicit InterestWatch(std::shared_ptr<Impl> impl);
  /// Cancels the stream and joins the reader thread.
  ~InterestWatch();
  InterestWatch(const InterestWatch&) = delete;
  InterestWatch& operator=(const InterestWatch&) = delete;

  /// Whether `topic` is wanted now (true while the set is not known, and for
  /// a topic outside the prefix).
  bool wanted(const std::string& topic) const;
  /// Whether the broker's wanted set is known (the stream is up).
  bool known() const;
  /// The wanted topics under the prefix (sorted; empty while not known).
  std::vector<std::string> wantedTopics() const;
  /// The rate `topic` is wanted at (WatchInterestResponse.max_rate_hz), in
  /// samples a second of wall time; 0 when every sample is wanted, or the
  /// set is not known, or the topic is not wanted.
  double maxRateHz(const std::string& topic) const;

 private:
  std::shared_ptr<Impl> impl_;
};

/// A connection to a channel broker. Thread-safe.
class ChannelClient {
 public:
  /// `address` is "host:port"; the gRPC channel is created here and connects
  /// lazily.
  explicit ChannelClient(const std::string& address);
  /// Closes the publish stream (half-close, waits for the broker's reply).
  /// Subscriptions made by this client keep working until they are destroyed.
  ~ChannelClient();
  ChannelClient(const ChannelClient&) = delete;
  ChannelClient& operator=(const ChannelClient&) = delete;

  const std::string& address() const;

  /// Publishes `sample` (packed into an Any) on `topic`. Uses one Publish
  /// stream per client, opened on first use and reopened after a failure.
  /// Returns INVALID_ARGUMENT at once for a bad topic name. A stream is
  /// asynchronous: when the broker refuses a sample (wrong type for the
  /// topic, ...) it ends the stream, and the refusal is returned by a later
  /// publish() (whose own sample was then not sent) or flush(). When the
  /// broker went away, the sample is retried once on a new stream.
  absl::Status publish(const std::string& topic, const google::protobuf::Message& sample);

  /// One sample of publishAll(); `sample` must stay valid during the call.
  struct TopicSample {
    std::string topic;
    const google::protobuf::Message* sample = nullptr;
  };
  /// Publishes `samples` in order as one batch (one message on the publish
  /// stream, PublishRequest.more): one write and one broker read for all of
  /// them. Each sample is numbered, checked and delivered as if published
  /// alone; otherwise as publish(). An empty batch does nothing.
  absl::Status publishAll(const std::vector<TopicSample>& samples);
  /// publishAll() and sync() in one round trip: the batch carries the sync
  /// request (PublishRequest.sync), and the broker answers once it took it.
  /// An empty batch is sync().
  absl::Status publishAllAndSync(const std::vector<TopicSample>& samples);

  /// Closes the publish stream and returns the number of samples the broker
  /// accepted on it, or the status it ended with. The next publish() opens
  /// a new stream.
  absl::StatusOr<uint64_t> flush();

  /// Returns once every sample published by this client so far has been
  /// accepted by the broker (one round trip on the open stream,
  /// DataChannel.PublishAcked; skipped when nothing was published since the
  /// last one); the deterministic mode's barrier. A refused sample or a
  /// broker gone ends the stream, and sync() returns why.
  absl::Status sync();
  /// With `buffer`, a publish may wait in the stream's buffer (gRPC's
  /// buffer hint: no write to the socket of its own) until the next sync()
  /// takes everything out at once. For a publisher that syncs before anyone
  /// may read what it published: a deterministic-mode follower, whose report
  /// comes after its sync.
  void bufferUntilSync(bool buffer);

  /// The topic_seq of the last sample this client published on each topic,
  /// as the broker reported at the last sync() or flush(); emptied when a
  /// stream failed (a restarted broker numbers anew).
  std::map<std::string, uint64_t> acceptedSeqs() const;

  /// Whether every connected subscription made by this client has processed
  /// the sample numbered `topic_seqs[topic]` on its topic, or a later one
  /// (topics not in the map, and subscriptions not connected, count as
  /// done); the deterministic mode's data barrier.
  bool delivered(const std::function<uint64_t(const std::string& topic)>& topic_seq) const;
  /// The topics delivered() looks at (its live subscriptions' that are not
  /// rate-limited, connected or not), sorted, each once.
  std::vector<std::string> awaitedTopics() const;
  /// Waits until delivered(topic_seq) (true) or `timeout` passes (false);
  /// woken by the subscriptions' progress, not by polling.
  bool waitDelivered(const std::function<uint64_t(const std::string& topic)>& topic_seq,
                     std::chrono::milliseconds timeout) const;

  /// The newest sample on `topic`; NOT_FOUND when nothing was published yet.
  absl::StatusOr<v1::SubscribeResponse> getLatest(
      const std::string& topic, std::chrono::milliseconds timeout = std::chrono::seconds(5));

  /// The broker's topics (sorted), optionally only those starting with
  /// `prefix`: every page of ListTopics, within `timeout` in all.
  absl::StatusOr<std::vector<v1::TopicInfo>> listTopics(
      const std::string& prefix = "", std::chrono::milliseconds timeout = std::chrono::seconds(5));

  /// Subscribes to `topic`; `on_sample` runs on the subscription's reader
  /// thread, one sample at a time, and should return quickly (a slow
  /// callback makes the broker drop samples for this subscription).
  std::unique_ptr<Subscription> subscribe(
      const std::string& topic, SubscribeOptions options,
      std::function<void(const v1::SubscribeResponse&)> on_sample);

  /// Declares to the broker that this client publishes the topics under
  /// `prefix` only while they are wanted (see watchInterest): the broker then
  /// keeps no sample of one nobody wants, and a GetLatest of it waits for
  /// the next. Applies from the next publish stream (the current one is
  /// closed).
  void gatePublishing(const std::string& prefix);

  /// Watches which topics starting with `prefix` are wanted. `on_change`
  /// runs on the watch's reader thread after every change of the wanted set
  /// (or of whether it is known).
  std::unique_ptr<InterestWatch> watchInterest(const std::string& prefix,
                                               std::function<void()> on_change);

  /// Like subscribe(), unpacking each sample as T; samples of another type
  /// are skipped.
  template <class T>
  std::unique_ptr<Subscription> subscribeTyped(const std::string& topic, SubscribeOptions options,
                                               std::function<void(const T&)> on_sample) {
    return subscribe(topic, options,
                     [on_sample = std::move(on_sample)](const v1::SubscribeResponse& response) {
                       T message;
                       if (response.sample().UnpackTo(&message)) on_sample(message);
                     });
  }

 private:
  class Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace behaviorlib::channel
