// Integration tests of the brokers' link over NATS (decision 39): a real
// nats-server and real channel_broker processes on loopback, each broker
// standing for one host of a fleet, driven with ChannelClient.

#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <signal.h>
#include <spawn.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <map>
#include <mutex>
#include <regex>
#include <set>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "behaviorlib/channel/channel_client.h"
#include "behaviorlib/channel/nats_link.h"
#include "behaviorlib/v1/channel.pb.h"
#include "behaviorlib/v1/types.pb.h"
#include "support/server_process.h"

extern char** environ;

namespace behaviorlib::channel {
namespace {

using std::chrono::milliseconds;
using std::chrono::seconds;

const char* const kBrokerPath = CHANNEL_BROKER_PATH;

template <class F>
bool eventually(F condition, milliseconds timeout = seconds(10)) {
  const auto deadline = std::chrono::steady_clock::now() + timeout;
  while (std::chrono::steady_clock::now() < deadline) {
    if (condition()) return true;
    std::this_thread::sleep_for(milliseconds(10));
  }
  return condition();
}

// A nats-server on loopback. Its first start picks a free port (-p -1) and
// writes it to a ports file; a restart takes the same port again.
class NatsServer {
 public:
  NatsServer() {
    dir_ = std::filesystem::temp_directory_path() /
           ("behaviorlib-nats-" + std::to_string(getpid()) + "-" + std::to_string(counter_++));
    std::filesystem::create_directories(dir_);
  }
  ~NatsServer() {
    kill();
    std::error_code ignored;
    std::filesystem::remove_all(dir_, ignored);
  }

  bool start() {
    const std::string port = port_ == 0 ? "-1" : std::to_string(port_);
    std::vector<std::string> args = {"nats-server",      "-a",         "127.0.0.1", "-p", port,
                                     "--ports_file_dir", dir_.string()};
    std::vector<char*> argv;
    for (auto& a : args) argv.push_back(a.data());
    argv.push_back(nullptr);
    if (posix_spawnp(&pid_, "nats-server", nullptr, nullptr, argv.data(), environ) != 0) {
      pid_ = -1;
      return false;
    }
    const std::string file = (dir_ / ("nats-server_" + std::to_string(pid_) + ".ports")).string();
    return eventually([&] {
      std::ifstream in(file);
      std::stringstream text;
      text << in.rdbuf();
      std::smatch match;
      const std::string body = text.str();
      if (!std::regex_search(body, match, std::regex(R"(nats://127\.0\.0\.1:(\d+))"))) {
        return false;
      }
      port_ = std::stoi(match[1]);
      return true;
    });
  }

  void kill() {
    if (pid_ <= 0) return;
    ::kill(pid_, SIGKILL);
    int status = 0;
    waitpid(pid_, &status, 0);
    pid_ = -1;
  }

  std::string url() const { return "nats://127.0.0.1:" + std::to_string(port_); }

 private:
  static inline int counter_ = 0;
  std::filesystem::path dir_;
  pid_t pid_ = -1;
  int port_ = 0;
};

bool natsServerInstalled() { return std::system("command -v nats-server > /dev/null") == 0; }

// The value of a metric series on a broker's /metrics (-1: absent).
double metric(const support::ServerProcess& broker, const std::string& series) {
  const std::string body = support::httpGet(broker.metricsPort(), "/metrics");
  std::istringstream lines(body);
  std::string line;
  while (std::getline(lines, line)) {
    if (line.rfind(series + " ", 0) == 0) return std::stod(line.substr(series.size() + 1));
  }
  return -1;
}

v1::Text text(const std::string& s) {
  v1::Text t;
  t.set_text(s);
  return t;
}

class ChannelLinkTest : public ::testing::Test {
 protected:
  void SetUp() override {
    if (!natsServerInstalled()) GTEST_SKIP() << "nats-server is not installed";
    ASSERT_TRUE(nats_.start());
  }

  std::unique_ptr<support::ServerProcess> startBroker(const std::string& name,
                                                      std::vector<std::string> more = {}) {
    std::vector<std::string> args = {"--link-url", nats_.url(), "--link-name", name};
    args.insert(args.end(), more.begin(), more.end());
    auto broker = std::make_unique<support::ServerProcess>(kBrokerPath, args);
    EXPECT_TRUE(broker->start()) << broker->error();
    EXPECT_TRUE(eventually([&] { return metric(*broker, "behaviorlib_channel_link_up") == 1; }))
        << name << " never connected to " << nats_.url();
    return broker;
  }

  // Whether `broker` comes to send what the others want: `count` wants (one
  // per other broker and topic) heard and taken up. A sample published
  // before that would not cross, and no sleep makes sure of it.
  ::testing::AssertionResult hearsWants(const support::ServerProcess& broker, double count) {
    if (eventually([&] { return metric(broker, "behaviorlib_channel_link_wants_heard") == count; }))
      return ::testing::AssertionSuccess();
    return ::testing::AssertionFailure()
           << "the broker heard " << metric(broker, "behaviorlib_channel_link_wants_heard")
           << " wants, not " << count;
  }

  // Collects the texts a subscription receives.
  struct Received {
    std::mutex mutex;
    std::vector<std::string> texts;
    std::size_t size() {
      std::lock_guard<std::mutex> lock(mutex);
      return texts.size();
    }
  };
  std::unique_ptr<Subscription> collect(ChannelClient& client, const std::string& topic,
                                        Received* into) {
    return client.subscribeTyped<v1::Text>(
        topic, {.mode = v1::DELIVERY_MODE_QUEUE, .queue_size = 1000}, [into](const v1::Text& t) {
          std::lock_guard<std::mutex> lock(into->mutex);
          into->texts.push_back(t.text());
        });
  }

  NatsServer nats_;
};

TEST_F(ChannelLinkTest, ATopicWantedOnOneHostIsCarriedFromAnother) {
  auto ground = startBroker("ground");
  auto vehicle = startBroker("drone1");
  ChannelClient ground_client(ground->address());
  ChannelClient vehicle_client(vehicle->address());
  const std::string topic = "robots/drone1/status_text";

  // Before anyone on the ground wants it, the vehicle sends nothing.
  ASSERT_TRUE(vehicle_client.publish(topic, text("unwanted")).ok());
  ASSERT_TRUE(vehicle_client.flush().ok());
  std::this_thread::sleep_for(milliseconds(300));
  EXPECT_LE(metric(*vehicle, "behaviorlib_channel_link_samples_out_total{topic=\"" + topic + "\"}"),
            0);

  // The ground's want reaches the vehicle's broker: its publishers see it.
  // Until its stream has answered, a watch says every topic is wanted: wait
  // for the broker's answer, or the samples below could go before the want
  // has reached the vehicle (and a sample nobody wanted is not carried).
  auto interest = vehicle_client.watchInterest("robots/", [] {});
  ASSERT_TRUE(eventually([&] { return interest->known(); }));
  ASSERT_FALSE(interest->wanted(topic));
  Received received;
  auto sub = collect(ground_client, topic, &received);
  ASSERT_TRUE(sub->waitConnected(seconds(5)));
  ASSERT_TRUE(eventually([&] { return interest->known() && interest->wanted(topic); }))
      << "the vehicle's broker never heard that the ground wants " << topic;

  for (int i = 0; i < 20; ++i)
    ASSERT_TRUE(vehicle_client.publish(topic, text(std::to_string(i))).ok());
  ASSERT_TRUE(vehicle_client.flush().ok());
  ASSERT_TRUE(eventually([&] { return received.size() == 20; }))
      << received.size() << " received; the vehicle sent "
      << metric(*vehicle, "behaviorlib_channel_link_samples_out_total{topic=\"" + topic + "\"}")
      << ", the ground took "
      << metric(*ground, "behaviorlib_channel_link_samples_in_total{topic=\"" + topic + "\"}");
  {
    std::lock_guard<std::mutex> lock(received.mutex);
    for (int i = 0; i < 20; ++i)
      EXPECT_EQ(received.texts[static_cast<std::size_t>(i)], std::to_string(i));
  }
  EXPECT_EQ(metric(*vehicle, "behaviorlib_channel_link_samples_out_total{topic=\"" + topic + "\"}"),
            20);
  EXPECT_EQ(metric(*ground, "behaviorlib_channel_link_samples_in_total{topic=\"" + topic + "\"}"),
            20);
  EXPECT_EQ(metric(*ground, "behaviorlib_channel_link_peers"), 1);

  // The ground stops wanting it: the vehicle's broker stops sending.
  sub.reset();
  ASSERT_TRUE(eventually([&] { return interest->known() && !interest->wanted(topic); }));
  ASSERT_TRUE(vehicle_client.publish(topic, text("late")).ok());
  ASSERT_TRUE(vehicle_client.flush().ok());
  std::this_thread::sleep_for(milliseconds(300));
  EXPECT_EQ(metric(*vehicle, "behaviorlib_channel_link_samples_out_total{topic=\"" + topic + "\"}"),
            20);
}

TEST_F(ChannelLinkTest, ATopicSeveralHostsPublishReachesEachOnceAndNeverComesBack) {
  auto a = startBroker("drone1");
  auto b = startBroker("drone2");
  auto c = startBroker("ground");
  ChannelClient a_client(a->address());
  ChannelClient b_client(b->address());
  ChannelClient c_client(c->address());
  const std::string topic = "robots/swarm/positions";
  Received on_a, on_b, on_c;
  auto sub_a = collect(a_client, topic, &on_a);
  auto sub_b = collect(b_client, topic, &on_b);
  auto sub_c = collect(c_client, topic, &on_c);
  for (auto* sub : {sub_a.get(), sub_b.get(), sub_c.get()})
    ASSERT_TRUE(sub->waitConnected(seconds(5)));
  // Every broker hears the two others want it.
  for (auto* broker : {a.get(), b.get(), c.get()}) {
    ASSERT_TRUE(eventually([&] { return metric(*broker, "behaviorlib_channel_link_peers") == 2; }));
    ASSERT_TRUE(hearsWants(*broker, 2));
  }
  constexpr int kEach = 50;
  for (int i = 0; i < kEach; ++i) {
    ASSERT_TRUE(a_client.publish(topic, text("a" + std::to_string(i))).ok());
    ASSERT_TRUE(b_client.publish(topic, text("b" + std::to_string(i))).ok());
  }
  ASSERT_TRUE(a_client.flush().ok());
  ASSERT_TRUE(b_client.flush().ok());
  for (Received* r : {&on_a, &on_b, &on_c}) {
    ASSERT_TRUE(eventually([&] { return r->size() >= 2 * kEach; })) << r->size();
  }
  std::this_thread::sleep_for(milliseconds(500));  // a duplicate or an echo would arrive by now
  for (Received* r : {&on_a, &on_b, &on_c}) {
    std::lock_guard<std::mutex> lock(r->mutex);
    EXPECT_EQ(r->texts.size(), 2u * kEach);
    const std::set<std::string> distinct(r->texts.begin(), r->texts.end());
    EXPECT_EQ(distinct.size(), 2u * kEach) << "a sample arrived twice";
    // Each publisher's own samples arrive in the order it sent them.
    int next_a = 0, next_b = 0;
    for (const auto& t : r->texts) {
      if (t[0] == 'a') {
        EXPECT_EQ(t, "a" + std::to_string(next_a++));
      } else {
        EXPECT_EQ(t, "b" + std::to_string(next_b++));
      }
    }
  }
  // Nothing went back out: each broker sent only its own publisher's.
  EXPECT_EQ(metric(*a, "behaviorlib_channel_link_samples_out_total{topic=\"" + topic + "\"}"),
            kEach);
  EXPECT_EQ(metric(*b, "behaviorlib_channel_link_samples_out_total{topic=\"" + topic + "\"}"),
            kEach);
  EXPECT_LE(metric(*c, "behaviorlib_channel_link_samples_out_total{topic=\"" + topic + "\"}"), 0);
}

TEST_F(ChannelLinkTest, GetLatestOfAnotherHostsTopicWaitsForItsSample) {
  auto ground = startBroker("ground");
  auto vehicle = startBroker("drone1");
  ChannelClient ground_client(ground->address());
  ChannelClient vehicle_client(vehicle->address());
  const std::string topic = "robots/drone1/battery_text";
  // A publisher on the vehicle that publishes while its topic is wanted
  // (as the simulator does), a sample every 50 ms.
  std::atomic<bool> stop{false};
  std::thread publisher([&] {
    int i = 0;
    while (!stop.load()) {
      (void)vehicle_client.publish(topic, text("p" + std::to_string(i++)));
      std::this_thread::sleep_for(milliseconds(50));
    }
  });
  // The first call makes the topic wanted on every host and waits up to 1 s
  // for a sample to cross; on a busy machine a second call gets it (the
  // topic stays wanted for 2 s after each call).
  auto latest = ground_client.getLatest(topic, seconds(5));
  for (int attempt = 1; attempt < 5 && !latest.ok(); ++attempt) {
    latest = ground_client.getLatest(topic, seconds(5));
  }
  stop.store(true);
  publisher.join();
  ASSERT_TRUE(latest.ok()) << latest.status();
  v1::Text got;
  ASSERT_TRUE(latest->sample().UnpackTo(&got));
  EXPECT_EQ(got.text().substr(0, 1), "p");
  // A name only ever asked for is not kept: once the interest lapses, a
  // topic nothing reached on this host is gone from the ground's list.
  auto never = ground_client.getLatest("robots/drone9/nothing", seconds(3));
  EXPECT_EQ(never.status().code(), absl::StatusCode::kNotFound) << never.status();
  ASSERT_TRUE(eventually(
      [&] {
        auto topics = ground_client.listTopics("robots/drone9/");
        return topics.ok() && topics->empty();
      },
      seconds(6)));
}

TEST_F(ChannelLinkTest, LocalPrefixesNeverCross) {
  auto sim_side = startBroker("simhost");
  auto vehicle = startBroker("drone1", {"--link-local", "clock"});
  ChannelClient sim_client(sim_side->address());
  ChannelClient vehicle_client(vehicle->address());
  std::atomic<int> clock_samples{0};
  auto sub = vehicle_client.subscribeTyped<v1::Clock>(
      "clock", {}, [&](const v1::Clock&) { clock_samples.fetch_add(1); });
  ASSERT_TRUE(sub->waitConnected(seconds(5)));
  Received texts;
  auto other = collect(vehicle_client, "robots/drone1/note", &texts);
  ASSERT_TRUE(hearsWants(*sim_side, 1));
  v1::Clock clock;
  clock.mutable_time()->set_seconds(1);
  for (int i = 0; i < 5; ++i) {
    ASSERT_TRUE(sim_client.publish("clock", clock).ok());
    ASSERT_TRUE(sim_client.publish("robots/drone1/note", text("n")).ok());
  }
  ASSERT_TRUE(sim_client.flush().ok());
  ASSERT_TRUE(eventually([&] { return texts.size() == 5; }));
  std::this_thread::sleep_for(milliseconds(300));
  EXPECT_EQ(clock_samples.load(), 0) << "the vehicle's clock is its own";
}

TEST_F(ChannelLinkTest, ALostServerIsDetectedAndTheLinkRecovers) {
  auto ground = startBroker("ground");
  auto vehicle = startBroker("drone1");
  ChannelClient ground_client(ground->address());
  ChannelClient vehicle_client(vehicle->address());
  const std::string topic = "robots/drone1/heartbeat_text";
  Received received;
  auto sub = collect(ground_client, topic, &received);
  ASSERT_TRUE(sub->waitConnected(seconds(5)));
  ASSERT_TRUE(hearsWants(*vehicle, 1));
  ASSERT_TRUE(vehicle_client.publish(topic, text("before")).ok());
  ASSERT_TRUE(eventually([&] { return received.size() == 1; }));

  nats_.kill();
  const auto lost = std::chrono::steady_clock::now();
  ASSERT_TRUE(eventually([&] { return metric(*vehicle, "behaviorlib_channel_link_up") == 0; }));
  EXPECT_LT(std::chrono::steady_clock::now() - lost, seconds(5));
  // Both brokers keep serving their own host.
  ASSERT_TRUE(vehicle_client.publish(topic, text("during")).ok());
  ASSERT_TRUE(vehicle_client.flush().ok());

  ASSERT_TRUE(nats_.start());
  const auto back = std::chrono::steady_clock::now();
  ASSERT_TRUE(eventually([&] {
    return metric(*vehicle, "behaviorlib_channel_link_up") == 1 &&
           metric(*ground, "behaviorlib_channel_link_up") == 1;
  }));
  EXPECT_GE(metric(*vehicle, "behaviorlib_channel_link_disconnects_total"), 1);
  // The wants are announced again and samples flow: within a few seconds.
  ASSERT_TRUE(eventually(
      [&] {
        (void)vehicle_client.publish(topic, text("after"));
        std::lock_guard<std::mutex> lock(received.mutex);
        return !received.texts.empty() && received.texts.back() == "after";
      },
      seconds(10)));
  EXPECT_LT(std::chrono::steady_clock::now() - back, seconds(5));
}

TEST_F(ChannelLinkTest, ARateLimitSendsTheNewestSampleInItsTurn) {
  auto ground = startBroker("ground");
  auto vehicle = startBroker("drone1", {"--link-max-rate-hz", "10"});
  ChannelClient ground_client(ground->address());
  ChannelClient vehicle_client(vehicle->address());
  const std::string topic = "robots/drone1/fast_text";
  Received received;
  auto sub = collect(ground_client, topic, &received);
  ASSERT_TRUE(sub->waitConnected(seconds(5)));
  ASSERT_TRUE(hearsWants(*vehicle, 1));
  // 100 samples in about half a second: at most 10 a second cross, and the
  // last one always does, once its turn comes.
  const auto start = std::chrono::steady_clock::now();
  for (int i = 0; i < 100; ++i) {
    ASSERT_TRUE(vehicle_client.publish(topic, text(std::to_string(i))).ok());
    std::this_thread::sleep_for(milliseconds(5));
  }
  ASSERT_TRUE(vehicle_client.flush().ok());
  ASSERT_TRUE(eventually([&] {
    std::lock_guard<std::mutex> lock(received.mutex);
    return !received.texts.empty() && received.texts.back() == "99";
  })) << "the newest sample never crossed";
  const double elapsed_s =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  std::this_thread::sleep_for(milliseconds(300));
  const std::size_t crossed = received.size();
  EXPECT_LE(static_cast<double>(crossed), 10.0 * elapsed_s + 2) << crossed << " in " << elapsed_s;
  EXPECT_GE(crossed, 2u);
  EXPECT_GE(metric(*vehicle, "behaviorlib_channel_link_thinned_samples_total"),
            100.0 - crossed - 1);
}

TEST_F(ChannelLinkTest, ARateLimitedLinkSendsItsTopicsTogetherInFrames) {
  auto ground = startBroker("ground");
  auto vehicle = startBroker("drone1", {"--link-max-rate-hz", "10"});
  ChannelClient ground_client(ground->address());
  ChannelClient vehicle_client(vehicle->address());
  const std::string a = "robots/drone1/frame_a";
  const std::string b = "robots/drone1/frame_b";
  Received got_a;
  Received got_b;
  auto sub_a = collect(ground_client, a, &got_a);
  auto sub_b = collect(ground_client, b, &got_b);
  ASSERT_TRUE(sub_a->waitConnected(seconds(5)));
  ASSERT_TRUE(sub_b->waitConnected(seconds(5)));
  ASSERT_TRUE(hearsWants(*vehicle, 2));
  // Two topics, interleaved, 50 samples each in about a second.
  const auto start = std::chrono::steady_clock::now();
  for (int i = 0; i < 50; ++i) {
    ASSERT_TRUE(vehicle_client.publish(a, text(std::to_string(i))).ok());
    std::this_thread::sleep_for(milliseconds(10));
    ASSERT_TRUE(vehicle_client.publish(b, text(std::to_string(i))).ok());
    std::this_thread::sleep_for(milliseconds(10));
  }
  ASSERT_TRUE(vehicle_client.flush().ok());
  for (Received* got : {&got_a, &got_b}) {
    ASSERT_TRUE(eventually([&] {
      std::lock_guard<std::mutex> lock(got->mutex);
      return !got->texts.empty() && got->texts.back() == "49";
    })) << "a topic's newest sample never crossed";
  }
  const double elapsed_s =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  const double frames = metric(*vehicle, "behaviorlib_channel_link_frames_total");
  const double sent =
      metric(*vehicle, "behaviorlib_channel_link_samples_out_total{topic=\"" + a + "\"}") +
      metric(*vehicle, "behaviorlib_channel_link_samples_out_total{topic=\"" + b + "\"}");
  EXPECT_GE(frames, 2.0);
  EXPECT_LE(frames, 10.0 * elapsed_s + 2) << frames << " frames in " << elapsed_s << " s";
  // Frames carried both topics: more samples went than frames.
  EXPECT_GT(sent, frames) << sent << " samples in " << frames << " frames";
}

TEST_F(ChannelLinkTest, BadLinkOptionsAreRefusedAtStart) {
  support::ServerProcess bad_name(kBrokerPath, {"--link-url", nats_.url(), "--link-name", "a.b"});
  EXPECT_FALSE(bad_name.start(seconds(5)));
  EXPECT_NE(bad_name.wait(seconds(5)), 0);
  support::ServerProcess half_tls(
      kBrokerPath, {"--link-url", nats_.url(), "--link-name", "a", "--link-tls-cert", "/x.pem"});
  EXPECT_FALSE(half_tls.start(seconds(5)));
  EXPECT_NE(half_tls.wait(seconds(5)), 0);
}

TEST(NatsSubjects, TopicsMapToSubjectsAndBack) {
  EXPECT_EQ(topicSubject("robots/drone1/pose"), "bl.t.robots.drone1.pose");
  EXPECT_EQ(topicSubject("robots/d.1/cam/front.left"), "bl.t.robots.d~1.cam.front~left");
  EXPECT_EQ(subjectTopic("bl.t.robots.d~1.cam.front~left"), "robots/d.1/cam/front.left");
  EXPECT_EQ(subjectTopic("bl.t.clock"), "clock");
  EXPECT_EQ(subjectTopic("bl.want.x"), std::nullopt);
  EXPECT_EQ(subjectTopic("bl.t.robots..x"), std::nullopt);
  EXPECT_EQ(subjectTopic("bl.t.nothere.x"), std::nullopt);
}

}  // namespace
}  // namespace behaviorlib::channel
