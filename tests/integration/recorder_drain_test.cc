// The flight recorder stopped right after a mission ended still holds the
// mission's end: stop() catches up with the coordinator first
// (FleetFollower::catchUp). A real coordinator and a real behavior system,
// built in-process, served on loopback. The recorder here never watches a
// mission and reads the mission list only at its start, so what it holds of
// the mission comes from the catch-up alone.

#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>
#include <unistd.h>

#include <chrono>
#include <filesystem>
#include <string>
#include <thread>

#include "behaviorlib/basic_quadrotor_behaviors/wait_behavior.h"
#include "behaviorlib/recorder/recorder.h"
#include "behaviorlib/server/behavior_system_main.h"
#include "behaviorlib/v1/behaviors/basic_quadrotor_behaviors.behaviors.h"
#include "behaviorlib/v1/coordinator.grpc.pb.h"
#include "coordinator/process/coordinator_process.h"
#include "formats/mcap/mcap.h"

namespace behaviorlib::coordinator {
namespace {

class RecorderDrainTest : public ::testing::Test {
 protected:
  void SetUp() override {
    CoordinatorOptions options;
    options.listen = "127.0.0.1:0";
    options.metrics_listen = "";
    auto started = Coordinator::start(std::move(options));
    ASSERT_TRUE(started.ok()) << started.status();
    coordinator_ = std::move(*started);
    address_ = "127.0.0.1:" + std::to_string(coordinator_->grpcPort());
    stub_ =
        v1::Coordinator::NewStub(grpc::CreateChannel(address_, grpc::InsecureChannelCredentials()));
    server::BehaviorSystemOptions system_options;
    system_options.system = "waits";
    system_options.robot_id = "drone1";
    system_options.listen = "127.0.0.1:0";
    system_options.metrics_listen = "";
    system_options.coordinator = address_;
    auto system = server::BehaviorSystemProcess::start(
        system_options, [](server::BehaviorSystemBuilder& b) { b.add<basic::WaitBehavior>(); });
    ASSERT_TRUE(system.ok()) << system.status();
    system_ = std::move(*system);
    // A mission needs the system UP (registered, its event stream open):
    // wait for it, bounded.
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(20);
    bool up = false;
    while (!up && std::chrono::steady_clock::now() < deadline) {
      grpc::ClientContext context;
      context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(10));
      v1::ListSystemsResponse systems;
      if (stub_->ListSystems(&context, v1::ListSystemsRequest(), &systems).ok()) {
        for (const auto& info : systems.systems()) up |= info.state() == v1::SYSTEM_STATE_UP;
      }
      if (!up) std::this_thread::sleep_for(std::chrono::milliseconds(10));
    }
    ASSERT_TRUE(up) << "the behavior system did not come UP";
    path_ = (std::filesystem::temp_directory_path() /
             ("behaviorlib-drain-" + std::to_string(::getpid()) + ".mcap"))
                .string();
  }
  void TearDown() override { std::filesystem::remove(path_); }

  // Starts a mission of one WAIT on drone1, and reads its
  // WatchMission stream to its end; returns the last state.
  v1::MissionState runMission(const std::string& mission_id) {
    v1::StartMissionRequest start;
    start.set_mission_id(mission_id);
    start.set_text(
        "name: drained\nrobot: drone1\nsteps:\n  - behavior: WAIT\n    parameters: {duration_s: "
        "0}\n");
    {
      grpc::ClientContext context;
      context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(10));
      v1::StartMissionResponse started;
      const grpc::Status status = stub_->StartMission(&context, start, &started);
      EXPECT_TRUE(status.ok()) << status.error_message();
    }
    grpc::ClientContext context;
    context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(20));
    v1::WatchMissionRequest watch;
    watch.set_mission_id(mission_id);
    auto reader = stub_->WatchMission(&context, watch);
    v1::WatchMissionResponse message;
    v1::MissionState last = v1::MISSION_STATE_UNSPECIFIED;
    while (reader->Read(&message)) last = message.status().state();
    EXPECT_TRUE(reader->Finish().ok());
    return last;
  }

  // The last recorded status of `mission_id`, and how many behavior events
  // the file holds.
  std::pair<v1::MissionState, int> recorded(const std::string& mission_id) {
    v1::MissionState last = v1::MISSION_STATE_UNSPECIFIED;
    int events = 0;
    auto scanned = recorder::mcap::scan(
        path_, {},
        [&](const recorder::mcap::ScanSummary& summary, const recorder::mcap::Message& m) {
          const std::string& topic = summary.channels.at(m.channel_id).topic;
          if (topic == recorder::kMissionsTopic) {
            v1::MissionStatus status;
            EXPECT_TRUE(status.ParseFromString(m.data));
            if (status.mission_id() == mission_id) last = status.state();
          } else if (topic == recorder::kEventsTopic) {
            ++events;
          }
          return true;
        });
    EXPECT_TRUE(scanned.ok()) << scanned.status();
    return {last, events};
  }

  std::unique_ptr<Coordinator> coordinator_;
  std::unique_ptr<server::BehaviorSystemProcess> system_;
  std::string address_;
  std::unique_ptr<v1::Coordinator::Stub> stub_;
  std::string path_;
};

// Starts a recorder blind to missions once mission `before` has ended, and
// waits until its one reading of the mission list has recorded that
// mission: whatever runs after this is never listed or watched by it.
std::unique_ptr<recorder::Recorder> startAfterItsListing(const std::string& address,
                                                         recorder::RecorderOptions options) {
  auto recording = recorder::Recorder::start(
      grpc::CreateChannel(address, grpc::InsecureChannelCredentials()), std::move(options));
  EXPECT_TRUE(recording.ok()) << recording.status();
  if (!recording.ok()) return nullptr;
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(20);
  while ((*recording)->stats().messages[recorder::kMissionsTopic] == 0 &&
         std::chrono::steady_clock::now() < deadline) {
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  EXPECT_EQ((*recording)->stats().messages[recorder::kMissionsTopic], 1u);
  return std::move(*recording);
}

recorder::RecorderOptions blindToMissions(const std::string& path) {
  recorder::RecorderOptions options;
  options.path = path;
  options.topics = {};
  options.mission_poll = std::chrono::hours(1);  // the list is read once, at the start
  options.max_watched_missions = 0;              // and no mission is watched
  return options;
}

TEST_F(RecorderDrainTest, AStopRightAfterTheMissionEndedRecordsItsEnd) {
  ASSERT_EQ(runMission("before"), v1::MISSION_STATE_SUCCEEDED);
  auto recording = startAfterItsListing(address_, blindToMissions(path_));
  ASSERT_NE(recording, nullptr);
  ASSERT_EQ(runMission("drained-1"), v1::MISSION_STATE_SUCCEEDED);
  ASSERT_TRUE(recording->stop().ok());
  EXPECT_TRUE(recording->stats().drained);
  const auto [state, events] = recorded("drained-1");
  EXPECT_EQ(state, v1::MISSION_STATE_SUCCEEDED);
  EXPECT_GT(events, 0);
}

TEST_F(RecorderDrainTest, WithoutTheCatchUpTheBlindRecorderMissesTheMission) {
  // The same recorder with no time to catch up: the file has no status of
  // the mission, which is what the catch-up adds above.
  ASSERT_EQ(runMission("before"), v1::MISSION_STATE_SUCCEEDED);
  recorder::RecorderOptions options = blindToMissions(path_);
  options.drain_timeout = std::chrono::milliseconds(0);
  auto recording = startAfterItsListing(address_, options);
  ASSERT_NE(recording, nullptr);
  ASSERT_EQ(runMission("drained-2"), v1::MISSION_STATE_SUCCEEDED);
  ASSERT_TRUE(recording->stop().ok());
  EXPECT_FALSE(recording->stats().drained);
  EXPECT_EQ(recorded("drained-2").first, v1::MISSION_STATE_UNSPECIFIED);
}

TEST_F(RecorderDrainTest, ACoordinatorThatIsGoneEndsTheCatchUpAtOnce) {
  auto recording = recorder::Recorder::start(
      grpc::CreateChannel(address_, grpc::InsecureChannelCredentials()), blindToMissions(path_));
  ASSERT_TRUE(recording.ok()) << recording.status();
  system_.reset();
  coordinator_.reset();
  const auto before = std::chrono::steady_clock::now();
  ASSERT_TRUE((*recording)->stop().ok());
  EXPECT_FALSE((*recording)->stats().drained);
  EXPECT_LT(std::chrono::steady_clock::now() - before, std::chrono::seconds(4));
}

}  // namespace
}  // namespace behaviorlib::coordinator
