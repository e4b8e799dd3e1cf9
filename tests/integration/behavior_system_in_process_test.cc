// A behavior system built in-process (BehaviorSystemProcess): the same wiring
// as a system's binary, served on a free loopback port and driven over real
// gRPC, with no process to start. An activation ends with its cause; shutdown
// ends an active behavior INTERRUPTED and its event reaches a watcher;
// inconsistent options are refused.

#include <gmock/gmock.h>
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>

#include <string>

#include "behaviorlib/basic_quadrotor_behaviors/wait_behavior.h"
#include "behaviorlib/server/behavior_system_main.h"
#include "behaviorlib/v1/behavior.grpc.pb.h"
#include "behaviorlib/v1/behaviors/basic_quadrotor_behaviors.behaviors.h"

namespace behaviorlib::server {
namespace {

using ::testing::HasSubstr;

BehaviorSystemOptions loopbackOptions() {
  BehaviorSystemOptions options;
  options.system = "in_process_waits";
  options.robot_id = "drone9";
  options.listen = "127.0.0.1:0";
  options.metrics_listen = "";
  return options;
}

void registerWait(BehaviorSystemBuilder& builder) { builder.add<basic::WaitBehavior>(); }

std::unique_ptr<v1::BehaviorSystem::Stub> connect(const BehaviorSystemProcess& system) {
  return v1::BehaviorSystem::NewStub(grpc::CreateChannel(
      "127.0.0.1:" + std::to_string(system.grpcPort()), grpc::InsecureChannelCredentials()));
}

grpc::Status activateWait(v1::BehaviorSystem::Stub& stub, double duration_s) {
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(10));
  v1::ActivateBehaviorRequest request;
  request.set_behavior("WAIT");
  (*request.mutable_parameters()->mutable_fields())["duration_s"].set_number_value(duration_s);
  v1::ActivateResponse response;
  return stub.ActivateBehavior(&context, request, &response);
}

// Reads the event stream until WAIT's finished event (or the stream ends).
v1::BehaviorEvent waitFinished(grpc::ClientReader<v1::WatchEventsResponse>& reader) {
  v1::WatchEventsResponse message;
  while (reader.Read(&message)) {
    if (message.event().has_finished()) return message.event();
  }
  return {};
}

TEST(BehaviorSystemInProcessTest, ServesItsBehaviorsAndTheirEvents) {
  auto system = BehaviorSystemProcess::start(loopbackOptions(), registerWait);
  ASSERT_TRUE(system.ok()) << system.status();
  EXPECT_THAT((*system)->behaviorNames(), ::testing::ElementsAre("WAIT"));
  auto stub = connect(**system);
  grpc::ClientContext watch;
  watch.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(30));
  auto reader = stub->WatchEvents(&watch, v1::WatchEventsRequest());
  ASSERT_TRUE(activateWait(*stub, 0.1).ok());
  const v1::BehaviorEvent finished = waitFinished(*reader);
  EXPECT_EQ(finished.behavior(), "WAIT");
  EXPECT_EQ(finished.robot_id(), "drone9");
  EXPECT_EQ(finished.finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED);
  watch.TryCancel();
  reader->Finish();
}

TEST(BehaviorSystemInProcessTest, ShutdownEndsAnActiveBehaviorInterruptedAndTellsTheWatchers) {
  auto system = BehaviorSystemProcess::start(loopbackOptions(), registerWait);
  ASSERT_TRUE(system.ok()) << system.status();
  auto stub = connect(**system);
  grpc::ClientContext watch;
  watch.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(30));
  auto reader = stub->WatchEvents(&watch, v1::WatchEventsRequest());
  ASSERT_TRUE(activateWait(*stub, 1000).ok());
  (*system)->shutdown();
  const v1::BehaviorEvent finished = waitFinished(*reader);
  EXPECT_EQ(finished.finished().cause(), v1::TERMINATION_CAUSE_INTERRUPTED);
  EXPECT_THAT(finished.finished().message(), HasSubstr("process shutting down"));
  // Refused once shut down: the port is closed.
  EXPECT_FALSE(activateWait(*stub, 1).ok());
  reader->Finish();
}

TEST(BehaviorSystemInProcessTest, InconsistentOptionsAreRefusedNamingTheFlag) {
  auto follow = loopbackOptions();
  follow.follow_time = "127.0.0.1:1";
  auto refused = BehaviorSystemProcess::start(follow, registerWait);
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(refused.status().message(), HasSubstr("--follow-time needs --clock sim"));

  auto sim = loopbackOptions();
  sim.clock = "sim";
  refused = BehaviorSystemProcess::start(sim, registerWait);
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(refused.status().message(), HasSubstr("--clock sim needs --channel"));

  auto bad_config = loopbackOptions();
  bad_config.config = YAML::Load("behaviors: {WAIT: {frequency_hz: -1}}");
  refused = BehaviorSystemProcess::start(bad_config, registerWait);
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(refused.status().message(), HasSubstr("frequency_hz"));
}

// Decision 45: every key of the file is checked at start, with its position.
TEST(BehaviorSystemInProcessTest, UnknownConfigKeysStopTheStartNamingFileAndLine) {
  auto options = loopbackOptions();
  options.config_file = "sys.yaml";
  options.config = YAML::Load("behaviors:\n  WAIT: {frequency_hz: 5}\nmaping: {}\n");
  auto refused = BehaviorSystemProcess::start(options, registerWait);
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(refused.status().message(),
              HasSubstr("sys.yaml:3:1: unknown key 'maping'; known keys: (none)"));

  options.config = YAML::Load("behaviors:\n  WAIT:\n    frequency_hz: 5\n    duration_s: 2\n");
  refused = BehaviorSystemProcess::start(options, registerWait);
  EXPECT_THAT(refused.status().message(),
              HasSubstr("sys.yaml:4:5: behaviors.WAIT: unknown key 'duration_s'"));

  options.config = YAML::Load("behaviors:\n  WAIT: {frequency_hz: 5}\n");
  auto started = BehaviorSystemProcess::start(options, registerWait);
  ASSERT_TRUE(started.ok()) << started.status();
  (*started)->shutdown();
}

}  // namespace
}  // namespace behaviorlib::server
