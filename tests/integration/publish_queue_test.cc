// The simulator's PublishQueue against a real channel_broker: the thread
// publishes what is pushed (free running); flushed by the caller (the
// deterministic mode), nothing goes out before flush(), which publishes on
// the caller's thread and, with sync, returns once the broker numbered it.

#include "simulator/service/publish_queue.h"

#include <gtest/gtest.h>

#include <chrono>
#include <map>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "behaviorlib/channel/channel_client.h"
#include "behaviorlib/v1/types.pb.h"
#include "simulator/service/channel_routes.h"
#include "support/server_process.h"

namespace behaviorlib::sim {
namespace {

std::unique_ptr<v1::Text> text(const std::string& s) {
  auto t = std::make_unique<v1::Text>();
  t->set_text(s);
  return t;
}

class PublishQueueTest : public ::testing::Test {
 protected:
  void SetUp() override {
    ASSERT_TRUE(broker_.start()) << broker_.error();
    routes_ = std::make_unique<ChannelRoutes>(broker_.address());
    reader_ = std::make_unique<channel::ChannelClient>(broker_.address());
  }

  // Samples the broker counted on each topic under robots/q/.
  std::map<std::string, uint64_t> counted() {
    std::map<std::string, uint64_t> out;
    auto topics = reader_->listTopics("robots/q/");
    EXPECT_TRUE(topics.ok()) << topics.status();
    if (topics.ok()) {
      for (const auto& t : *topics) out[t.name()] = t.published_count();
    }
    return out;
  }

  support::ServerProcess broker_{BEHAVIORLIB_CHANNEL_BROKER_PATH, {}};
  std::unique_ptr<ChannelRoutes> routes_;
  std::unique_ptr<channel::ChannelClient> reader_;
};

TEST_F(PublishQueueTest, FlushedByTheCallerNothingGoesOutBeforeFlush) {
  PublishQueue queue(*routes_, {}, /*flushed_by_caller=*/true);
  queue.push("robots/q/a", text("a1"));
  queue.push("robots/q/b", text("b1"));
  queue.push("robots/q/a", text("a2"));
  // Whatever the thread does meanwhile, it does not publish.
  std::this_thread::sleep_for(std::chrono::milliseconds(200));
  EXPECT_TRUE(counted().empty());
  EXPECT_EQ(queue.publishedCount(), 0u);

  ASSERT_TRUE(queue.flush(/*sync=*/true).ok());
  // Synced: the broker took and numbered all three when flush returned.
  EXPECT_EQ(counted(), (std::map<std::string, uint64_t>{{"robots/q/a", 2}, {"robots/q/b", 1}}));
  EXPECT_EQ(queue.publishedCount(), 3u);
  EXPECT_EQ(routes_->acceptedSeqsByDomain().at(""),
            (std::map<std::string, uint64_t>{{"robots/q/a", 2}, {"robots/q/b", 1}}));
  // An empty queue with sync is a sync alone; without, nothing.
  ASSERT_TRUE(queue.flush(true).ok());
  ASSERT_TRUE(queue.flush(false).ok());
  // Without sync the samples are written; a later sync covers them.
  queue.push("robots/q/b", text("b2"));
  ASSERT_TRUE(queue.flush(false).ok());
  ASSERT_TRUE(routes_->sync().ok());
  EXPECT_EQ(counted().at("robots/q/b"), 2u);
}

// A sample held while nobody wanted its topic, released when a subscriber
// comes, is not left for the next flush (the stepping thread may be waiting
// for time to start, or for a follower): the queue's thread sends it.
TEST_F(PublishQueueTest, FlushedByTheCallerASampleReleasedByInterestGoesAtOnce) {
  PublishQueue queue(*routes_, {}, /*flushed_by_caller=*/true);
  routes_->gatePublishing("robots/");
  routes_->watchInterest("robots/", [&queue] { queue.interestChanged(); });
  // The watch ends before the queue its callback names (declared after it).
  struct StopWatching {
    ChannelRoutes& routes;
    ~StopWatching() { routes.stopWatching(); }
  } stop_watching{*routes_};
  queue.setInterest(routes_.get());
  const auto known_by = std::chrono::steady_clock::now() + std::chrono::seconds(10);
  while (!routes_->known() && std::chrono::steady_clock::now() < known_by) {
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  ASSERT_TRUE(routes_->known()) << "the broker's interest watch";
  queue.push("robots/q/held", text("first"));  // a topic's first sample announces it
  ASSERT_TRUE(queue.flush(true).ok());
  queue.push("robots/q/held", text("newest"));  // nobody wants it: held
  ASSERT_TRUE(queue.flush(true).ok());
  EXPECT_EQ(counted().at("robots/q/held"), 1u);
  std::mutex mutex;
  std::vector<std::string> got;
  auto sub = reader_->subscribeTyped<v1::Text>("robots/q/held", {}, [&](const v1::Text& t) {
    std::lock_guard lock(mutex);
    got.push_back(t.text());
  });
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(10);
  while (std::chrono::steady_clock::now() < deadline) {
    {
      std::lock_guard lock(mutex);
      if (!got.empty() && got.back() == "newest") break;
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  std::lock_guard lock(mutex);
  ASSERT_FALSE(got.empty());
  EXPECT_EQ(got.back(), "newest") << "sent without a flush";
}

TEST_F(PublishQueueTest, ALongQueueGoesInSeveralBatchesTheLastOneSynced) {
  PublishQueue queue(*routes_, {}, /*flushed_by_caller=*/true);
  constexpr int kSamples = 1000;  // several batches of at most 256
  for (int i = 0; i < kSamples; ++i) queue.push("robots/q/many", text(std::to_string(i)));
  ASSERT_TRUE(queue.flush(true).ok());
  EXPECT_EQ(counted().at("robots/q/many"), static_cast<uint64_t>(kSamples));
  auto latest = reader_->getLatest("robots/q/many");
  ASSERT_TRUE(latest.ok()) << latest.status();
  v1::Text last;
  ASSERT_TRUE(latest->sample().UnpackTo(&last));
  EXPECT_EQ(last.text(), std::to_string(kSamples - 1)) << "in order";
}

TEST_F(PublishQueueTest, FreeRunningTheThreadPublishesWhatIsPushed) {
  PublishQueue queue(*routes_, {});
  queue.push("robots/q/c", text("c1"));
  ASSERT_TRUE(queue.waitDrained(std::chrono::seconds(10)));
  ASSERT_TRUE(routes_->sync().ok());
  EXPECT_EQ(counted().at("robots/q/c"), 1u);
}

}  // namespace
}  // namespace behaviorlib::sim
