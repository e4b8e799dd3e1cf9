// The simulator built in-process (simulator/service/simulator_process.h):
// the same wiring as the binary, served on a free loopback port and driven
// over real gRPC in lock-step, with no process to start.

#include <gmock/gmock.h>
#include <google/protobuf/util/time_util.h>
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>
#include <prometheus/registry.h>

#include <atomic>
#include <memory>
#include <string>
#include <thread>

#include "behaviorlib/channel/broker.h"
#include "behaviorlib/channel/channel_client.h"
#include "behaviorlib/errors/status_details.h"
#include "behaviorlib/v1/simulator.grpc.pb.h"
#include "behaviorlib/v1/types.pb.h"
#include "simulator/service/simulator_process.h"

namespace behaviorlib::sim {
namespace {

using google::protobuf::util::TimeUtil;
using ::testing::ElementsAre;
using ::testing::HasSubstr;

SimulatorOptions lockStep() {
  SimulatorOptions options;
  options.listen = "127.0.0.1:0";
  options.metrics_listen = "";
  options.lock_step = true;
  options.worlds_dir = BEHAVIORLIB_WORLDS_DIR;
  options.vehicles = {"drone1", "drone2"};
  return options;
}

TEST(SimulatorInProcessTest, LockStepTimeAdvancesByEachStep) {
  auto simulator = SimulatorProcess::start(lockStep());
  ASSERT_TRUE(simulator.ok()) << simulator.status();
  EXPECT_THAT((*simulator)->robotIds(), ElementsAre("drone1", "drone2"));
  auto stub = v1::Simulator::NewStub(grpc::CreateChannel(
      "127.0.0.1:" + std::to_string((*simulator)->grpcPort()), grpc::InsecureChannelCredentials()));
  int64_t previous_ns = -1;
  for (int i = 0; i < 3; ++i) {
    grpc::ClientContext context;
    context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(10));
    v1::StepRequest request;
    *request.mutable_duration() = TimeUtil::MillisecondsToDuration(250);
    v1::StepResponse response;
    ASSERT_TRUE(stub->Step(&context, request, &response).ok());
    const int64_t now_ns = TimeUtil::TimestampToNanoseconds(response.time());
    if (previous_ns >= 0) {
      EXPECT_EQ(now_ns - previous_ns, 250'000'000);
    }
    previous_ns = now_ns;
  }
  (*simulator)->shutdown();
  (*simulator)->shutdown();  // idempotent
}

TEST(SimulatorInProcessTest, AMissingWorldIsRefusedNamingIt) {
  SimulatorOptions options = lockStep();
  options.world = "/nonexistent/world.yaml";
  auto simulator = SimulatorProcess::start(std::move(options));
  ASSERT_FALSE(simulator.ok());
  EXPECT_EQ(simulator.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(simulator.status().message()), HasSubstr("--world"));
  EXPECT_THAT(std::string(simulator.status().message()), HasSubstr("/nonexistent/world.yaml"));
}

TEST(SimulatorInProcessTest, NoVehicleIsRefused) {
  SimulatorOptions options = lockStep();
  options.vehicles.clear();
  auto simulator = SimulatorProcess::start(std::move(options));
  ASSERT_FALSE(simulator.ok());
  EXPECT_EQ(simulator.status().code(), absl::StatusCode::kInvalidArgument);
}

TEST(SimulatorInProcessTest, EverySettingOutOfRangeIsRefusedNamingItsFlag) {
  SimulatorOptions options = lockStep();
  options.time_scale = 5000;
  options.quantum = std::chrono::milliseconds(0);
  options.min_followers = -1;
  options.follower_timeout = std::chrono::hours(1);
  options.idle_time_scale = 0.5;
  options.seed = 0;
  options.vehicle_channels = {{"drone1", "127.0.0.1:2"}};  // without --channel
  const absl::Status status = options.validate();
  ASSERT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
  for (const char* flag :
       {"--time-scale", "--quantum-ms", "--min-followers", "--follower-timeout-s",
        "--idle-time-scale", "--seed", "--vehicle-channels"}) {
    EXPECT_THAT(std::string(status.message()), HasSubstr(flag));
  }
  const auto bad = errors::badRequest(status);
  ASSERT_TRUE(bad.has_value());
  std::vector<std::string> fields;
  for (const auto& violation : bad->field_violations()) fields.push_back(violation.field());
  EXPECT_THAT(fields, ElementsAre("time_scale", "quantum", "min_followers", "follower_timeout",
                                  "idle_time_scale", "seed", "vehicle_channels"));
  auto simulator = SimulatorProcess::start(std::move(options));
  ASSERT_FALSE(simulator.ok());
  EXPECT_EQ(simulator.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_TRUE(lockStep().validate().ok());
}

// A broker built in-process on a free loopback port.
struct InProcessBroker {
  InProcessBroker() {
    grpc::ServerBuilder builder;
    builder.AddListeningPort("127.0.0.1:0", grpc::InsecureServerCredentials(), &port);
    builder.RegisterService(&broker);
    server = builder.BuildAndStart();
  }
  ~InProcessBroker() {
    broker.shutdown();
    server->Shutdown();
  }
  std::string address() const { return "127.0.0.1:" + std::to_string(port); }
  prometheus::Registry registry;
  channel::Broker broker{registry};
  int port = 0;
  std::unique_ptr<grpc::Server> server;
};

TEST(SimulatorInProcessTest, AVehicleWithABrokerOfItsOwnGetsItsTopicsAndTheClockThere) {
  InProcessBroker ground;
  InProcessBroker onboard;  // drone2's own broker
  SimulatorOptions options = lockStep();
  options.lock_step = false;  // free running, 1x
  options.channel = ground.address();
  options.vehicle_channels = {{"drone2", onboard.address()}};
  auto simulator = SimulatorProcess::start(std::move(options));
  ASSERT_TRUE(simulator.ok()) << simulator.status();

  channel::ChannelClient ground_client(ground.address());
  channel::ChannelClient onboard_client(onboard.address());
  std::atomic<int> drone2_poses{0}, drone1_poses{0}, onboard_clock{0};
  auto sub2 = onboard_client.subscribeTyped<v1::PoseStamped>(
      "robots/drone2/ground_truth/pose", {}, [&](const v1::PoseStamped&) { ++drone2_poses; });
  auto sub1 = ground_client.subscribeTyped<v1::PoseStamped>(
      "robots/drone1/ground_truth/pose", {}, [&](const v1::PoseStamped&) { ++drone1_poses; });
  auto clock = onboard_client.subscribeTyped<v1::Clock>("clock", {.send_latest_first = true},
                                                        [&](const v1::Clock&) { ++onboard_clock; });
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(10);
  while ((drone2_poses < 5 || drone1_poses < 5 || onboard_clock < 1) &&
         std::chrono::steady_clock::now() < deadline) {
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  EXPECT_GE(drone2_poses.load(), 5) << "drone2's topics reach its own broker";
  EXPECT_GE(drone1_poses.load(), 5) << "drone1's topics stay on the main broker";
  EXPECT_GE(onboard_clock.load(), 1) << "the clock reaches every broker";
  // Nothing of drone2 on the main broker, nothing of drone1 on drone2's.
  auto on_ground = ground_client.listTopics("robots/drone2/");
  ASSERT_TRUE(on_ground.ok());
  EXPECT_TRUE(on_ground->empty());
  auto on_board = onboard_client.listTopics("robots/drone1/");
  ASSERT_TRUE(on_board.ok());
  EXPECT_TRUE(on_board->empty());
  (*simulator)->shutdown();
}

TEST(SimulatorInProcessTest, AVehicleChannelForNoVehicleIsRefused) {
  SimulatorOptions options = lockStep();
  options.channel = "127.0.0.1:1";
  options.vehicle_channels = {{"drone7", "127.0.0.1:2"}};
  auto simulator = SimulatorProcess::start(std::move(options));
  ASSERT_FALSE(simulator.ok());
  EXPECT_EQ(simulator.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(simulator.status().message()), HasSubstr("drone7"));
}

}  // namespace
}  // namespace behaviorlib::sim
