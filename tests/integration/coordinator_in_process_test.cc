// The coordinator built in-process (coordinator/process): the same wiring as
// the binary, served on a free loopback port and driven over real gRPC, with
// no process to start. Belief memory survives a restart through the journal;
// shutdown ends an event stream UNAVAILABLE with its resume point; a state
// directory that cannot be used is refused, naming it; the List RPCs page
// their items (beliefs; and the systems, behaviors and missions of behavior
// systems built in-process that register with it).

#include <gmock/gmock.h>
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>

#include <chrono>
#include <filesystem>
#include <fstream>
#include <string>
#include <thread>
#include <vector>

#include "behaviorlib/basic_quadrotor_behaviors/wait_behavior.h"
#include "behaviorlib/server/behavior_system_main.h"
#include "behaviorlib/v1/behaviors/basic_quadrotor_behaviors.behaviors.h"
#include "behaviorlib/v1/coordinator.grpc.pb.h"
#include "coordinator/process/coordinator_process.h"
#include "support/paging.h"

namespace behaviorlib::coordinator {
namespace {

using ::testing::ElementsAre;
using ::testing::HasSubstr;
using ::testing::UnorderedElementsAre;
using Pages = std::vector<std::vector<std::string>>;

class TempDir {
 public:
  TempDir() {
    char pattern[] = "/tmp/behaviorlib-coordinator-XXXXXX";
    path_ = mkdtemp(pattern);
  }
  ~TempDir() { std::filesystem::remove_all(path_); }
  const std::string& path() const { return path_; }

 private:
  std::string path_;
};

CoordinatorOptions loopbackOptions(const std::string& state_dir) {
  CoordinatorOptions options;
  options.listen = "127.0.0.1:0";
  options.metrics_listen = "";
  options.state_dir = state_dir;
  return options;
}

std::unique_ptr<v1::Coordinator::Stub> connect(const Coordinator& coordinator) {
  return v1::Coordinator::NewStub(grpc::CreateChannel(
      "127.0.0.1:" + std::to_string(coordinator.grpcPort()), grpc::InsecureChannelCredentials()));
}

grpc::Status writeBelief(v1::Coordinator::Stub& stub, const std::string& key, double value) {
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(10));
  v1::WriteBeliefRequest request;
  request.set_key(key);
  request.mutable_value()->set_number_value(value);
  request.set_writer("test");
  v1::WriteBeliefResponse response;
  return stub.WriteBelief(&context, request, &response);
}

grpc::Status readBelief(v1::Coordinator::Stub& stub, const std::string& key, v1::Belief* out) {
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(10));
  v1::ReadBeliefRequest request;
  request.set_key(key);
  v1::ReadBeliefResponse response;
  grpc::Status status = stub.ReadBelief(&context, request, &response);
  *out = response.belief();
  return status;
}

TEST(CoordinatorInProcessTest, BeliefsSurviveARestartThroughTheJournal) {
  TempDir state;
  std::string first_incarnation;
  {
    auto coordinator = Coordinator::start(loopbackOptions(state.path()));
    ASSERT_TRUE(coordinator.ok()) << coordinator.status();
    first_incarnation = (*coordinator)->incarnation();
    auto stub = connect(**coordinator);
    ASSERT_TRUE(writeBelief(*stub, "drone1/altitude_m", 1.5).ok());
  }  // the destructor shuts it down
  auto coordinator = Coordinator::start(loopbackOptions(state.path()));
  ASSERT_TRUE(coordinator.ok()) << coordinator.status();
  EXPECT_NE((*coordinator)->incarnation(), first_incarnation);
  auto stub = connect(**coordinator);
  v1::Belief belief;
  ASSERT_TRUE(readBelief(*stub, "drone1/altitude_m", &belief).ok());
  EXPECT_DOUBLE_EQ(belief.value().number_value(), 1.5);
  EXPECT_EQ(belief.writer(), "test");
}

TEST(CoordinatorInProcessTest, ShutdownEndsAnEventStreamWithItsResumePoint) {
  auto coordinator = Coordinator::start(loopbackOptions(""));
  ASSERT_TRUE(coordinator.ok()) << coordinator.status();
  auto stub = connect(**coordinator);
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(10));
  v1::WatchFleetEventsRequest request;
  auto reader = stub->WatchEvents(&context, request);
  v1::WatchFleetEventsResponse start;
  ASSERT_TRUE(reader->Read(&start));
  ASSERT_TRUE(start.has_start());
  EXPECT_EQ(start.start().incarnation(), (*coordinator)->incarnation());

  (*coordinator)->shutdown();
  v1::WatchFleetEventsResponse more;
  while (reader->Read(&more)) {
  }
  const grpc::Status status = reader->Finish();
  EXPECT_EQ(status.error_code(), grpc::StatusCode::UNAVAILABLE);
  EXPECT_THAT(status.error_message(), HasSubstr("the coordinator is shutting down"));
  EXPECT_THAT(status.error_message(),
              HasSubstr("resume with since_seq=0 and incarnation=" + start.start().incarnation()));
}

TEST(CoordinatorInProcessTest, AStateDirectoryThatIsAFileIsRefusedNamingIt) {
  TempDir state;
  const std::string file = state.path() + "/not-a-directory";
  std::ofstream(file) << "x";
  auto coordinator = Coordinator::start(loopbackOptions(file));
  ASSERT_FALSE(coordinator.ok());
  EXPECT_EQ(coordinator.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(coordinator.status().message()), HasSubstr("--state-dir"));
}

// The safety rules' vehicle clock: steady or sim, and simulated time needs
// the channel it comes from.
TEST(CoordinatorInProcessTest, AVehicleClockIsSteadyOrSimFromAChannel) {
  CoordinatorOptions unknown = loopbackOptions("");
  unknown.clock = "wall";
  auto refused = Coordinator::start(std::move(unknown));
  ASSERT_FALSE(refused.ok());
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(refused.status().message()),
              HasSubstr("--clock must be 'steady' or 'sim', got 'wall'"));

  CoordinatorOptions no_channel = loopbackOptions("");
  no_channel.clock = "sim";
  refused = Coordinator::start(std::move(no_channel));
  ASSERT_FALSE(refused.ok());
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(refused.status().message()), HasSubstr("--clock sim needs --channel"));
}

TEST(CoordinatorInProcessTest, AnAddressInUseIsRefused) {
  auto first = Coordinator::start(loopbackOptions(""));
  ASSERT_TRUE(first.ok()) << first.status();
  CoordinatorOptions options = loopbackOptions("");
  options.listen = "127.0.0.1:" + std::to_string((*first)->grpcPort());
  auto second = Coordinator::start(std::move(options));
  ASSERT_FALSE(second.ok());
  EXPECT_EQ(second.status().code(), absl::StatusCode::kUnavailable);
}

// ListBeliefs pages belief memory: two beliefs a page, in key order, each
// belief under the prefix once, the last page without a next_page_token; a
// page_token the coordinator did not give and a negative page_size are
// INVALID_ARGUMENT.
TEST(CoordinatorInProcessTest, ListBeliefsPagesEveryBeliefOnce) {
  auto coordinator = Coordinator::start(loopbackOptions(""));
  ASSERT_TRUE(coordinator.ok()) << coordinator.status();
  auto stub = connect(**coordinator);
  for (const std::string key :
       {"drone1/e", "drone1/a", "drone2/c", "drone1/d", "drone1/b", "drone1/c"}) {
    ASSERT_TRUE(writeBelief(*stub, key, 1).ok()) << key;
  }
  const auto beliefs = [](const v1::ListBeliefsResponse& r) -> const auto& { return r.beliefs(); };
  const auto key = [](const v1::Belief& b) { return b.key(); };
  v1::ListBeliefsRequest request;
  request.set_prefix("drone1/");
  request.set_page_size(2);
  Pages pages;
  grpc::Status status =
      support::pageKeys(*stub, &v1::Coordinator::Stub::ListBeliefs, request, beliefs, key, &pages);
  ASSERT_TRUE(status.ok()) << status.error_message();
  EXPECT_THAT(pages, ElementsAre(ElementsAre("drone1/a", "drone1/b"),
                                 ElementsAre("drone1/c", "drone1/d"), ElementsAre("drone1/e")));

  request.set_page_token("not-a-token");
  status =
      support::pageKeys(*stub, &v1::Coordinator::Stub::ListBeliefs, request, beliefs, key, &pages);
  EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << status.error_message();
  EXPECT_THAT(status.error_message(), HasSubstr("page_token"));
  request.clear_page_token();
  request.set_page_size(-1);
  status =
      support::pageKeys(*stub, &v1::Coordinator::Stub::ListBeliefs, request, beliefs, key, &pages);
  EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << status.error_message();
}

// Starts a mission of one WAIT on `robot` and reads its WatchMission stream
// to its end; returns the last status.
v1::MissionStatus runWaitMission(v1::Coordinator::Stub& stub, const std::string& mission_id,
                                 const std::string& robot) {
  v1::StartMissionRequest start;
  start.set_mission_id(mission_id);
  start.set_text("name: paged\nrobot: " + robot +
                 "\nsteps:\n  - behavior: WAIT\n    parameters: {duration_s: 0}\n");
  v1::StartMissionResponse started;
  {
    grpc::ClientContext context;
    context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(10));
    const grpc::Status status = stub.StartMission(&context, start, &started);
    EXPECT_TRUE(status.ok()) << mission_id << ": " << status.error_message();
    if (!status.ok()) return {};
  }
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(10));
  v1::WatchMissionRequest watch;
  watch.set_mission_id(mission_id);
  auto reader = stub.WatchMission(&context, watch);
  v1::WatchMissionResponse message;
  v1::MissionStatus last;
  while (reader->Read(&message)) last = message.status();
  const grpc::Status status = reader->Finish();
  EXPECT_TRUE(status.ok()) << mission_id << ": " << status.error_message();
  return last;
}

// The systems, behaviors and missions of the fleet, paged: three behavior
// systems (WAIT on drone1, drone2 and drone3) register, five missions run
// one after another; ListSystems, ListBehaviors and ListMissions give two
// items a page, each item once, the last page without a next_page_token;
// ListMissions' pages, put together, are its list in one page (newest first).
TEST(CoordinatorInProcessTest, ListSystemsBehaviorsAndMissionsPageEveryItemOnce) {
  auto coordinator = Coordinator::start(loopbackOptions(""));
  ASSERT_TRUE(coordinator.ok()) << coordinator.status();
  auto stub = connect(**coordinator);
  std::vector<std::unique_ptr<server::BehaviorSystemProcess>> systems;
  for (const std::string robot : {"drone3", "drone1", "drone2"}) {
    server::BehaviorSystemOptions options;
    options.system = "waits";
    options.robot_id = robot;
    options.listen = "127.0.0.1:0";
    options.metrics_listen = "";
    options.coordinator = "127.0.0.1:" + std::to_string((*coordinator)->grpcPort());
    auto system = server::BehaviorSystemProcess::start(
        options, [](server::BehaviorSystemBuilder& b) { b.add<basic::WaitBehavior>(); });
    ASSERT_TRUE(system.ok()) << system.status();
    systems.push_back(std::move(*system));
  }
  const auto systemKey = [](const v1::SystemInfo& s) {
    return s.robot_id() + "/" + s.system() + "/" + v1::SystemState_Name(s.state());
  };
  const auto listed = [](const v1::ListSystemsResponse& r) -> const auto& { return r.systems(); };
  v1::ListSystemsRequest list_systems;
  list_systems.set_page_size(2);
  Pages pages;
  // Registration and the event streams take a moment: wait (bounded) until
  // every system is UP.
  const Pages up = {{"drone1/waits/SYSTEM_STATE_UP", "drone2/waits/SYSTEM_STATE_UP"},
                    {"drone3/waits/SYSTEM_STATE_UP"}};
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(20);
  grpc::Status status;
  do {
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
    status = support::pageKeys(*stub, &v1::Coordinator::Stub::ListSystems, list_systems, listed,
                               systemKey, &pages);
  } while (status.ok() && pages != up && std::chrono::steady_clock::now() < deadline);
  ASSERT_TRUE(status.ok()) << status.error_message();
  ASSERT_EQ(pages, up) << "the three systems were not all UP";

  v1::ListFleetBehaviorsRequest list_behaviors;
  list_behaviors.set_page_size(2);
  status = support::pageKeys(
      *stub, &v1::Coordinator::Stub::ListBehaviors, list_behaviors,
      [](const v1::ListFleetBehaviorsResponse& r) -> const auto& { return r.behaviors(); },
      [](const v1::FleetBehavior& b) { return b.robot_id() + "/" + b.description().name(); },
      &pages);
  ASSERT_TRUE(status.ok()) << status.error_message();
  EXPECT_THAT(pages,
              ElementsAre(ElementsAre("drone1/WAIT", "drone2/WAIT"), ElementsAre("drone3/WAIT")));

  const std::vector<std::string> robots = {"drone1", "drone2", "drone3", "drone1", "drone2"};
  for (size_t i = 0; i < robots.size(); ++i) {
    const v1::MissionStatus last = runWaitMission(*stub, "paged-" + std::to_string(i), robots[i]);
    ASSERT_EQ(last.state(), v1::MISSION_STATE_SUCCEEDED) << last.ShortDebugString();
  }
  const auto missions = [](const v1::ListMissionsResponse& r) -> const auto& {
    return r.missions();
  };
  const auto missionId = [](const v1::MissionStatus& m) { return m.mission_id(); };
  v1::ListMissionsRequest list_missions;
  Pages whole;
  status = support::pageKeys(*stub, &v1::Coordinator::Stub::ListMissions, list_missions, missions,
                             missionId, &whole);
  ASSERT_TRUE(status.ok()) << status.error_message();
  ASSERT_EQ(whole.size(), 1u);
  ASSERT_THAT(whole[0],
              UnorderedElementsAre("paged-0", "paged-1", "paged-2", "paged-3", "paged-4"));
  list_missions.set_page_size(2);
  status = support::pageKeys(*stub, &v1::Coordinator::Stub::ListMissions, list_missions, missions,
                             missionId, &pages);
  ASSERT_TRUE(status.ok()) << status.error_message();
  const std::vector<std::string>& all = whole[0];
  EXPECT_THAT(pages, ElementsAre(ElementsAre(all[0], all[1]), ElementsAre(all[2], all[3]),
                                 ElementsAre(all[4])));
  list_missions.set_page_token("not-a-token");
  status = support::pageKeys(*stub, &v1::Coordinator::Stub::ListMissions, list_missions, missions,
                             missionId, &pages);
  EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << status.error_message();
}

}  // namespace
}  // namespace behaviorlib::coordinator
