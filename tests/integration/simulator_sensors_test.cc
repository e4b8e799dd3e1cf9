// The simulator's sensors on the real data channel: the simulator binary and
// the channel broker as real processes on free loopback ports, the simulator
// in lock-step so that simulated time advances only through Simulator.Step.
// Checks each topic's type, header and rate in simulated time, that the
// camera renders only while subscribed (and shows the world's QR marker),
// and that a seed reproduces the samples bit for bit.

#include <google/protobuf/descriptor.h>
#include <google/protobuf/message.h>
#include <google/protobuf/util/time_util.h>
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>

#include <chrono>
#include <cmath>
#include <fstream>
#include <map>
#include <mutex>
#include <opencv2/imgcodecs.hpp>
#include <string>
#include <thread>
#include <vector>

#include "behaviorlib/channel/channel_client.h"
#include "behaviorlib/v1/channel.grpc.pb.h"
#include "behaviorlib/v1/platform.grpc.pb.h"
#include "behaviorlib/v1/simulator.grpc.pb.h"
#include "behaviorlib/v1/types.pb.h"
#include "simulator/world/camera.h"  // decodeQr
#include "support/server_process.h"

namespace {

namespace v1 = behaviorlib::v1;
using google::protobuf::util::TimeUtil;
using std::chrono::milliseconds;
using std::chrono::seconds;

constexpr char kMarkerText[] = "behaviorlib sensor integration";

std::unique_ptr<grpc::ClientContext> deadline(seconds s = seconds(10)) {
  auto context = std::make_unique<grpc::ClientContext>();
  context->set_deadline(std::chrono::system_clock::now() + s);
  return context;
}

template <class F>
bool eventually(F condition, milliseconds timeout = seconds(10)) {
  const auto end = std::chrono::steady_clock::now() + timeout;
  while (std::chrono::steady_clock::now() < end) {
    if (condition()) return true;
    std::this_thread::sleep_for(milliseconds(10));
  }
  return condition();
}

/// A panel 3 m ahead of drone1 (which starts landed at the origin facing
/// +x) with a QR marker the camera sees.
std::string writeWorld() {
  const std::string path = ::testing::TempDir() + "/sensor_test_world.yaml";
  std::ofstream out(path);
  out << "name: sensor_test\n"
         "boxes:\n"
         "  - name: panel\n"
         "    center_m: [3.1, 0, 1.5]\n"
         "    size_m: [0.2, 4, 3]\n"
         "markers:\n"
         "  - name: m\n"
         "    text: \""
      << kMarkerText
      << "\"\n"
         "    center_m: [3.0, 0, 0.5]\n"
         "    normal: [-1, 0, 0]\n"
         "    size_m: 0.8\n"
         "    attached_to: panel\n"
         "start_poses:\n"
         "  - robot_id: drone1\n"
         "    position_m: [0, 0, 0]\n";
  return path;
}

/// One received sample: its header, type and bytes.
struct Record {
  std::string type;
  v1::Header header;
  std::string bytes;  ///< the serialized message
};

/// Records every sample of some topics (queued subscriptions, so that
/// nothing is lost).
class Recorder {
 public:
  Recorder(behaviorlib::channel::ChannelClient& client, const std::vector<std::string>& topics) {
    for (const std::string& topic : topics) {
      subscriptions_.push_back(client.subscribe(
          topic, {.mode = v1::DELIVERY_MODE_QUEUE, .queue_size = 10000},
          [this, topic](const v1::SubscribeResponse& response) { record(topic, response); }));
    }
  }
  bool waitConnected() {
    for (const auto& s : subscriptions_) {
      if (!s->waitConnected(seconds(10))) return false;
    }
    return true;
  }
  std::vector<Record> of(const std::string& topic) {
    std::lock_guard lock(mutex_);
    return records_[topic];
  }
  /// Waits (wall time) until `topic` has a sample stamped at or after `stamp`.
  bool waitForStamp(const std::string& topic, int64_t stamp_ns) {
    return eventually([&] {
      std::lock_guard lock(mutex_);
      const auto& r = records_[topic];
      return !r.empty() && TimeUtil::TimestampToNanoseconds(r.back().header.stamp()) >= stamp_ns;
    });
  }
  void clear() {
    std::lock_guard lock(mutex_);
    records_.clear();
  }

 private:
  void record(const std::string& topic, const v1::SubscribeResponse& response) {
    Record record;
    const std::string& url = response.sample().type_url();
    record.type = url.substr(url.rfind('/') + 1);
    record.bytes = response.sample().value();
    // Every data type has `Header header = 1`.
    const auto* descriptor =
        google::protobuf::DescriptorPool::generated_pool()->FindMessageTypeByName(record.type);
    if (descriptor != nullptr) {
      std::unique_ptr<google::protobuf::Message> message(
          google::protobuf::MessageFactory::generated_factory()->GetPrototype(descriptor)->New());
      const auto* field = descriptor->FindFieldByName("header");
      if (message->ParseFromString(record.bytes) && field != nullptr) {
        record.header.CopyFrom(message->GetReflection()->GetMessage(*message, field));
      }
    }
    std::lock_guard lock(mutex_);
    records_[topic].push_back(std::move(record));
  }

  std::mutex mutex_;
  std::map<std::string, std::vector<Record>> records_;
  std::vector<std::unique_ptr<behaviorlib::channel::Subscription>> subscriptions_;
};

class SimulatorSensorsTest : public ::testing::Test {
 protected:
  void SetUp() override {
    ASSERT_TRUE(broker_.start()) << broker_.error();
    simulator_ = std::make_unique<support::ServerProcess>(
        BEHAVIORLIB_SIMULATOR_PATH,
        std::vector<std::string>{"--channel", broker_.address(), "--world", writeWorld(),
                                 "--lock-step", "--seed", "5"});
    ASSERT_TRUE(simulator_->start()) << simulator_->error();
    auto channel = grpc::CreateChannel(simulator_->address(), grpc::InsecureChannelCredentials());
    sim_ = v1::Simulator::NewStub(channel);
    flight_ = v1::FlightController::NewStub(channel);
    client_ = std::make_unique<behaviorlib::channel::ChannelClient>(broker_.address());
  }

  /// Advances simulated time by `ms` (lock-step); the new time in ns.
  int64_t step(int ms) {
    v1::StepRequest request;
    *request.mutable_duration() = TimeUtil::MillisecondsToDuration(ms);
    v1::StepResponse response;
    const grpc::Status status = sim_->Step(deadline().get(), request, &response);
    EXPECT_TRUE(status.ok()) << status.error_message();
    return TimeUtil::TimestampToNanoseconds(response.time());
  }

  std::map<std::string, v1::TopicInfo> topics() {
    std::map<std::string, v1::TopicInfo> out;
    auto listed = client_->listTopics("robots/drone1/");
    EXPECT_TRUE(listed.ok()) << listed.status();
    if (listed.ok()) {
      for (const auto& topic : *listed) out[topic.name()] = topic;
    }
    return out;
  }

  support::ServerProcess broker_{BEHAVIORLIB_CHANNEL_BROKER_PATH, {}};
  std::unique_ptr<support::ServerProcess> simulator_;
  std::unique_ptr<v1::Simulator::Stub> sim_;
  std::unique_ptr<v1::FlightController::Stub> flight_;
  std::unique_ptr<behaviorlib::channel::ChannelClient> client_;
};

struct Expected {
  std::string topic;
  std::string type;
  std::string frame;
  int rate_hz;
};

TEST_F(SimulatorSensorsTest, EveryTopicCarriesItsTypeAtItsRateInSimulatedTime) {
  const std::vector<Expected> expected = {
      {"robots/drone1/imu", "behaviorlib.v1.Imu", "base_link", 200},
      {"robots/drone1/gps", "behaviorlib.v1.PositionFix", "world", 10},
      {"robots/drone1/baro", "behaviorlib.v1.Altitude", "world", 25},
      {"robots/drone1/linear_speed", "behaviorlib.v1.TwistStamped", "base_link", 30},
      {"robots/drone1/battery", "behaviorlib.v1.BatteryState", "base_link", 2},
      {"robots/drone1/lidar/scan", "behaviorlib.v1.LaserScan", "lidar", 10},
      {"robots/drone1/camera/info", "behaviorlib.v1.CameraInfo", "camera", 1},
  };
  std::vector<std::string> names;
  for (const auto& e : expected) names.push_back(e.topic);
  Recorder recorder(*client_, names);
  ASSERT_TRUE(recorder.waitConnected());

  for (int i = 0; i < 4; ++i) step(500);  // 2 s of simulated time
  for (const auto& e : expected) {
    ASSERT_TRUE(recorder.waitForStamp(e.topic, 2'000'000'000)) << e.topic;
  }
  const auto listed = topics();
  for (const auto& e : expected) {
    SCOPED_TRACE(e.topic);
    const auto records = recorder.of(e.topic);
    ASSERT_FALSE(records.empty());
    // Samples are due at k / rate for k = 1, 2, ...: 2 s hold 2 * rate,
    // numbered from 0. The simulator publishes a topic's first sample (it
    // makes the topic known), then holds the others until it learns that the
    // topic is wanted (the broker's interest, decision 17), which may come
    // after the first steps on a busy machine. So the samples received are
    // perhaps seq 0, then the last ones, every one, up to the 2 s.
    std::size_t begin = 0;
    if (records.size() > 1 && records[0].header.seq() == 0 && records[1].header.seq() != 1) {
      begin = 1;
    }
    const std::size_t first = records[begin].header.seq();
    ASSERT_EQ(first + records.size() - begin, static_cast<std::size_t>(2 * e.rate_hz));
    for (std::size_t i = 0; i < records.size(); ++i) {
      const std::size_t k = i < begin ? 0 : first + i - begin;
      EXPECT_EQ(records[i].type, e.type);
      EXPECT_EQ(records[i].header.frame_id(), e.frame);
      EXPECT_EQ(records[i].header.robot_id(), "drone1");
      EXPECT_EQ(records[i].header.seq(), k);
      // At the first 1 ms physics step at or after the due time.
      const int64_t due_ns = static_cast<int64_t>(std::llround(1e9 / e.rate_hz)) * (k + 1);
      const int64_t stamp_ns = TimeUtil::TimestampToNanoseconds(records[i].header.stamp());
      EXPECT_GE(stamp_ns, due_ns);
      EXPECT_LT(stamp_ns, due_ns + 1'000'000);
    }
    ASSERT_TRUE(listed.count(e.topic));
    EXPECT_EQ(listed.at(e.topic).type(), e.type);
  }

  // What they measure: landed at the origin, 3 m from the panel.
  v1::Imu imu;
  ASSERT_TRUE(imu.ParseFromString(recorder.of("robots/drone1/imu").back().bytes));
  EXPECT_NEAR(imu.linear_acceleration_m_s2().z(), 9.81, 0.3);
  v1::PositionFix fix;
  ASSERT_TRUE(fix.ParseFromString(recorder.of("robots/drone1/gps").back().bytes));
  EXPECT_NEAR(fix.position_m().x(), 0.0, 4 * fix.horizontal_stddev_m());
  EXPECT_GT(fix.horizontal_stddev_m(), 0.0);
  v1::LaserScan scan;
  ASSERT_TRUE(scan.ParseFromString(recorder.of("robots/drone1/lidar/scan").back().bytes));
  ASSERT_EQ(scan.ranges_m_size(), 360);
  const int ahead =
      static_cast<int>(std::lround((0.0 - scan.angle_min_rad()) / scan.angle_increment_rad()));
  EXPECT_NEAR(scan.ranges_m(ahead), 3.0, 0.05);
  EXPECT_TRUE(std::isinf(scan.ranges_m((ahead + 180) % 360)));
  v1::CameraInfo info;
  ASSERT_TRUE(info.ParseFromString(recorder.of("robots/drone1/camera/info").back().bytes));
  EXPECT_EQ(info.width_px(), 640u);
  EXPECT_EQ(info.height_px(), 480u);
  EXPECT_GT(info.fx_px(), 0.0);

  // Nobody subscribed to the camera: not a single image.
  EXPECT_TRUE(!listed.count("robots/drone1/camera/image") ||
              listed.at("robots/drone1/camera/image").published_count() == 0);
}

TEST_F(SimulatorSensorsTest, TheCameraIsRenderedOnlyWhileSubscribedAndShowsTheMarker) {
  step(1000);
  ASSERT_TRUE(eventually([&] { return topics().count("robots/drone1/camera/info") > 0; }));
  EXPECT_EQ(topics().count("robots/drone1/camera/image"), 0u) << "no image without a subscriber";

  std::mutex mutex;
  std::vector<v1::Image> images;
  auto subscription = client_->subscribeTyped<v1::Image>(
      "robots/drone1/camera/image", {.mode = v1::DELIVERY_MODE_QUEUE}, [&](const v1::Image& image) {
        std::lock_guard lock(mutex);
        images.push_back(image);
      });
  ASSERT_TRUE(subscription->waitConnected(seconds(10)));
  // The simulator notices the subscriber within about 0.5 s of wall time.
  ASSERT_TRUE(eventually(
      [&] {
        step(100);
        std::lock_guard lock(mutex);
        return !images.empty();
      },
      seconds(15)));
  v1::Image image;
  {
    std::lock_guard lock(mutex);
    image = images.front();
  }
  EXPECT_EQ(image.encoding(), "jpeg");
  EXPECT_EQ(image.width_px(), 640u);
  EXPECT_EQ(image.header().frame_id(), "camera");
  EXPECT_EQ(image.header().robot_id(), "drone1");
  const std::string& data = image.data();
  const cv::Mat bgr = cv::imdecode(
      cv::Mat(1, static_cast<int>(data.size()), CV_8UC1, const_cast<char*>(data.data())),
      cv::IMREAD_COLOR);
  ASSERT_FALSE(bgr.empty());
  EXPECT_EQ(bgr.cols, 640);
  EXPECT_EQ(bgr.rows, 480);
  const std::vector<std::string> texts = behaviorlib::sim::decodeQr(bgr);
  ASSERT_EQ(texts.size(), 1u);
  EXPECT_EQ(texts.front(), kMarkerText);

  // Unsubscribed: once the simulator has noticed, images stop.
  subscription.reset();
  ASSERT_TRUE(eventually([&] {
    const auto listed = topics();
    auto it = listed.find("robots/drone1/camera/image");
    return it != listed.end() && it->second.subscriber_count() == 0;
  }));
  std::this_thread::sleep_for(milliseconds(1500));  // at least two polls of the broker
  step(100);
  std::this_thread::sleep_for(milliseconds(300));
  const uint64_t before = topics().at("robots/drone1/camera/image").published_count();
  step(1000);  // 15 frames' worth
  std::this_thread::sleep_for(milliseconds(300));
  EXPECT_EQ(topics().at("robots/drone1/camera/image").published_count(), before);
}

TEST_F(SimulatorSensorsTest, ResetWithTheSameSeedReproducesEverySampleBitForBit) {
  const std::vector<std::string> names = {"robots/drone1/imu",     "robots/drone1/gps",
                                          "robots/drone1/baro",    "robots/drone1/linear_speed",
                                          "robots/drone1/battery", "robots/drone1/lidar/scan"};
  Recorder recorder(*client_, names);
  ASSERT_TRUE(recorder.waitConnected());
  // Connected at the broker is not yet known to the simulator: until its
  // interest watch hears of a topic it holds the topic's samples (decision
  // 17), and on a busy machine that may be after a run's first steps. Step
  // until every topic delivered more than its announcing first sample.
  const auto wanted = [&] {
    for (const std::string& topic : names) {
      if (recorder.of(topic).size() < 2) return false;
    }
    return true;
  };
  for (int i = 0; i < 100 && !wanted(); ++i) {
    step(100);
    std::this_thread::sleep_for(milliseconds(20));
  }
  ASSERT_TRUE(wanted()) << "the simulator never published every topic";

  // One run: Reset(seed), then the same time-stamped commands: take off at
  // 0.5 s, fly forward from 2 s, samples until 3 s.
  auto run = [&](uint64_t seed) {
    v1::ResetRequest reset;
    reset.set_seed(seed);
    v1::ResetResponse reset_response;
    EXPECT_TRUE(sim_->Reset(deadline().get(), reset, &reset_response).ok());
    recorder.clear();
    step(500);
    v1::AcquireLeaseRequest lease_request;
    lease_request.set_robot_id("drone1");
    lease_request.set_holder("test");
    *lease_request.mutable_ttl() = TimeUtil::SecondsToDuration(10);
    v1::AcquireLeaseResponse lease;
    EXPECT_TRUE(flight_->AcquireLease(deadline().get(), lease_request, &lease).ok());
    v1::ExecuteFlightActionRequest takeoff;
    takeoff.set_robot_id("drone1");
    takeoff.set_lease_id(lease.lease_id());
    takeoff.set_action(v1::FLIGHT_ACTION_TAKE_OFF);
    takeoff.set_takeoff_altitude_m(1.0);
    v1::ExecuteFlightActionResponse takeoff_response;
    EXPECT_TRUE(flight_->ExecuteFlightAction(deadline().get(), takeoff, &takeoff_response).ok());
    step(1500);
    v1::SetpointRequest setpoint;
    setpoint.set_robot_id("drone1");
    setpoint.set_lease_id(lease.lease_id());
    setpoint.mutable_velocity_yaw_rate()->mutable_velocity_m_s()->set_x(0.5);
    v1::SendSetpointResponse setpoint_response;
    EXPECT_TRUE(flight_->SendSetpoint(deadline().get(), setpoint, &setpoint_response).ok());
    step(1000);
    std::map<std::string, std::vector<std::string>> samples;
    for (const std::string& topic : names) {
      EXPECT_TRUE(recorder.waitForStamp(topic, 3'000'000'000)) << topic;
      for (const Record& r : recorder.of(topic)) samples[topic].push_back(r.bytes);
    }
    return samples;
  };

  const auto a = run(42);
  const auto b = run(42);
  const auto c = run(43);
  ASSERT_EQ(a.at("robots/drone1/imu").size(), 600u);
  ASSERT_EQ(a.at("robots/drone1/lidar/scan").size(), 30u);
  for (const std::string& topic : names) {
    SCOPED_TRACE(topic);
    EXPECT_TRUE(a.at(topic) == b.at(topic)) << "the same seed and commands: the same bytes";
    ASSERT_EQ(c.at(topic).size(), a.at(topic).size());
    std::size_t same = 0;
    for (std::size_t i = 0; i < a.at(topic).size(); ++i) same += a.at(topic)[i] == c.at(topic)[i];
    EXPECT_EQ(same, 0u) << "another seed: other noise in every sample";
  }
  // The vehicle really moved: the samples are not of a vehicle at rest.
  v1::PositionFix last;
  ASSERT_TRUE(last.ParseFromString(a.at("robots/drone1/gps").back()));
  EXPECT_GT(last.position_m().z(), -1.0);
  v1::TwistStamped speed;
  ASSERT_TRUE(speed.ParseFromString(a.at("robots/drone1/linear_speed").back()));
  EXPECT_GT(speed.twist().linear_m_s().x(), 0.2);
}

TEST(SimulatorSensorConfig, AMalformedSensorConfigurationStopsTheSimulatorAtStart) {
  const std::string path = ::testing::TempDir() + "/bad_sensors.yaml";
  {
    std::ofstream out(path);
    out << "lidar:\n  beams: 0\n";
  }
  support::ServerProcess simulator(BEHAVIORLIB_SIMULATOR_PATH, {"--sensor-config", path});
  EXPECT_FALSE(simulator.start());
  EXPECT_NE(simulator.error().find("exited before binding"), std::string::npos)
      << simulator.error();
}

}  // namespace
