// Integration tests of the channel_broker binary: started as a real process on
// free loopback ports, driven over gRPC (raw stubs and ChannelClient).

#include <dirent.h>
#include <fcntl.h>
#include <gmock/gmock.h>
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>
#include <signal.h>
#include <spawn.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <fstream>
#include <functional>
#include <map>
#include <mutex>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "absl/synchronization/mutex.h"
#include "behaviorlib/channel/channel_client.h"
#include "behaviorlib/channel/shm_ring.h"
#include "behaviorlib/channel/sim_clock.h"
#include "behaviorlib/channel/topic.h"
#include "behaviorlib/error_details.h"
#include "behaviorlib/server_kit/server_runtime.h"
#include "behaviorlib/v1/channel.grpc.pb.h"
#include "behaviorlib/v1/types.pb.h"
#include "support/server_process.h"

extern char** environ;

namespace behaviorlib::channel {
namespace {

using std::chrono::milliseconds;
using std::chrono::seconds;
using ::testing::HasSubstr;

const char* const kBrokerPath = CHANNEL_BROKER_PATH;

// Polls `condition` until true or `timeout`.
template <class F>
bool eventually(F condition, std::chrono::milliseconds timeout = seconds(10)) {
  const auto deadline = std::chrono::steady_clock::now() + timeout;
  while (std::chrono::steady_clock::now() < deadline) {
    if (condition()) return true;
    std::this_thread::sleep_for(milliseconds(10));
  }
  return condition();
}

std::shared_ptr<grpc::Channel> makeChannel(const std::string& address, bool small_window = false) {
  grpc::ChannelArguments args;
  // Each channel gets its own connection, so that one stream's flow control
  // cannot interfere with another's.
  args.SetInt(GRPC_ARG_USE_LOCAL_SUBCHANNEL_POOL, 1);
  if (small_window) {
    // A reader that does not read stalls the broker's writes as soon as the
    // default 64 KiB stream window is full; without BDP probing the window
    // does not grow.
    args.SetInt(GRPC_ARG_HTTP2_BDP_PROBE, 0);
  }
  return grpc::CreateCustomChannel(address, grpc::InsecureChannelCredentials(), args);
}

v1::SubscribeRequest subscribeRequest(const std::string& topic,
                                      v1::DeliveryMode mode = v1::DELIVERY_MODE_QUEUE,
                                      uint32_t queue_size = 0, bool send_latest_first = false) {
  v1::SubscribeRequest request;
  request.set_topic(topic);
  request.set_mode(mode);
  request.set_queue_size(queue_size);
  request.set_send_latest_first(send_latest_first);
  return request;
}

v1::Text text(const std::string& s) {
  v1::Text t;
  t.set_text(s);
  return t;
}

v1::Clock clockSample(int64_t sec, double time_scale = 1.0) {
  v1::Clock c;
  c.mutable_time()->set_seconds(sec);
  *c.mutable_header()->mutable_stamp() = c.time();
  c.set_time_scale(time_scale);
  return c;
}

v1::PublishRequest publishRequest(const std::string& topic, const google::protobuf::Message& m) {
  v1::PublishRequest request;
  request.set_topic(topic);
  request.mutable_sample()->PackFrom(m);
  return request;
}

// A raw Publish stream.
class RawPublisher {
 public:
  explicit RawPublisher(const std::shared_ptr<grpc::Channel>& channel)
      : stub_(v1::DataChannel::NewStub(channel)) {
    context_.set_deadline(std::chrono::system_clock::now() + seconds(60));
    writer_ = stub_->Publish(&context_, &response_);
  }
  bool write(const v1::PublishRequest& request) { return writer_->Write(request); }
  bool write(const std::string& topic, const google::protobuf::Message& m) {
    return write(publishRequest(topic, m));
  }
  grpc::Status finish() {
    writer_->WritesDone();
    return writer_->Finish();
  }
  uint64_t accepted() const { return response_.accepted_count(); }

 private:
  std::unique_ptr<v1::DataChannel::Stub> stub_;
  grpc::ClientContext context_;
  v1::PublishResponse response_;
  std::unique_ptr<grpc::ClientWriter<v1::PublishRequest>> writer_;
};

// Publishes one sample on a fresh stream and returns the stream's status.
grpc::Status publishOnce(const std::shared_ptr<grpc::Channel>& channel,
                         const v1::PublishRequest& request) {
  RawPublisher publisher(channel);
  publisher.write(request);
  return publisher.finish();
}

// A raw Subscribe stream.
class RawSubscriber {
 public:
  RawSubscriber(const std::shared_ptr<grpc::Channel>& channel, const v1::SubscribeRequest& request,
                std::chrono::milliseconds deadline = seconds(60))
      : stub_(v1::DataChannel::NewStub(channel)) {
    context_.set_deadline(std::chrono::system_clock::now() + deadline);
    reader_ = stub_->Subscribe(&context_, request);
  }
  // True once the broker registered the subscription.
  bool waitSubscribed() {
    reader_->WaitForInitialMetadata();
    return context_.GetServerInitialMetadata().count(kSubscribedMetadataKey) > 0;
  }
  bool read(v1::SubscribeResponse* response) { return reader_->Read(response); }
  grpc::Status finish() { return reader_->Finish(); }
  void cancel() { context_.TryCancel(); }

 private:
  std::unique_ptr<v1::DataChannel::Stub> stub_;
  grpc::ClientContext context_;
  std::unique_ptr<grpc::ClientReader<v1::SubscribeResponse>> reader_;
};

class ChannelBrokerTest : public ::testing::Test {
 protected:
  void SetUp() override {
    ASSERT_TRUE(broker_.start()) << broker_.error();
    channel_ = makeChannel(broker_.address());
    stub_ = v1::DataChannel::NewStub(channel_);
  }

  grpc::Status getLatest(const std::string& topic, v1::GetLatestResponse* response) {
    grpc::ClientContext context;
    context.set_deadline(std::chrono::system_clock::now() + seconds(5));
    v1::GetLatestRequest request;
    request.set_topic(topic);
    return stub_->GetLatest(&context, request, response);
  }

  v1::ListTopicsResponse listTopics(const std::string& prefix = "") {
    grpc::ClientContext context;
    context.set_deadline(std::chrono::system_clock::now() + seconds(5));
    v1::ListTopicsRequest request;
    request.set_prefix(prefix);
    v1::ListTopicsResponse response;
    EXPECT_TRUE(stub_->ListTopics(&context, request, &response).ok());
    return response;
  }

  support::ServerProcess broker_{kBrokerPath, {}};
  std::shared_ptr<grpc::Channel> channel_;
  std::unique_ptr<v1::DataChannel::Stub> stub_;
};

TEST_F(ChannelBrokerTest, PublishSubscribeRoundTrip) {
  RawSubscriber subscriber(channel_, subscribeRequest("robots/d1/imu"));
  ASSERT_TRUE(subscriber.waitSubscribed());

  RawPublisher publisher(channel_);
  for (int i = 0; i < 3; ++i) {
    v1::Imu imu;
    imu.mutable_header()->set_seq(static_cast<uint64_t>(i));
    imu.mutable_angular_velocity_rad_s()->set_z(0.5 * i);
    ASSERT_TRUE(publisher.write("robots/d1/imu", imu));
  }
  for (uint64_t i = 0; i < 3; ++i) {
    v1::SubscribeResponse response;
    ASSERT_TRUE(subscriber.read(&response));
    EXPECT_EQ(response.topic(), "robots/d1/imu");
    EXPECT_EQ(response.topic_seq(), i + 1);
    EXPECT_EQ(response.dropped_count(), 0u);
    EXPECT_GT(response.receive_time().seconds(), 0);
    v1::Imu imu;
    ASSERT_TRUE(response.sample().UnpackTo(&imu));
    EXPECT_EQ(imu.header().seq(), i);
    EXPECT_DOUBLE_EQ(imu.angular_velocity_rad_s().z(), 0.5 * static_cast<double>(i));
  }
  ASSERT_TRUE(publisher.finish().ok());
  EXPECT_EQ(publisher.accepted(), 3u);
  subscriber.cancel();
  EXPECT_EQ(subscriber.finish().error_code(), grpc::StatusCode::CANCELLED);
}

// A subscriber that does not read loses samples (counted) instead of slowing
// the publisher or a fast subscriber.
TEST_F(ChannelBrokerTest, SlowSubscriberDropsWithoutBlockingPublisherOrOthers) {
  constexpr int kSamples = 1000;
  constexpr uint32_t kSlowQueue = 10;
  const std::string topic = "robots/d1/camera";
  // Each sample is larger than the slow reader's flow-control window, so
  // that the transport cannot hide the reader's slowness: the broker's
  // first write to it stalls and everything else goes through its queue.
  v1::Image image;
  image.set_encoding("mono8");
  image.set_data(std::string(100 * 1024, 'x'));

  RawSubscriber slow(makeChannel(broker_.address(), /*small_window=*/true),
                     subscribeRequest(topic, v1::DELIVERY_MODE_QUEUE, kSlowQueue));
  ASSERT_TRUE(slow.waitSubscribed());
  RawSubscriber fast(makeChannel(broker_.address()),
                     subscribeRequest(topic, v1::DELIVERY_MODE_QUEUE, kMaxQueueSize));
  ASSERT_TRUE(fast.waitSubscribed());

  std::vector<uint64_t> fast_seqs;
  uint64_t fast_dropped = 0;
  std::thread fast_reader([&] {
    v1::SubscribeResponse response;
    while (fast_seqs.size() < kSamples && fast.read(&response)) {
      fast_seqs.push_back(response.topic_seq());
      fast_dropped = response.dropped_count();
    }
  });

  const auto start = std::chrono::steady_clock::now();
  RawPublisher publisher(makeChannel(broker_.address()));
  for (int i = 0; i < kSamples; ++i) {
    image.mutable_header()->set_seq(static_cast<uint64_t>(i));
    ASSERT_TRUE(publisher.write(topic, image)) << "sample " << i;
  }
  ASSERT_TRUE(publisher.finish().ok());
  EXPECT_EQ(publisher.accepted(), static_cast<uint64_t>(kSamples));
  const auto publish_time = std::chrono::steady_clock::now() - start;
  fast_reader.join();

  ASSERT_EQ(fast_seqs.size(), static_cast<size_t>(kSamples));
  for (int i = 0; i < kSamples; ++i) EXPECT_EQ(fast_seqs[i], static_cast<uint64_t>(i + 1));
  EXPECT_EQ(fast_dropped, 0u);
  EXPECT_LT(publish_time, seconds(30));

  // Now the slow subscriber reads what it was left with: the newest samples,
  // with the loss counted.
  std::vector<uint64_t> slow_seqs;
  uint64_t slow_dropped = 0;
  v1::SubscribeResponse response;
  while (slow.read(&response)) {
    slow_seqs.push_back(response.topic_seq());
    EXPECT_GE(response.dropped_count(), slow_dropped) << "dropped_count is cumulative";
    slow_dropped = response.dropped_count();
    if (response.topic_seq() == kSamples) break;
  }
  ASSERT_FALSE(slow_seqs.empty());
  EXPECT_EQ(slow_seqs.back(), static_cast<uint64_t>(kSamples));
  EXPECT_LE(slow_seqs.size(), kSlowQueue + 1u);
  EXPECT_GE(slow_dropped, kSamples - kSlowQueue);
  EXPECT_EQ(slow_seqs.size() + slow_dropped, static_cast<size_t>(kSamples));
  slow.cancel();
  fast.cancel();
  slow.finish();
  fast.finish();
}

// Concurrent publishers on one topic while subscriptions come and go: a
// steady subscriber sees every sample once, in topic_seq order.
TEST_F(ChannelBrokerTest, ConcurrentPublishersAndSubscriberChurn) {
  constexpr int kPublishers = 4;
  constexpr int kPerPublisher = 2000;
  constexpr uint64_t kTotal = kPublishers * kPerPublisher;
  const std::string topic = "robots/d6/chatter";
  RawSubscriber steady(makeChannel(broker_.address()),
                       subscribeRequest(topic, v1::DELIVERY_MODE_QUEUE, kMaxQueueSize));
  ASSERT_TRUE(steady.waitSubscribed());

  std::atomic<bool> publishing{true};
  std::vector<std::thread> churners;
  std::atomic<int> churn_rounds{0};
  for (int c = 0; c < 3; ++c) {
    churners.emplace_back([&, c] {
      auto channel = makeChannel(broker_.address());
      while (publishing.load()) {
        RawSubscriber sub(
            channel,
            subscribeRequest(topic, c % 2 ? v1::DELIVERY_MODE_LATEST : v1::DELIVERY_MODE_QUEUE, 3,
                             /*send_latest_first=*/c == 2),
            /*deadline=*/milliseconds(300));
        if (sub.waitSubscribed()) {
          v1::SubscribeResponse response;
          for (int i = 0; i < 3 && sub.read(&response); ++i) {
          }
        }
        sub.cancel();
        sub.finish();
        ++churn_rounds;
      }
    });
  }
  std::vector<std::thread> publishers;
  for (int p = 0; p < kPublishers; ++p) {
    publishers.emplace_back([&, p] {
      RawPublisher publisher(makeChannel(broker_.address()));
      for (int i = 0; i < kPerPublisher; ++i) {
        if (!publisher.write(topic, text(std::to_string(p) + ":" + std::to_string(i)))) break;
      }
      EXPECT_TRUE(publisher.finish().ok());
      EXPECT_EQ(publisher.accepted(), static_cast<uint64_t>(kPerPublisher));
    });
  }

  uint64_t expected_seq = 1;
  v1::SubscribeResponse response;
  while (expected_seq <= kTotal && steady.read(&response)) {
    ASSERT_EQ(response.topic_seq(), expected_seq);
    ASSERT_EQ(response.dropped_count(), 0u);
    ++expected_seq;
  }
  EXPECT_EQ(expected_seq, kTotal + 1);
  for (auto& t : publishers) t.join();
  publishing = false;
  for (auto& t : churners) t.join();
  EXPECT_GT(churn_rounds.load(), 0);
  steady.cancel();
  steady.finish();

  EXPECT_TRUE(eventually([&] {
    auto topics = listTopics(topic);
    return topics.topics_size() == 1 && topics.topics(0).subscriber_count() == 0 &&
           topics.topics(0).published_count() == kTotal;
  }));
}

TEST_F(ChannelBrokerTest, LatestModeKeepsOnlyTheNewestSample) {
  const std::string topic = "robots/d1/state";
  v1::Image image;
  image.set_data(std::string(100 * 1024, 'y'));
  RawSubscriber latest(makeChannel(broker_.address(), /*small_window=*/true),
                       subscribeRequest(topic, v1::DELIVERY_MODE_LATEST));
  ASSERT_TRUE(latest.waitSubscribed());
  RawPublisher publisher(channel_);
  for (int i = 0; i < 50; ++i) ASSERT_TRUE(publisher.write(topic, image));
  ASSERT_TRUE(publisher.finish().ok());

  std::vector<uint64_t> seqs;
  v1::SubscribeResponse response;
  while (latest.read(&response)) {
    seqs.push_back(response.topic_seq());
    if (response.topic_seq() == 50) break;
  }
  ASSERT_FALSE(seqs.empty());
  EXPECT_EQ(seqs.back(), 50u);
  // At most the sample whose write had started, then the newest.
  EXPECT_LE(seqs.size(), 2u);
  EXPECT_EQ(response.dropped_count() + seqs.size(), 50u);
  latest.cancel();
  latest.finish();
}

TEST_F(ChannelBrokerTest, SendLatestFirstAndWaitingForUnpublishedTopic) {
  // Subscribing to a topic nobody published on yet is allowed: it waits.
  RawSubscriber waiting(channel_, subscribeRequest("robots/d2/text", v1::DELIVERY_MODE_LATEST));
  ASSERT_TRUE(waiting.waitSubscribed());
  ASSERT_TRUE(publishOnce(channel_, publishRequest("robots/d2/text", text("first"))).ok());
  v1::SubscribeResponse response;
  ASSERT_TRUE(waiting.read(&response));
  v1::Text t;
  ASSERT_TRUE(response.sample().UnpackTo(&t));
  EXPECT_EQ(t.text(), "first");

  RawSubscriber late(channel_, subscribeRequest("robots/d2/text", v1::DELIVERY_MODE_QUEUE, 5,
                                                /*send_latest_first=*/true));
  ASSERT_TRUE(late.waitSubscribed());
  ASSERT_TRUE(late.read(&response));
  EXPECT_EQ(response.topic_seq(), 1u);
  ASSERT_TRUE(publishOnce(channel_, publishRequest("robots/d2/text", text("second"))).ok());
  ASSERT_TRUE(late.read(&response));
  EXPECT_EQ(response.topic_seq(), 2u);
  waiting.cancel();
  late.cancel();
  waiting.finish();
  late.finish();
}

TEST_F(ChannelBrokerTest, TypeConflictEndsOnlyThatStream) {
  const std::string topic = "robots/d1/tick";
  RawPublisher good(channel_);
  ASSERT_TRUE(good.write(topic, clockSample(1)));
  // Make sure the first sample fixed the topic's type.
  ASSERT_TRUE(eventually([&] {
    v1::GetLatestResponse r;
    return getLatest(topic, &r).ok();
  }));

  RawPublisher bad(channel_);
  bad.write(topic, v1::Imu());
  grpc::Status status = bad.finish();
  EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_EQ(status.error_message(),
            "topic 'robots/d1/tick' carries behaviorlib.v1.Clock; got behaviorlib.v1.Imu");

  // The other stream and the broker carry on.
  ASSERT_TRUE(good.write(topic, clockSample(2)));
  ASSERT_TRUE(good.finish().ok());
  EXPECT_EQ(good.accepted(), 2u);
  v1::GetLatestResponse latest;
  ASSERT_TRUE(getLatest(topic, &latest).ok());
  EXPECT_EQ(latest.sample().topic_seq(), 2u);
  auto topics = listTopics(topic);
  ASSERT_EQ(topics.topics_size(), 1);
  EXPECT_EQ(topics.topics(0).type(), "behaviorlib.v1.Clock");
}

TEST_F(ChannelBrokerTest, MalformedOrUnknownSamplesAreRejected) {
  v1::PublishRequest malformed;
  malformed.set_topic("robots/d1/imu");
  malformed.mutable_sample()->set_type_url("type.googleapis.com/behaviorlib.v1.Imu");
  malformed.mutable_sample()->set_value(std::string(12, '\xff'));
  grpc::Status status = publishOnce(channel_, malformed);
  EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_THAT(status.error_message(), HasSubstr("robots/d1/imu"));
  EXPECT_THAT(status.error_message(), HasSubstr("malformed"));

  v1::PublishRequest unknown;
  unknown.set_topic("robots/d1/imu");
  unknown.mutable_sample()->set_type_url("type.googleapis.com/acme.Secret");
  status = publishOnce(channel_, unknown);
  EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_THAT(status.error_message(), HasSubstr("acme.Secret"));

  v1::PublishRequest missing;
  missing.set_topic("robots/d1/imu");
  EXPECT_EQ(publishOnce(channel_, missing).error_code(), grpc::StatusCode::INVALID_ARGUMENT);

  // Nothing was stored, and the broker still serves.
  v1::GetLatestResponse latest;
  EXPECT_EQ(getLatest("robots/d1/imu", &latest).error_code(), grpc::StatusCode::NOT_FOUND);
  EXPECT_TRUE(publishOnce(channel_, publishRequest("robots/d1/imu", v1::Imu())).ok());
}

TEST_F(ChannelBrokerTest, InvalidTopicsAndRequestsAreRejected) {
  grpc::Status status = publishOnce(channel_, publishRequest("robots/d1", text("x")));
  EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_THAT(status.error_message(), HasSubstr("'robots/d1'"));
  EXPECT_THAT(status.error_message(), HasSubstr("robots/{robot_id}/{name}"));

  RawSubscriber bad_topic(channel_, subscribeRequest("robots/d 1/x"));
  EXPECT_FALSE(bad_topic.waitSubscribed());
  status = bad_topic.finish();
  EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_THAT(status.error_message(), HasSubstr("robots/d 1/x"));

  RawSubscriber bad_queue(
      channel_, subscribeRequest("robots/d1/x", v1::DELIVERY_MODE_QUEUE, kMaxQueueSize + 1));
  EXPECT_FALSE(bad_queue.waitSubscribed());
  status = bad_queue.finish();
  EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_THAT(status.error_message(), HasSubstr("queue_size"));

  v1::GetLatestResponse latest;
  EXPECT_EQ(getLatest("nope", &latest).error_code(), grpc::StatusCode::INVALID_ARGUMENT);
}

TEST_F(ChannelBrokerTest, GetLatestAndListTopics) {
  v1::GetLatestResponse latest;
  grpc::Status status = getLatest("robots/d1/pose", &latest);
  EXPECT_EQ(status.error_code(), grpc::StatusCode::NOT_FOUND);
  EXPECT_THAT(status.error_message(), HasSubstr("robots/d1/pose"));
  const auto info = errors::errorInfo(status);
  ASSERT_TRUE(info.has_value());
  EXPECT_EQ(info->reason(), "TOPIC_EMPTY");
  EXPECT_EQ(info->metadata().at("topic"), "robots/d1/pose");

  RawPublisher publisher(channel_);
  v1::PoseStamped pose;
  pose.mutable_pose()->mutable_position_m()->set_x(1.5);
  ASSERT_TRUE(publisher.write("robots/d1/pose", pose));
  pose.mutable_pose()->mutable_position_m()->set_x(2.5);
  ASSERT_TRUE(publisher.write("robots/d1/pose", pose));
  ASSERT_TRUE(publisher.write("robots/d2/pose", pose));
  ASSERT_TRUE(publisher.write("clock", clockSample(7)));
  ASSERT_TRUE(publisher.finish().ok());

  ASSERT_TRUE(getLatest("robots/d1/pose", &latest).ok());
  EXPECT_EQ(latest.sample().topic_seq(), 2u);
  v1::PoseStamped got;
  ASSERT_TRUE(latest.sample().sample().UnpackTo(&got));
  EXPECT_DOUBLE_EQ(got.pose().position_m().x(), 2.5);

  RawSubscriber subscriber(channel_, subscribeRequest("robots/d2/pose"));
  ASSERT_TRUE(subscriber.waitSubscribed());

  auto all = listTopics();
  ASSERT_EQ(all.topics_size(), 3);
  EXPECT_EQ(all.topics(0).name(), "clock");
  EXPECT_EQ(all.topics(0).type(), "behaviorlib.v1.Clock");
  EXPECT_EQ(all.topics(1).name(), "robots/d1/pose");
  EXPECT_EQ(all.topics(1).type(), "behaviorlib.v1.PoseStamped");
  EXPECT_EQ(all.topics(1).published_count(), 2u);
  EXPECT_EQ(all.topics(1).subscriber_count(), 0u);
  EXPECT_GT(all.topics(1).last_receive_time().seconds(), 0);
  EXPECT_EQ(all.topics(2).name(), "robots/d2/pose");
  EXPECT_EQ(all.topics(2).subscriber_count(), 1u);

  auto d1 = listTopics("robots/d1/");
  ASSERT_EQ(d1.topics_size(), 1);
  EXPECT_EQ(d1.topics(0).name(), "robots/d1/pose");

  // A cancelled subscription is released.
  subscriber.cancel();
  subscriber.finish();
  EXPECT_TRUE(
      eventually([&] { return listTopics("robots/d2/").topics(0).subscriber_count() == 0; }));

  // A topic that only ever had a waiting subscriber is forgotten with it.
  {
    RawSubscriber waiting(channel_, subscribeRequest("robots/d9/nothing"));
    ASSERT_TRUE(waiting.waitSubscribed());
    EXPECT_EQ(listTopics("robots/d9/").topics_size(), 1);
    waiting.cancel();
    waiting.finish();
  }
  EXPECT_TRUE(eventually([&] { return listTopics("robots/d9/").topics_size() == 0; }));
}

TEST_F(ChannelBrokerTest, ChannelClientPublishSubscribeAndQueries) {
  ChannelClient client(broker_.address());
  std::mutex mutex;
  std::vector<std::string> texts;
  auto sub = client.subscribeTyped<v1::Text>("robots/d3/chat",
                                             {.mode = v1::DELIVERY_MODE_QUEUE, .queue_size = 50},
                                             [&](const v1::Text& t) {
                                               std::lock_guard lock(mutex);
                                               texts.push_back(t.text());
                                             });
  ASSERT_TRUE(sub->waitConnected(seconds(10)));
  EXPECT_EQ(sub->connectCount(), 1u);

  for (int i = 0; i < 5; ++i)
    ASSERT_TRUE(client.publish("robots/d3/chat", text(std::to_string(i))).ok());
  ASSERT_TRUE(eventually([&] {
    std::lock_guard lock(mutex);
    return texts.size() == 5;
  }));
  {
    std::lock_guard lock(mutex);
    EXPECT_THAT(texts, ::testing::ElementsAre("0", "1", "2", "3", "4"));
  }
  EXPECT_EQ(sub->receivedCount(), 5u);

  auto latest = client.getLatest("robots/d3/chat");
  ASSERT_TRUE(latest.ok()) << latest.status();
  EXPECT_EQ(latest->topic_seq(), 5u);
  EXPECT_EQ(client.getLatest("robots/d3/none").status().code(), absl::StatusCode::kNotFound);

  auto topics = client.listTopics("robots/d3/");
  ASSERT_TRUE(topics.ok());
  ASSERT_EQ(topics->size(), 1u);
  EXPECT_EQ((*topics)[0].type(), "behaviorlib.v1.Text");

  EXPECT_EQ(client.publish("bad topic", text("x")).code(), absl::StatusCode::kInvalidArgument);

  // A refused sample ends the stream; the refusal surfaces on flush().
  auto accepted = client.flush();
  ASSERT_TRUE(accepted.ok()) << accepted.status();
  EXPECT_EQ(*accepted, 5u);
  ASSERT_TRUE(client.publish("robots/d3/chat", clockSample(1)).ok());  // wrong type
  auto refused = client.flush();
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(refused.status().message()), HasSubstr("carries behaviorlib.v1.Text"));
  // The next publish opens a new stream.
  EXPECT_TRUE(client.publish("robots/d3/chat", text("after")).ok());
  EXPECT_TRUE(client.flush().ok());

  // A subscription the broker refuses stops for good.
  auto bad = client.subscribe("robots/x", {}, [](const v1::SubscribeResponse&) {});
  EXPECT_EQ(bad->status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_FALSE(bad->connected());
}

// A batch (PublishRequest.more) is one message: every sample in it is
// numbered, checked and delivered as if published alone, and a refused one
// ends the stream with the samples before it taken.
TEST_F(ChannelBrokerTest, BatchesArePublishedSampleBySample) {
  ChannelClient client(broker_.address());
  std::mutex mutex;
  std::vector<std::pair<std::string, uint64_t>> got;
  std::vector<std::unique_ptr<Subscription>> subs;
  for (const std::string topic : {"robots/b1/a", "robots/b1/b"}) {
    subs.push_back(client.subscribe(topic, {.mode = v1::DELIVERY_MODE_QUEUE},
                                    [&](const v1::SubscribeResponse& r) {
                                      v1::Text t;
                                      r.sample().UnpackTo(&t);
                                      std::lock_guard lock(mutex);
                                      got.emplace_back(t.text(), r.topic_seq());
                                    }));
  }
  for (const auto& sub : subs) ASSERT_TRUE(sub->waitConnected(seconds(10)));
  const v1::Text a1 = text("a1"), b1 = text("b1"), a2 = text("a2");
  ASSERT_TRUE(
      client.publishAll({{"robots/b1/a", &a1}, {"robots/b1/b", &b1}, {"robots/b1/a", &a2}}).ok());
  ASSERT_TRUE(client.publishAll({}).ok());
  auto accepted = client.flush();
  ASSERT_TRUE(accepted.ok()) << accepted.status();
  EXPECT_EQ(*accepted, 3u);
  EXPECT_EQ(client.acceptedSeqs(),
            (std::map<std::string, uint64_t>{{"robots/b1/a", 2}, {"robots/b1/b", 1}}));
  ASSERT_TRUE(eventually([&] {
    std::lock_guard lock(mutex);
    return got.size() == 3;
  }));
  {
    std::lock_guard lock(mutex);
    std::sort(got.begin(), got.end());
    EXPECT_THAT(got, ::testing::ElementsAre(std::pair<std::string, uint64_t>{"a1", 1},
                                            std::pair<std::string, uint64_t>{"a2", 2},
                                            std::pair<std::string, uint64_t>{"b1", 1}));
  }

  // A bad topic name is refused before anything is sent.
  EXPECT_EQ(client.publishAll({{"robots/b1/a", &a1}, {"bad topic", &a1}}).code(),
            absl::StatusCode::kInvalidArgument);
  // A sample of the wrong type in the middle: the one before it is taken.
  const v1::Clock wrong = clockSample(1);
  ASSERT_TRUE(
      client.publishAll({{"robots/b1/a", &a1}, {"robots/b1/b", &wrong}, {"robots/b1/a", &a2}})
          .ok());
  auto refused = client.flush();
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kInvalidArgument);
  auto latest = client.getLatest("robots/b1/a");
  ASSERT_TRUE(latest.ok());
  EXPECT_EQ(latest->topic_seq(), 3u) << "a1 of the refused batch was taken, a2 was not";

  // A batch nested in a batch is refused.
  v1::PublishRequest nested = publishRequest("robots/b1/a", text("x"));
  *nested.add_more() = publishRequest("robots/b1/a", text("y"));
  *nested.mutable_more(0)->add_more() = publishRequest("robots/b1/a", text("z"));
  const grpc::Status status = publishOnce(channel_, nested);
  EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_THAT(status.error_message(), HasSubstr("batch of its own"));
}

// PublishAcked answers each `sync` request with what the stream has taken,
// in order, and keeps the stream open; a refused sample still ends it.
TEST_F(ChannelBrokerTest, PublishAckedAnswersEverySyncOnTheOpenStream) {
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + seconds(30));
  auto stream = stub_->PublishAcked(&context);
  v1::PublishRequest sync;
  sync.set_sync(true);
  v1::PublishResponse answer;
  ASSERT_TRUE(stream->Write(publishRequest("robots/k1/a", text("1"))));
  v1::PublishRequest second = publishRequest("robots/k1/b", text("2"));
  second.set_sync(true);  // a sample and the question in one request
  ASSERT_TRUE(stream->Write(second));
  ASSERT_TRUE(stream->Read(&answer));
  EXPECT_EQ(answer.accepted_count(), 2u);
  EXPECT_EQ(answer.topic_seqs().at("robots/k1/a"), 1u);
  EXPECT_EQ(answer.topic_seqs().at("robots/k1/b"), 1u);
  ASSERT_TRUE(stream->Write(publishRequest("robots/k1/a", text("3"))));
  ASSERT_TRUE(stream->Write(sync));
  ASSERT_TRUE(stream->Write(sync));
  ASSERT_TRUE(stream->Read(&answer));
  EXPECT_EQ(answer.accepted_count(), 3u);
  EXPECT_EQ(answer.topic_seqs().at("robots/k1/a"), 2u);
  ASSERT_TRUE(stream->Read(&answer));
  EXPECT_EQ(answer.accepted_count(), 3u) << "a question alone takes nothing";
  // A sample of another type than the topic's ends the stream, unanswered.
  ASSERT_TRUE(stream->Write(publishRequest("robots/k1/a", clockSample(1))));
  stream->Write(sync);
  EXPECT_FALSE(stream->Read(&answer));
  const grpc::Status status = stream->Finish();
  EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_THAT(status.error_message(), HasSubstr("carries behaviorlib.v1.Text"));
}

// The deterministic mode's barrier: sync() returns once the broker accepted
// everything published, and delivered() tells whether each subscription has
// processed the sample a topic_seq names (samples published before it
// registered are not waited for).
TEST_F(ChannelBrokerTest, SyncAndDeliveredAreTheDataBarrier) {
  ChannelClient publisher(broker_.address());
  EXPECT_TRUE(publisher.sync().ok());  // nothing published: nothing to wait for
  for (int i = 0; i < 3; ++i) ASSERT_TRUE(publisher.publish("robots/d9/a", text("x")).ok());
  ASSERT_TRUE(publisher.sync().ok());
  // Accepted means counted: no waiting needed.
  auto topics = publisher.listTopics("robots/d9/");
  ASSERT_TRUE(topics.ok()) << topics.status();
  ASSERT_EQ(topics->size(), 1u);
  EXPECT_EQ((*topics)[0].published_count(), 3u);
  // The broker's reply numbers the stream's last sample on each topic.
  EXPECT_EQ(publisher.acceptedSeqs(), (std::map<std::string, uint64_t>{{"robots/d9/a", 3}}));

  ChannelClient subscriber(broker_.address());
  std::map<std::string, uint64_t> seqs = {{"robots/d9/a", 3}, {"robots/d9/b", 1}};
  const auto seq_of = [&seqs](const std::string& topic) -> uint64_t {
    const auto it = seqs.find(topic);
    return it == seqs.end() ? 0 : it->second;
  };
  EXPECT_TRUE(subscriber.delivered(seq_of));  // no subscription yet
  std::atomic<bool> release{false};
  auto a = subscriber.subscribeTyped<v1::Text>("robots/d9/a", {.mode = v1::DELIVERY_MODE_QUEUE},
                                               [](const v1::Text&) {});
  // The callback holds b's samples until released: processed means returned.
  auto b = subscriber.subscribeTyped<v1::Text>(
      "robots/d9/b", {.mode = v1::DELIVERY_MODE_QUEUE}, [&release](const v1::Text&) {
        while (!release.load()) std::this_thread::sleep_for(std::chrono::milliseconds(1));
      });
  ASSERT_TRUE(a->waitConnected(seconds(10)));
  ASSERT_TRUE(b->waitConnected(seconds(10)));
  // a registered after its 3 samples: they are not waited for. b's first
  // sample is not published yet.
  EXPECT_EQ(a->processedSeq(), 3u);
  EXPECT_FALSE(subscriber.delivered(seq_of));
  ASSERT_TRUE(publisher.publish("robots/d9/b", text("y")).ok());
  ASSERT_TRUE(publisher.sync().ok());
  ASSERT_TRUE(eventually([&] { return b->receivedCount() == 1; }));
  EXPECT_FALSE(subscriber.delivered(seq_of));  // received, callback still running
  release = true;
  ASSERT_TRUE(eventually([&] { return subscriber.delivered(seq_of); }));
  EXPECT_EQ(b->processedSeq(), 1u);
  // A later sample on a is waited for once named.
  seqs["robots/d9/a"] = 4;
  EXPECT_FALSE(subscriber.delivered(seq_of));
  ASSERT_TRUE(publisher.publish("robots/d9/a", text("z")).ok());
  ASSERT_TRUE(publisher.sync().ok());
  ASSERT_TRUE(eventually([&] { return subscriber.delivered(seq_of); }));
  // A subscription that ended is not waited for.
  seqs["robots/d9/b"] = 100;
  b.reset();
  EXPECT_TRUE(subscriber.delivered(seq_of));
}

// publishAllAndSync: the batch and the question in one round trip; when it
// returns, the broker took the batch and numbered it, as after publishAll()
// and sync(); a refused sample is its answer.
TEST_F(ChannelBrokerTest, ABatchCarriesItsSyncInOneRoundTrip) {
  ChannelClient publisher(broker_.address());
  const v1::Text a1 = text("a1"), b1 = text("b1"), a2 = text("a2");
  ASSERT_TRUE(publisher.publishAllAndSync({}).ok());  // nothing: nothing to wait for
  ASSERT_TRUE(
      publisher
          .publishAllAndSync({{"robots/s1/a", &a1}, {"robots/s1/b", &b1}, {"robots/s1/a", &a2}})
          .ok());
  EXPECT_EQ(publisher.acceptedSeqs(),
            (std::map<std::string, uint64_t>{{"robots/s1/a", 2}, {"robots/s1/b", 1}}));
  auto topics = publisher.listTopics("robots/s1/");
  ASSERT_TRUE(topics.ok()) << topics.status();
  ASSERT_EQ(topics->size(), 2u);
  EXPECT_EQ((*topics)[0].published_count() + (*topics)[1].published_count(), 3u);
  // Samples published before, without a sync, are covered by the next one.
  ASSERT_TRUE(publisher.publish("robots/s1/b", text("b2")).ok());
  ASSERT_TRUE(publisher.publishAllAndSync({{"robots/s1/a", &a1}}).ok());
  EXPECT_EQ(publisher.acceptedSeqs(),
            (std::map<std::string, uint64_t>{{"robots/s1/a", 3}, {"robots/s1/b", 2}}));
  // A sample of the wrong type: the answer is the refusal.
  const v1::Clock wrong = clockSample(1);
  const absl::Status refused = publisher.publishAllAndSync({{"robots/s1/a", &wrong}});
  EXPECT_EQ(refused.code(), absl::StatusCode::kInvalidArgument) << refused;
  // The next batch opens a new stream.
  ASSERT_TRUE(publisher.publishAllAndSync({{"robots/s1/a", &a2}}).ok());
  EXPECT_EQ(publisher.acceptedSeqs().at("robots/s1/a"), 4u);
}

// bufferUntilSync: publishes may wait in the stream's buffer, and sync()
// takes them all out; turned off, a publish goes out by itself again.
TEST_F(ChannelBrokerTest, BufferedPublishesGoOutWithTheSync) {
  ChannelClient publisher(broker_.address());
  ChannelClient reader(broker_.address());
  const auto counted = [&reader]() -> uint64_t {
    auto topics = reader.listTopics("robots/u1/");
    return topics.ok() && topics->size() == 1 ? (*topics)[0].published_count() : 0;
  };
  publisher.bufferUntilSync(true);
  for (int i = 0; i < 3; ++i) ASSERT_TRUE(publisher.publish("robots/u1/a", text("x")).ok());
  ASSERT_TRUE(publisher.sync().ok());
  EXPECT_EQ(counted(), 3u);
  EXPECT_EQ(publisher.acceptedSeqs(), (std::map<std::string, uint64_t>{{"robots/u1/a", 3}}));
  publisher.bufferUntilSync(false);
  ASSERT_TRUE(publisher.publish("robots/u1/a", text("y")).ok());
  EXPECT_TRUE(eventually([&] { return counted() == 4u; })) << "sent without a sync";
}

TEST_F(ChannelBrokerTest, ChannelClientSubscriberReconnectsAfterBrokerRestart) {
  const int port = broker_.grpcPort();
  ChannelClient client(broker_.address());
  std::atomic<int> received{0};
  auto sub = client.subscribeTyped<v1::Text>("robots/d4/chat", {.mode = v1::DELIVERY_MODE_QUEUE},
                                             [&](const v1::Text&) { ++received; });
  ASSERT_TRUE(sub->waitConnected(seconds(10)));
  ASSERT_TRUE(client.publish("robots/d4/chat", text("before")).ok());
  ASSERT_TRUE(eventually([&] { return received.load() == 1; }));

  ASSERT_EQ(broker_.terminate(), 0);
  ASSERT_TRUE(eventually([&] { return !sub->connected(); }));

  // Same port, new process.
  support::ServerProcess restarted(kBrokerPath, {"--listen", "127.0.0.1:" + std::to_string(port)});
  ASSERT_TRUE(restarted.start()) << restarted.error();
  ASSERT_EQ(restarted.grpcPort(), port);
  ASSERT_TRUE(eventually([&] { return sub->connected() && sub->connectCount() >= 2; }, seconds(15)))
      << sub->status();
  // The client's publish stream died with the old broker; publish reopens it.
  ASSERT_TRUE(eventually([&] { return client.publish("robots/d4/chat", text("after")).ok(); }));
  ASSERT_TRUE(eventually([&] { return received.load() >= 2; }));
  EXPECT_EQ(restarted.terminate(), 0);
}

// The rings of a broker (named after its pid) under /dev/shm.
std::vector<std::string> ringsOf(pid_t broker) {
  std::vector<std::string> found;
  const std::string prefix = "behaviorlib-ch-" + std::to_string(broker) + "-";
  if (DIR* dir = opendir("/dev/shm")) {
    while (const dirent* entry = readdir(dir)) {
      if (std::string(entry->d_name).rfind(prefix, 0) == 0) found.push_back(entry->d_name);
    }
    closedir(dir);
  }
  return found;
}

std::string metricLine(const std::string& metrics, const std::string& series) {
  const auto at = metrics.find(series + " ");
  if (at == std::string::npos) return "";
  return metrics.substr(at, metrics.find('\n', at) - at);
}

// Subscribers on the broker's host read every sample from one shared-memory
// ring (decision 20); one that opts out gets its samples on its stream. Both
// see the same samples in the same order, also across a sample too big for
// the ring's slots, which makes the broker open a bigger ring.
TEST_F(ChannelBrokerTest, SubscribersOnThisHostReadOneCopyFromSharedMemory) {
  const std::string topic = "robots/s1/chat";
  ChannelClient client(broker_.address());
  std::mutex mutex;
  std::map<int, std::vector<std::string>> texts;
  std::vector<std::unique_ptr<Subscription>> subs;
  for (int i = 0; i < 4; ++i) {
    subs.push_back(client.subscribeTyped<v1::Text>(
        topic, {.mode = v1::DELIVERY_MODE_QUEUE, .queue_size = 50, .shared_memory = i != 3},
        [&, i](const v1::Text& t) {
          std::lock_guard lock(mutex);
          texts[i].push_back(t.text().size() > 100 ? "big" : t.text());
        }));
  }
  for (const auto& sub : subs) ASSERT_TRUE(sub->waitConnected(seconds(10)));
  EXPECT_EQ(ringsOf(broker_.pid()).size(), 1u);

  std::vector<std::string> expected;
  for (int i = 0; i < 20; ++i) {
    expected.push_back(std::to_string(i));
    ASSERT_TRUE(client.publish(topic, text(expected.back())).ok());
  }
  ASSERT_TRUE(client.publish(topic, text(std::string(200000, 'x'))).ok());
  expected.push_back("big");
  ASSERT_TRUE(client.publish(topic, text("after")).ok());
  expected.push_back("after");
  ASSERT_TRUE(eventually([&] {
    std::lock_guard lock(mutex);
    for (int i = 0; i < 4; ++i) {
      if (texts[i].size() < expected.size()) return false;
    }
    return true;
  }));
  {
    std::lock_guard lock(mutex);
    for (int i = 0; i < 4; ++i) EXPECT_EQ(texts[i], expected) << "subscriber " << i;
  }
  for (const auto& sub : subs) EXPECT_EQ(sub->processedSeq(), expected.size());

  // One copy into the ring per sample; the stream carried only the
  // opted-out subscriber's.
  const std::string metrics = support::httpGet(broker_.metricsPort(), "/metrics");
  EXPECT_EQ(metricLine(metrics, "behaviorlib_channel_shm_samples_total{topic=\"" + topic + "\"}"),
            "behaviorlib_channel_shm_samples_total{topic=\"" + topic + "\"} 22");
  EXPECT_EQ(metricLine(metrics, "behaviorlib_channel_samples_out_total{topic=\"" + topic + "\"}"),
            "behaviorlib_channel_samples_out_total{topic=\"" + topic + "\"} 22");
  EXPECT_EQ(ringsOf(broker_.pid()).size(), 1u) << "the small ring was replaced, not kept";

  // The ring goes with its last reader.
  subs.clear();
  EXPECT_TRUE(eventually([&] { return ringsOf(broker_.pid()).empty(); }));
}

// The broker offers a ring only to a client whose shared memory is its own
// (same host and IPC namespace, SubscribeRequest.shm_domain); a client that
// names none gets one only on the loopback.
TEST_F(ChannelBrokerTest, RingsAreOfferedOnlyInTheBrokersSharedMemoryDomain) {
  const auto offered = [&](const std::string& domain) {
    v1::SubscribeRequest request = subscribeRequest("robots/s4/chat");
    request.set_shared_memory(true);
    request.set_shm_domain(domain);
    auto stub = v1::DataChannel::NewStub(channel_);
    grpc::ClientContext context;
    auto reader = stub->Subscribe(&context, request);
    reader->WaitForInitialMetadata();
    const bool ring = context.GetServerInitialMetadata().count(kShmRingMetadataKey) > 0;
    context.TryCancel();
    reader->Finish();
    return ring;
  };
  ASSERT_FALSE(ShmRing::domain().empty());
  EXPECT_TRUE(offered(ShmRing::domain()));
  EXPECT_TRUE(offered("")) << "a loopback client naming no domain";
  EXPECT_FALSE(offered("another-host/4026531839"));
}

// With --shared-memory=false the broker offers no ring: a client that asks
// for one gets its samples on the stream.
TEST_F(ChannelBrokerTest, BrokerWithoutSharedMemoryStreamsEverySample) {
  support::ServerProcess broker(kBrokerPath, {"--shared-memory=false"});
  ASSERT_TRUE(broker.start()) << broker.error();
  ChannelClient client(broker.address());
  std::atomic<int> received{0};
  auto sub = client.subscribeTyped<v1::Text>("robots/s2/chat", {.mode = v1::DELIVERY_MODE_QUEUE},
                                             [&](const v1::Text&) { ++received; });
  ASSERT_TRUE(sub->waitConnected(seconds(10)));
  for (int i = 0; i < 5; ++i) ASSERT_TRUE(client.publish("robots/s2/chat", text("x")).ok());
  ASSERT_TRUE(eventually([&] { return received.load() == 5; }));
  EXPECT_TRUE(ringsOf(broker.pid()).empty());
  const std::string metrics = support::httpGet(broker.metricsPort(), "/metrics");
  EXPECT_THAT(metrics,
              HasSubstr("behaviorlib_channel_samples_out_total{topic=\"robots/s2/chat\"} 5"));
}

// A broker killed with SIGKILL cannot remove its rings; the next one does,
// and the subscriber reads on from a ring of the new broker.
TEST_F(ChannelBrokerTest, RingsOfAKilledBrokerAreRemovedByTheNext) {
  const int port = broker_.grpcPort();
  const pid_t old_pid = broker_.pid();
  ChannelClient client(broker_.address());
  std::atomic<int> received{0};
  auto sub = client.subscribeTyped<v1::Text>("robots/s3/chat", {.mode = v1::DELIVERY_MODE_QUEUE},
                                             [&](const v1::Text&) { ++received; });
  ASSERT_TRUE(sub->waitConnected(seconds(10)));
  ASSERT_EQ(ringsOf(old_pid).size(), 1u);
  broker_.kill();
  ASSERT_EQ(ringsOf(old_pid).size(), 1u) << "a killed broker leaves its ring";

  support::ServerProcess restarted(kBrokerPath, {"--listen", "127.0.0.1:" + std::to_string(port)});
  ASSERT_TRUE(restarted.start()) << restarted.error();
  EXPECT_TRUE(ringsOf(old_pid).empty());
  ASSERT_TRUE(eventually([&] { return sub->connected() && sub->connectCount() >= 2; }, seconds(15)))
      << sub->status();
  ASSERT_TRUE(eventually([&] { return client.publish("robots/s3/chat", text("after")).ok(); }));
  ASSERT_TRUE(eventually([&] { return received.load() >= 1; }));
  const pid_t new_pid = restarted.pid();
  EXPECT_EQ(ringsOf(new_pid).size(), 1u);
  EXPECT_EQ(restarted.terminate(), 0);
  EXPECT_TRUE(ringsOf(new_pid).empty()) << "a broker that stops removes its rings";
}

TEST_F(ChannelBrokerTest, SimClockFollowsTheClockTopic) {
  ChannelClient publisher(broker_.address());
  // Lock-step (time scale 0): a sample is the time.
  ASSERT_TRUE(publisher.publish("clock", clockSample(1000, 0.0)).ok());
  ASSERT_TRUE(publisher.flush().ok());

  SimClock clock(broker_.address());
  // send_latest_first: the time already on the topic arrives at once.
  ASSERT_TRUE(eventually([&] { return clock.valid(); }));
  EXPECT_EQ(clock.now(), TimePoint(seconds(1000)));
  EXPECT_DOUBLE_EQ(clock.timeScale(), 0.0);
  EXPECT_FALSE(clock.stale(seconds(5)));

  struct Listener : ClockListener {
    void onClockAdvanced() override { ++calls; }
    std::atomic<int> calls{0};
  } listener;
  clock.addListener(&listener);
  ASSERT_TRUE(publisher.publish("clock", clockSample(1001, 0.0)).ok());
  ASSERT_TRUE(eventually([&] { return clock.now() == TimePoint(seconds(1001)); }));
  EXPECT_GE(listener.calls.load(), 1);
  // Free-running at 5x: the line is extrapolated between samples.
  ASSERT_TRUE(publisher.publish("clock", clockSample(2000, 5.0)).ok());
  ASSERT_TRUE(eventually([&] { return clock.timeScale() == 5.0; }));
  const TimePoint first = clock.now();
  EXPECT_GE(first, TimePoint(seconds(2000)));
  ASSERT_TRUE(eventually([&] { return clock.now() >= first + milliseconds(100); }))
      << "time advances without samples";
  clock.removeListener(&listener);
  EXPECT_EQ(clock.wallWaitFor(milliseconds(100)), milliseconds(20));
}

// WatchInterest: a topic is wanted while it has a subscriber and for 2 s
// after a GetLatest. A gated topic (its publisher says it publishes only
// while wanted) keeps no sample while nobody wants it, and a GetLatest of it
// waits for the next one (NOT_FOUND after 1 s); other topics are untouched.
TEST_F(ChannelBrokerTest, InterestFollowsSubscribersAndGetLatestOfGatedTopics) {
  const std::string topic = "robots/d7/imu";
  ChannelClient watcher(broker_.address());
  std::atomic<int> changes{0};
  auto watch = watcher.watchInterest("robots/d7/", [&] { ++changes; });
  ASSERT_TRUE(eventually([&] { return watch->known(); }));
  EXPECT_GE(changes.load(), 1);
  EXPECT_TRUE(watch->wanted("clock")) << "outside the prefix: not gated";

  ChannelClient publisher(broker_.address());
  publisher.gatePublishing("robots/d7/");
  ASSERT_TRUE(publisher.publish(topic, text("first")).ok());
  ChannelClient other(broker_.address());  // does not gate
  ASSERT_TRUE(other.publish("robots/d7/chat", text("kept")).ok());
  ASSERT_TRUE(eventually([&] { return listTopics("robots/d7/").topics_size() == 2; }));
  EXPECT_FALSE(watch->wanted(topic));
  // Gated and unwanted: the topic is known, its sample not kept.
  EXPECT_EQ(listTopics("robots/d7/").topics(1).name(), topic);
  EXPECT_EQ(listTopics("robots/d7/").topics(1).published_count(), 1u);
  EXPECT_FALSE(listTopics("robots/d7/").topics(1).has_last_receive_time());
  // The other publisher's topic keeps its sample, wanted or not.
  ChannelClient reader(broker_.address());
  EXPECT_TRUE(reader.getLatest("robots/d7/chat", seconds(5)).ok());

  // A GetLatest makes the gated topic wanted and waits for a sample; none
  // comes.
  const auto asked = std::chrono::steady_clock::now();
  EXPECT_EQ(reader.getLatest(topic, seconds(5)).status().code(), absl::StatusCode::kNotFound);
  EXPECT_GE(std::chrono::steady_clock::now() - asked, milliseconds(900)) << "it waited";
  EXPECT_TRUE(eventually([&] { return watch->wanted(topic); }));
  // A sample published while one waits is its answer.
  std::thread later([&] {
    std::this_thread::sleep_for(milliseconds(100));
    EXPECT_TRUE(publisher.publish(topic, text("second")).ok());
  });
  auto got = reader.getLatest(topic, seconds(5));
  later.join();
  ASSERT_TRUE(got.ok()) << got.status();
  v1::Text sample;
  ASSERT_TRUE(got->sample().UnpackTo(&sample));
  EXPECT_EQ(sample.text(), "second");
  // 2 s after the last GetLatest nobody wants it, and its sample is gone.
  EXPECT_TRUE(eventually([&] { return !watch->wanted(topic); }));
  EXPECT_FALSE(listTopics("robots/d7/").topics(1).has_last_receive_time());

  // A subscriber wants it until it leaves.
  auto sub = reader.subscribe(topic, {}, [](const v1::SubscribeResponse&) {});
  ASSERT_TRUE(sub->waitConnected(seconds(10)));
  EXPECT_TRUE(eventually([&] { return watch->wanted(topic); }));
  sub.reset();
  EXPECT_TRUE(eventually([&] { return !watch->wanted(topic); }));
}

// What a subscription received: when, and which sample.
struct Received {
  absl::Mutex mutex;
  std::vector<uint64_t> seqs ABSL_GUARDED_BY(mutex);
  std::function<void(const v1::SubscribeResponse&)> callback() {
    return [this](const v1::SubscribeResponse& sample) {
      absl::MutexLock lock(&mutex);
      seqs.push_back(sample.topic_seq());
    };
  }
  std::vector<uint64_t> get() {
    absl::MutexLock lock(&mutex);
    return seqs;
  }
};

TEST_F(ChannelBrokerTest, RateLimitedSubscriptionsGetTheNewestAtMostThatOftenAndTheLast) {
  const std::string topic = "robots/r1/pose";
  ChannelClient watcher(broker_.address());
  auto watch = watcher.watchInterest("robots/r1/", [] {});
  ASSERT_TRUE(eventually([&] { return watch->known(); }));

  const auto start = std::chrono::steady_clock::now();
  ChannelClient reader(broker_.address());
  Received by_stream;
  Received by_ring;
  auto stream_sub =
      reader.subscribe(topic, {.shared_memory = false, .max_rate_hz = 10}, by_stream.callback());
  auto ring_sub = reader.subscribe(topic, {.max_rate_hz = 10}, by_ring.callback());
  ASSERT_TRUE(stream_sub->waitConnected(seconds(10)));
  ASSERT_TRUE(ring_sub->waitConnected(seconds(10)));
  // The broker tells a gating publisher the rate its readers want.
  ASSERT_TRUE(eventually([&] { return watch->wanted(topic) && watch->maxRateHz(topic) == 10; }));
  EXPECT_TRUE(reader.delivered([](const std::string&) { return 1'000'000; }))
      << "the data barrier does not wait for a rate-limited reader";

  // 600 samples, about a millisecond apart.
  ChannelClient publisher(broker_.address());
  constexpr uint64_t kSamples = 600;
  for (uint64_t i = 1; i <= kSamples; ++i) {
    ASSERT_TRUE(publisher.publish(topic, text(std::to_string(i))).ok());
    std::this_thread::sleep_for(milliseconds(1));
  }
  ASSERT_TRUE(publisher.sync().ok());
  // The last sample always arrives (it waits for its interval)...
  for (Received* received : {&by_stream, &by_ring}) {
    ASSERT_TRUE(eventually([&] {
      auto seqs = received->get();
      return !seqs.empty() && seqs.back() == kSamples;
    }));
  }
  const double elapsed_s =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  // ... and at most one sample every 100 ms came, each newer than the last.
  for (Received* received : {&by_stream, &by_ring}) {
    const auto seqs = received->get();
    EXPECT_LE(static_cast<double>(seqs.size()), elapsed_s * 10 + 2) << seqs.size();
    EXPECT_TRUE(std::is_sorted(seqs.begin(), seqs.end()));
    EXPECT_EQ(std::adjacent_find(seqs.begin(), seqs.end()), seqs.end()) << "no repeats";
  }
  EXPECT_EQ(stream_sub->receivedCount(), by_stream.get().size());

  // A reader of every sample makes the topic wanted at every sample, until
  // it leaves.
  auto every = reader.subscribe(topic, {.shared_memory = false}, [](const auto&) {});
  ASSERT_TRUE(every->waitConnected(seconds(10)));
  EXPECT_TRUE(eventually([&] { return watch->maxRateHz(topic) == 0; }));
  every.reset();
  EXPECT_TRUE(eventually([&] { return watch->maxRateHz(topic) == 10; }));

  // A rate out of range is refused, naming the field.
  for (double bad : {-1.0, std::nan(""), 1e9}) {
    v1::SubscribeRequest request = subscribeRequest(topic);
    request.set_max_rate_hz(bad);
    RawSubscriber refused(channel_, request, seconds(5));
    v1::SubscribeResponse ignored;
    EXPECT_FALSE(refused.read(&ignored));
    const grpc::Status status = refused.finish();
    EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << bad;
    EXPECT_THAT(status.error_message(), HasSubstr("max_rate_hz"));
    EXPECT_FALSE(status.error_details().empty()) << "google.rpc details";
  }
}

TEST_F(ChannelBrokerTest, MetricsEndpoint) {
  ASSERT_GT(broker_.metricsPort(), 0);
  RawPublisher publisher(channel_);
  for (int i = 0; i < 5; ++i) ASSERT_TRUE(publisher.write("robots/m1/pose", v1::PoseStamped()));
  ASSERT_TRUE(publisher.finish().ok());
  publishOnce(channel_, publishRequest("robots/m1", v1::PoseStamped()));  // rejected
  RawSubscriber subscriber(channel_, subscribeRequest("robots/m1/pose"));
  ASSERT_TRUE(subscriber.waitSubscribed());

  const std::string metrics = support::httpGet(broker_.metricsPort(), "/metrics");
  EXPECT_THAT(metrics,
              HasSubstr("behaviorlib_channel_samples_in_total{topic=\"robots/m1/pose\"} 5"));
  EXPECT_THAT(metrics,
              HasSubstr("behaviorlib_channel_rejected_samples_total{reason=\"invalid_topic\"} 1"));
  EXPECT_THAT(metrics, HasSubstr("behaviorlib_channel_subscribers{topic=\"robots/m1/pose\"} 1"));
  EXPECT_THAT(metrics, HasSubstr("behaviorlib_channel_samples_out_total"));
  EXPECT_THAT(metrics, HasSubstr("behaviorlib_channel_dropped_samples_total"));
  subscriber.cancel();
  subscriber.finish();
}

TEST_F(ChannelBrokerTest, SigtermEndsStreamsAndExitsZero) {
  RawSubscriber subscriber(channel_, subscribeRequest("robots/d5/x"));
  ASSERT_TRUE(subscriber.waitSubscribed());
  // An open publish stream must not hold the shutdown up either.
  RawPublisher publisher(channel_);
  ASSERT_TRUE(publisher.write("robots/d5/x", text("hello")));
  v1::SubscribeResponse response;
  ASSERT_TRUE(subscriber.read(&response));

  const auto start = std::chrono::steady_clock::now();
  EXPECT_EQ(broker_.terminate(), 0);
  // Streams are ended at once; the rest is bounded gRPC and metrics-server
  // shutdown, far from the 10 s that terminate() would wait.
  EXPECT_LT(std::chrono::steady_clock::now() - start, seconds(5));
  EXPECT_FALSE(subscriber.read(&response));  // the stream ended
  EXPECT_EQ(subscriber.finish().error_code(), grpc::StatusCode::UNAVAILABLE);
  EXPECT_FALSE(publisher.finish().ok());
}

// Runs the broker with `args` until it exits by itself; returns the wait
// status and the stderr output.
int runToExit(const std::vector<std::string>& args, std::string* stderr_text) {
  char path[] = "/tmp/channel-broker-stderr-XXXXXX";
  int fd = mkstemp(path);
  if (fd < 0) return -1;
  close(fd);
  std::vector<std::string> argv_s = {kBrokerPath};
  argv_s.insert(argv_s.end(), args.begin(), args.end());
  std::vector<char*> argv;
  for (auto& a : argv_s) argv.push_back(a.data());
  argv.push_back(nullptr);
  posix_spawn_file_actions_t actions;
  posix_spawn_file_actions_init(&actions);
  posix_spawn_file_actions_addopen(&actions, STDERR_FILENO, path, O_WRONLY | O_TRUNC, 0);
  pid_t pid = -1;
  const int rc = posix_spawn(&pid, kBrokerPath, &actions, nullptr, argv.data(), environ);
  posix_spawn_file_actions_destroy(&actions);
  if (rc != 0) return -1;
  int status = 0;
  const auto deadline = std::chrono::steady_clock::now() + seconds(10);
  while (waitpid(pid, &status, WNOHANG) == 0) {
    if (std::chrono::steady_clock::now() > deadline) {
      kill(pid, SIGKILL);
      waitpid(pid, &status, 0);
      break;
    }
    std::this_thread::sleep_for(milliseconds(10));
  }
  std::ifstream in(path);
  std::stringstream ss;
  ss << in.rdbuf();
  *stderr_text = ss.str();
  unlink(path);
  return status;
}

TEST_F(ChannelBrokerTest, PortInUseFailsCleanly) {
  std::string err;
  int status = runToExit({"--listen", broker_.address(), "--metrics-listen", "127.0.0.1:0"}, &err);
  ASSERT_TRUE(WIFEXITED(status)) << "killed by signal " << WTERMSIG(status) << ": " << err;
  EXPECT_EQ(WEXITSTATUS(status), 1);
  EXPECT_THAT(err, HasSubstr("cannot listen on " + broker_.address()));

  status = runToExit({"--listen", "127.0.0.1:0", "--metrics-listen",
                      "127.0.0.1:" + std::to_string(broker_.metricsPort())},
                     &err);
  ASSERT_TRUE(WIFEXITED(status)) << "killed by signal " << WTERMSIG(status) << ": " << err;
  EXPECT_EQ(WEXITSTATUS(status), 1);
  EXPECT_THAT(err, HasSubstr("cannot serve metrics"));

  // The running broker is unaffected.
  EXPECT_TRUE(publishOnce(channel_, publishRequest("robots/d1/x", text("still here"))).ok());
}

// ---- The server limits every process sets (ServerLimits) -------------------

// ListTopics on `channel` within `timeout`.
grpc::Status listTopicsWithin(const std::shared_ptr<grpc::Channel>& channel,
                              std::chrono::milliseconds timeout) {
  auto stub = v1::DataChannel::NewStub(channel);
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + timeout);
  v1::ListTopicsResponse response;
  return stub->ListTopics(&context, v1::ListTopicsRequest(), &response);
}

TEST_F(ChannelBrokerTest, ConcurrentStreamsAreCappedPerConnection) {
  constexpr int kLimit = server_kit::ServerLimits::kMaxConcurrentStreams;
  const auto full = makeChannel(broker_.address());  // a connection of its own
  std::vector<std::unique_ptr<RawSubscriber>> streams;
  for (int i = 0; i < kLimit; ++i) {
    streams.push_back(std::make_unique<RawSubscriber>(full, subscribeRequest("robots/limits/t")));
  }
  for (auto& stream : streams) ASSERT_TRUE(stream->waitSubscribed());
  const v1::ListTopicsResponse topics = listTopics("robots/limits/");
  ASSERT_EQ(topics.topics_size(), 1);
  EXPECT_EQ(topics.topics(0).subscriber_count(), static_cast<uint32_t>(kLimit));

  // One call more on that connection waits for a free stream...
  EXPECT_EQ(listTopicsWithin(full, seconds(3)).error_code(), grpc::StatusCode::DEADLINE_EXCEEDED);
  // ...while another connection, of the same client, is served.
  EXPECT_TRUE(listTopicsWithin(makeChannel(broker_.address()), seconds(10)).ok());
  // A stream that ends frees its place.
  streams.front()->cancel();
  EXPECT_EQ(streams.front()->finish().error_code(), grpc::StatusCode::CANCELLED);
  EXPECT_TRUE(listTopicsWithin(full, seconds(10)).ok());
  for (auto& stream : streams) stream->cancel();
}

TEST_F(ChannelBrokerTest, AClientThatPingsTooOftenIsDisconnected) {
  // Pings every 100 ms, also without data: the server allows one per 10 s
  // (ServerLimits::kMinClientPingIntervalMs) and closes the connection after
  // two strikes with GOAWAY too_many_pings.
  grpc::ChannelArguments args;
  args.SetInt(GRPC_ARG_USE_LOCAL_SUBCHANNEL_POOL, 1);
  args.SetInt(GRPC_ARG_KEEPALIVE_TIME_MS, 100);
  args.SetInt(GRPC_ARG_KEEPALIVE_TIMEOUT_MS, 20'000);
  args.SetInt(GRPC_ARG_KEEPALIVE_PERMIT_WITHOUT_CALLS, 1);
  args.SetInt(GRPC_ARG_HTTP2_MAX_PINGS_WITHOUT_DATA, 0);
  const auto pinging =
      grpc::CreateCustomChannel(broker_.address(), grpc::InsecureChannelCredentials(), args);
  RawSubscriber abusive(pinging, subscribeRequest("robots/limits/pings"), seconds(60));
  RawSubscriber polite(makeChannel(broker_.address()), subscribeRequest("robots/limits/pings"),
                       seconds(60));
  ASSERT_TRUE(abusive.waitSubscribed());
  ASSERT_TRUE(polite.waitSubscribed());

  v1::SubscribeResponse response;
  EXPECT_FALSE(abusive.read(&response));  // the stream ends: no sample was published
  const grpc::Status ended = abusive.finish();
  EXPECT_EQ(ended.error_code(), grpc::StatusCode::UNAVAILABLE) << ended.error_message();

  // The polite client's stream on its own connection goes on.
  ASSERT_TRUE(publishOnce(channel_, publishRequest("robots/limits/pings", text("after"))).ok());
  ASSERT_TRUE(polite.read(&response));
  v1::Text got;
  ASSERT_TRUE(response.sample().UnpackTo(&got));
  EXPECT_EQ(got.text(), "after");
  polite.cancel();
}

}  // namespace
}  // namespace behaviorlib::channel
