// The data channel's broker built in-process (channel::Broker on a gRPC
// server of the test), driven by the real ChannelClient over loopback: a
// sample published is the latest and reaches a subscriber; shutting the
// broker down ends the subscription's stream UNAVAILABLE, which the client
// reports; a new topic beyond the broker's cap is RESOURCE_EXHAUSTED;
// ListTopics pages the topics, and the client reads every page.

#include <gmock/gmock.h>
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>
#include <prometheus/registry.h>

#include <chrono>
#include <condition_variable>
#include <cstdio>
#include <mutex>
#include <thread>

#include "behaviorlib/channel/broker.h"
#include "behaviorlib/channel/channel_client.h"
#include "behaviorlib/v1/channel.grpc.pb.h"
#include "behaviorlib/v1/types.pb.h"
#include "support/paging.h"

namespace behaviorlib::channel {
namespace {

using ::testing::ElementsAre;

class BrokerInProcessTest : public ::testing::Test {
 protected:
  void SetUp() override {
    grpc::ServerBuilder builder;
    builder.AddListeningPort("127.0.0.1:0", grpc::InsecureServerCredentials(), &port_);
    builder.RegisterService(&broker_);
    server_ = builder.BuildAndStart();
    ASSERT_NE(server_, nullptr);
    ASSERT_GT(port_, 0);
    client_ = std::make_unique<ChannelClient>("127.0.0.1:" + std::to_string(port_));
  }
  void TearDown() override {
    client_.reset();
    broker_.shutdown();
    server_->Shutdown(std::chrono::system_clock::now() + std::chrono::milliseconds(500));
  }

  prometheus::Registry registry_;
  Broker broker_{registry_};
  int port_ = 0;
  std::unique_ptr<grpc::Server> server_;
  std::unique_ptr<ChannelClient> client_;
};

v1::Altitude altitude(double metres) {
  v1::Altitude sample;
  sample.set_altitude_m(metres);
  return sample;
}

TEST_F(BrokerInProcessTest, APublishedSampleIsTheLatestAndReachesASubscriber) {
  EXPECT_EQ(client_->getLatest("robots/r/baro").status().code(), absl::StatusCode::kNotFound);

  std::mutex mutex;
  std::condition_variable arrived;
  std::vector<double> received;
  auto subscription = client_->subscribeTyped<v1::Altitude>(
      "robots/r/baro", {.mode = v1::DELIVERY_MODE_QUEUE, .queue_size = 10},
      [&](const v1::Altitude& a) {
        std::lock_guard lock(mutex);
        received.push_back(a.altitude_m());
        arrived.notify_all();
      });
  // Once connected, every published sample reaches the subscription.
  ASSERT_TRUE(subscription->waitConnected(std::chrono::seconds(10)));
  ASSERT_TRUE(client_->publish("robots/r/baro", altitude(12.5)).ok());
  std::unique_lock lock(mutex);
  arrived.wait_for(lock, std::chrono::seconds(10), [&] { return !received.empty(); });
  ASSERT_FALSE(received.empty());
  EXPECT_EQ(received.front(), 12.5);
  lock.unlock();

  auto latest = client_->getLatest("robots/r/baro");
  ASSERT_TRUE(latest.ok()) << latest.status();
  v1::Altitude read;
  ASSERT_TRUE(latest->sample().UnpackTo(&read));
  EXPECT_EQ(read.altitude_m(), 12.5);
}

TEST_F(BrokerInProcessTest, ShutdownEndsTheSubscriptionsStream) {
  // On a gRPC stream (a ring's reader sees its ring closed first and ends
  // the stream itself, CANCELLED).
  auto subscription = client_->subscribeTyped<v1::Altitude>(
      "robots/r/baro", {.shared_memory = false}, [](const v1::Altitude&) {});
  ASSERT_TRUE(subscription->waitConnected(std::chrono::seconds(10)));
  broker_.shutdown();
  for (int i = 0; i < 200 && subscription->connected(); ++i) {
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  EXPECT_FALSE(subscription->connected());
  EXPECT_EQ(subscription->status().code(), absl::StatusCode::kUnavailable)
      << subscription->status();
}

// ListTopics pages the topics, and the client reads every page. two a page, in name order, each topic under
// the prefix once, the last page without a next_page_token; a page_token the
// broker did not give is INVALID_ARGUMENT.
TEST_F(BrokerInProcessTest, ListTopicsPagesEveryTopicOnce) {
  for (const std::string topic :
       {"robots/r/e", "robots/r/a", "robots/q/c", "robots/r/d", "robots/r/b", "robots/r/c"}) {
    ASSERT_TRUE(client_->publish(topic, altitude(1)).ok()) << topic;
  }
  // Closing the publish stream returns once the broker took every sample.
  auto accepted = client_->flush();
  ASSERT_TRUE(accepted.ok()) << accepted.status();
  ASSERT_EQ(*accepted, 6u);
  auto stub = v1::DataChannel::NewStub(grpc::CreateChannel("127.0.0.1:" + std::to_string(port_),
                                                           grpc::InsecureChannelCredentials()));
  const auto topics = [](const v1::ListTopicsResponse& r) -> const auto& { return r.topics(); };
  const auto name = [](const v1::TopicInfo& t) { return t.name(); };
  v1::ListTopicsRequest request;
  request.set_prefix("robots/r/");
  request.set_page_size(2);
  std::vector<std::vector<std::string>> pages;
  grpc::Status status =
      support::pageKeys(*stub, &v1::DataChannel::Stub::ListTopics, request, topics, name, &pages);
  ASSERT_TRUE(status.ok()) << status.error_message();
  EXPECT_THAT(pages,
              ElementsAre(ElementsAre("robots/r/a", "robots/r/b"),
                          ElementsAre("robots/r/c", "robots/r/d"), ElementsAre("robots/r/e")));

  request.set_page_token("not-a-token");
  status =
      support::pageKeys(*stub, &v1::DataChannel::Stub::ListTopics, request, topics, name, &pages);
  EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << status.error_message();
}

// The client reads every page: more topics than the broker puts on one
// (1000 at most).
TEST_F(BrokerInProcessTest, TheClientListsTopicsBeyondOnePage) {
  constexpr int kTopics = 1205;
  for (int i = 0; i < kTopics; ++i) {
    char topic[32];
    std::snprintf(topic, sizeof(topic), "robots/many/%04d", i);
    ASSERT_TRUE(client_->publish(topic, altitude(i)).ok()) << topic;
  }
  ASSERT_TRUE(client_->publish("robots/other/x", altitude(0)).ok());
  auto accepted = client_->flush();
  ASSERT_TRUE(accepted.ok()) << accepted.status();
  auto listed = client_->listTopics("robots/many/");
  ASSERT_TRUE(listed.ok()) << listed.status();
  ASSERT_EQ(listed->size(), static_cast<size_t>(kTopics));
  for (int i = 0; i < kTopics; ++i) {
    char topic[32];
    std::snprintf(topic, sizeof(topic), "robots/many/%04d", i);
    EXPECT_EQ((*listed)[static_cast<size_t>(i)].name(), topic);
  }
}

TEST(BrokerLimitsTest, ANewTopicBeyondTheCapIsResourceExhausted) {
  prometheus::Registry registry;
  Broker broker(registry, {.shared_memory = false, .max_topics = 2});
  grpc::ServerBuilder builder;
  int port = 0;
  builder.AddListeningPort("127.0.0.1:0", grpc::InsecureServerCredentials(), &port);
  builder.RegisterService(&broker);
  std::unique_ptr<grpc::Server> server = builder.BuildAndStart();
  ASSERT_NE(server, nullptr);
  {
    ChannelClient client("127.0.0.1:" + std::to_string(port));
    ASSERT_TRUE(client.publish("robots/r/a", altitude(1)).ok());
    ASSERT_TRUE(client.publish("robots/r/b", altitude(2)).ok());
    // The publish stream is asynchronous: the refusal ends it, and flush()
    // (or the next publish) returns it.
    absl::Status third = client.publish("robots/r/c", altitude(3));
    if (third.ok()) third = client.flush().status();
    EXPECT_EQ(third.code(), absl::StatusCode::kResourceExhausted) << third;
    EXPECT_NE(third.message().find("2 topics"), absl::string_view::npos) << third;
    // The topics it keeps still take samples.
    EXPECT_TRUE(client.publish("robots/r/a", altitude(4)).ok());
    EXPECT_EQ(client.getLatest("robots/r/c").status().code(), absl::StatusCode::kNotFound);
  }
  broker.shutdown();
  server->Shutdown(std::chrono::system_clock::now() + std::chrono::milliseconds(500));
}

}  // namespace
}  // namespace behaviorlib::channel
