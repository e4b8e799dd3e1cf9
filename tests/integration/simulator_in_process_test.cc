// The simulator built in-process (simulator/service/simulator_process.h):
// the same wiring as the binary, served on a free loopback port and driven
// over real gRPC in lock-step, with no process to start.

#include <gmock/gmock.h>
#include <google/protobuf/util/time_util.h>
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>

#include <string>

#include "behaviorlib/v1/simulator.grpc.pb.h"
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

}  // namespace
}  // namespace behaviorlib::sim
