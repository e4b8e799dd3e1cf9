// Fleet missions against the real stack: the channel broker, the simulator
// with two vehicles in the deterministic mode, basic_quadrotor_behaviors once
// per robot, and the coordinator with the catalog and --clock sim (the
// missions' waits count the vehicles' time). One mission commands both
// vehicles: parallel branches, each on its robot, synchronised by wait_for;
// docs/missions.md's fleet examples run here as documented; a kill -9 of the
// coordinator inside the branches resumes them without activating anything
// twice.

#include <google/protobuf/util/json_util.h>
#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <map>
#include <memory>
#include <set>
#include <string>
#include <vector>

#include "coordinator_test_support.h"
#include "mission_test_support.h"
#include "support/deterministic.h"
#include "support/server_process.h"

namespace coordinator_test {
namespace {

constexpr char kCatalog[] = BEHAVIORLIB_CATALOG_PATH;
const std::vector<std::string> kRobots = {"drone1", "drone2"};

// Both vehicles take off (drone1 waits until drone2 is up), then both land.
constexpr char kTogether[] = R"(name: together
robot: drone1
recurrent:
  - {robot: drone1, behavior: SELF_LOCALIZE_WITH_GROUND_TRUTH}
  - {robot: drone2, behavior: SELF_LOCALIZE_WITH_GROUND_TRUTH}
safety:
  - {robot: drone1, behavior: LAND}
  - {robot: drone2, behavior: LAND}
steps:
  - name: fly
    parallel:
      branches:
        - robot: drone1
          steps:
            - {behavior: WAIT, parameters: {duration_s: 1.0}}
            - {name: up_drone1, behavior: TAKE_OFF, parameters: {altitude_m: 1.0}, on: {REFUSED: {retry: 2}}}
            - {name: wait_drone2, wait_for: {step: up_drone2, timeout_s: 60}}
            - {name: hold_drone1, behavior: WAIT, parameters: {duration_s: HOLD}}
        - robot: drone2
          steps:
            - {behavior: WAIT, parameters: {duration_s: 1.0}}
            - {name: up_drone2, behavior: TAKE_OFF, parameters: {altitude_m: 1.5}, on: {REFUSED: {retry: 2}}}
            - {name: hold_drone2, behavior: WAIT, parameters: {duration_s: HOLD}}
  - name: land
    parallel:
      branches:
        - {robot: drone1, behavior: LAND}
        - {robot: drone2, behavior: LAND}
)";

std::string together(double hold_s) {
  std::string text = kTogether;
  for (size_t at = text.find("HOLD"); at != std::string::npos; at = text.find("HOLD")) {
    text.replace(at, 4, std::to_string(hold_s));
  }
  return text;
}

class FleetMissionsTest : public ::testing::Test {
 protected:
  void SetUp() override {
    char dir[] = "/tmp/fleet_missions_XXXXXX";
    ASSERT_NE(mkdtemp(dir), nullptr);
    state_dir_ = dir;
    // The coordinator's --mission-dir, where missions import sub-missions.
    char missions[] = "/tmp/fleet_mission_dir_XXXXXX";
    ASSERT_NE(mkdtemp(missions), nullptr);
    mission_dir_ = missions;
    ASSERT_TRUE(broker_.start()) << broker_.error();
    simulator_ = std::make_unique<support::ServerProcess>(
        BEHAVIORLIB_SIMULATOR_PATH,
        support::deterministicSimulatorArgs(
            {"--channel", broker_.address(), "--vehicles", "drone1,drone2", "--seed", "7"}, 2));
    ASSERT_TRUE(simulator_->start()) << simulator_->error();
    ASSERT_NO_FATAL_FAILURE(startCoordinator({}));
    for (const std::string& robot : kRobots) {
      auto system = std::make_unique<support::ServerProcess>(
          BEHAVIORLIB_BASIC_QUADROTOR_BEHAVIORS_PATH,
          support::followTimeArgs(
              {"--robot-id", robot, "--channel", broker_.address(), "--clock", "sim",
               "--flight-controller", simulator_->address(), "--config",
               BEHAVIORLIB_BASIC_CONFIG_PATH, "--coordinator", coordinator_->address()},
              simulator_->address()));
      ASSERT_TRUE(system->start()) << system->error();
      systems_[robot] = std::move(system);
    }
    ASSERT_NO_FATAL_FAILURE(waitForSystems());
  }

  void TearDown() override {
    for (auto& [robot, system] : systems_) {
      if (system && system->running()) system->kill();
    }
    if (coordinator_ && coordinator_->running()) {
      EXPECT_EQ(coordinator_->terminate(), 0) << "the coordinator exits 0 on SIGTERM";
    }
    if (simulator_ && simulator_->running()) simulator_->kill();
    std::filesystem::remove_all(state_dir_);
    std::filesystem::remove_all(mission_dir_);
  }

  void startCoordinator(std::vector<std::string> extra) {
    std::vector<std::string> args = {"--catalog",
                                     kCatalog,
                                     "--state-dir",
                                     state_dir_,
                                     "--mission-dir",
                                     mission_dir_,
                                     "--clock",
                                     "sim",
                                     "--channel",
                                     broker_.address(),
                                     "--heartbeat-interval-s",
                                     "0.25"};
    args.insert(args.end(), extra.begin(), extra.end());
    coordinator_ = std::make_unique<support::ServerProcess>(BEHAVIORLIB_COORDINATOR_PATH, args);
    ASSERT_TRUE(coordinator_->start()) << coordinator_->error();
    client_ = std::make_unique<CoordinatorClient>(coordinator_->address());
    stub_ = v1::Coordinator::NewStub(
        grpc::CreateChannel(coordinator_->address(), grpc::InsecureChannelCredentials()));
  }

  // Each robot's system registered and UP.
  void waitForSystems() {
    for (const std::string& robot : kRobots) {
      ASSERT_TRUE(waitUntil(
          [&] {
            auto reply = client_->listSystems(robot);
            return reply.status.ok() && reply.response.systems_size() == 1 &&
                   reply.response.systems(0).state() == v1::SYSTEM_STATE_UP;
          },
          seconds(10)))
          << robot << ": " << json(client_->listSystems(robot).response);
    }
  }

  Reply<v1::StartMissionResponse> start(const std::string& text, const std::string& id = "") {
    v1::StartMissionRequest request;
    request.set_text(text);
    request.set_mission_id(id);
    return unary(*stub_, &v1::Coordinator::Stub::StartMission, request);
  }

  // Each robot's behaviors as its own system recorded them: activations by
  // behavior.
  std::map<std::string, int> activations(const std::string& robot) {
    std::map<std::string, int> count;
    for (const auto& e : systemHistory(systems_.at(robot)->address())) {
      count[e.behavior()] += e.has_activated();
    }
    return count;
  }

  std::string state_dir_;
  std::string mission_dir_;
  support::ServerProcess broker_{BEHAVIORLIB_CHANNEL_BROKER_PATH, {}};
  std::unique_ptr<support::ServerProcess> simulator_;
  std::unique_ptr<support::ServerProcess> coordinator_;
  std::map<std::string, std::unique_ptr<support::ServerProcess>> systems_;
  std::unique_ptr<CoordinatorClient> client_;
  std::unique_ptr<v1::Coordinator::Stub> stub_;
};

const v1::MissionStepRecord* named(const v1::MissionStatus& status, const std::string& name) {
  for (const auto& r : status.steps()) {
    if (r.name() == name) return &r;
  }
  return nullptr;
}

// One mission flies both vehicles: the branches run at once, each on its
// robot; drone1's wait_for is reached only once drone2 is up; a mission on
// one of its robots is refused while it runs.
TEST_F(FleetMissionsTest, ParallelBranchesFlyBothVehiclesAndWaitForEachOther) {
  auto started = start(together(2.0), "together-1");
  ASSERT_TRUE(started.status.ok()) << describe(started.status);
  const v1::MissionStatus& first = started.response.status();
  EXPECT_EQ(first.robot_id(), "drone1");
  EXPECT_EQ(std::vector<std::string>(first.robot_ids().begin(), first.robot_ids().end()), kRobots);
  // drone2 runs the fleet mission: another mission for it is refused.
  auto other = start("name: alone\nrobot: drone2\nsteps:\n  - behavior: LAND\n");
  EXPECT_EQ(other.status.error_code(), grpc::StatusCode::FAILED_PRECONDITION)
      << describe(other.status);
  EXPECT_NE(other.status.error_message().find("robot 'drone2' runs mission 'together-1'"),
            std::string::npos)
      << other.status.error_message();

  MissionWatcher watcher(coordinator_->address(), "together-1");
  // At some point both vehicles' steps run at once.
  auto both = watcher.waitFor(
      [](const v1::MissionStatus& s) {
        std::set<std::string> running;
        for (const auto& r : s.steps()) {
          if (r.state() == v1::MISSION_STEP_STATE_RUNNING && !r.behavior().empty()) {
            running.insert(r.robot_id());
          }
        }
        return running.size() == 2;
      },
      seconds(60));
  ASSERT_TRUE(both) << "the branches never ran at once";
  const auto last = watcher.waitEnd(seconds(90));
  ASSERT_TRUE(last);
  ASSERT_EQ(last->state(), v1::MISSION_STATE_SUCCEEDED) << json(*last);

  const auto* up2 = named(*last, "up_drone2");
  const auto* wait = named(*last, "wait_drone2");
  ASSERT_TRUE(up2 && wait) << json(*last);
  EXPECT_EQ(up2->robot_id(), "drone2");
  EXPECT_EQ(up2->node(), "steps/0/attempt/1/branch/1/steps/1");
  EXPECT_EQ(wait->robot_id(), "drone1");
  EXPECT_EQ(wait->wait_for(), "step 'up_drone2' achieved");
  EXPECT_EQ(wait->cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED);
  // The wait ended only after drone2's take-off ended: it is recorded after.
  int up2_at = -1, wait_end_at = -1;
  const std::vector<v1::MissionStatus> statuses = watcher.statuses();
  for (size_t i = 0; i < statuses.size(); ++i) {
    const v1::MissionStatus& s = statuses[i];
    const auto* u = named(s, "up_drone2");
    const auto* w = named(s, "wait_drone2");
    if (up2_at < 0 && u && u->state() == v1::MISSION_STEP_STATE_FINISHED) up2_at = int(i);
    if (wait_end_at < 0 && w && w->state() == v1::MISSION_STEP_STATE_FINISHED) {
      wait_end_at = int(i);
    }
  }
  EXPECT_GE(up2_at, 0);
  EXPECT_GT(wait_end_at, up2_at);
  for (const std::string& robot : kRobots) {
    SCOPED_TRACE(robot);
    const auto count = activations(robot);
    EXPECT_EQ(count.at("TAKE_OFF"), 1);
    EXPECT_EQ(count.at("LAND"), 1);
    EXPECT_EQ(count.at("WAIT"), 2);
  }
}

// kill -9 of the coordinator while both branches of a fleet mission hold
// their vehicles in the air; the coordinator restarted on the same state
// directory resumes each branch where it was: the mission succeeds, and each
// vehicle's system recorded every behavior activated once.
TEST_F(FleetMissionsTest, AKilledCoordinatorResumesEveryBranchWithoutDoublingActivations) {
  auto started = start(together(20.0), "together-crash");
  ASSERT_TRUE(started.status.ok()) << describe(started.status);
  std::map<std::string, std::string> hold_ids;
  {
    MissionWatcher watcher(coordinator_->address(), "together-crash");
    auto holding = watcher.waitFor(
        [](const v1::MissionStatus& s) {
          const auto* one = named(s, "hold_drone1");
          const auto* two = named(s, "hold_drone2");
          return one && two && !one->activation_id().empty() && !two->activation_id().empty();
        },
        seconds(60));
    ASSERT_TRUE(holding) << "the branches did not reach their holds";
    for (const std::string& robot : kRobots) {
      hold_ids[robot] = named(*holding, "hold_" + robot)->activation_id();
    }
  }
  const int port = coordinator_->grpcPort();
  coordinator_->kill();
  ASSERT_NO_FATAL_FAILURE(startCoordinator({"--listen", "127.0.0.1:" + std::to_string(port)}));
  ASSERT_EQ(coordinator_->grpcPort(), port);
  ASSERT_NO_FATAL_FAILURE(waitForSystems());
  MissionWatcher watcher(coordinator_->address(), "together-crash");
  const auto last = watcher.waitEnd(seconds(90));
  ASSERT_TRUE(last);
  ASSERT_EQ(last->state(), v1::MISSION_STATE_SUCCEEDED) << json(*last);
  for (const std::string& robot : kRobots) {
    SCOPED_TRACE(robot);
    const auto* hold = named(*last, "hold_" + robot);
    ASSERT_NE(hold, nullptr);
    EXPECT_EQ(hold->activation_id(), hold_ids[robot]) << "the same activation, not a new one";
    EXPECT_EQ(hold->attempt(), 1);
    EXPECT_EQ(hold->cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED);
    const std::map<std::string, int> once = {
        {"WAIT", 2}, {"TAKE_OFF", 1}, {"LAND", 1}, {"SELF_LOCALIZE_WITH_GROUND_TRUTH", 1}};
    EXPECT_EQ(activations(robot), once);
  }
  // Each record once: no step was started again.
  std::map<std::string, int> nodes;
  for (const auto& r : last->steps()) ++nodes[r.node()];
  for (const auto& [node, n] : nodes) EXPECT_EQ(n, 1) << node;
}

// kill -9 of the coordinator in the second iteration of a loop inside a
// sub-mission imported from the mission directory, on drone2 of a fleet
// mission; the restarted coordinator parses the imported file as journaled
// (it is deleted from the directory meanwhile) and resumes at that
// iteration: each iteration's behaviors activated once.
TEST_F(FleetMissionsTest, AKilledCoordinatorResumesALoopOfAnImportedSubMission) {
  {
    std::ofstream out(mission_dir_ + "/laps.yaml");
    out << "submissions:\n"
           "  laps:\n"
           "    parameters: {hold_s: {type: number, min: 0.1, max: 60}}\n"
           "    steps:\n"
           "      - repeat: {times: 3}\n"
           "        steps:\n"
           "          - {name: lap, behavior: WAIT, parameters: {duration_s: "
           "\"${param.hold_s}\"}}\n";
  }
  auto started = start(
      "name: laps_on_drone2\n"
      "robot: drone1\n"
      "import: [laps.yaml]\n"
      "steps:\n"
      "  - {robot: drone2, call: laps, with: {hold_s: 8}}\n",
      "laps-crash");
  ASSERT_TRUE(started.status.ok()) << describe(started.status);
  std::string second_id;
  {
    MissionWatcher watcher(coordinator_->address(), "laps-crash");
    auto second = watcher.waitFor(
        [](const v1::MissionStatus& s) {
          for (const auto& r : s.steps()) {
            if (r.node().find("/iteration/1/") != std::string::npos && !r.activation_id().empty()) {
              return true;
            }
          }
          return false;
        },
        seconds(60));
    ASSERT_TRUE(second) << "the loop did not reach its second iteration";
    for (const auto& r : second->steps()) {
      if (r.node().find("/iteration/1/") != std::string::npos) second_id = r.activation_id();
    }
  }
  const int port = coordinator_->grpcPort();
  coordinator_->kill();
  std::filesystem::remove(mission_dir_ + "/laps.yaml");  // the journal has its text
  ASSERT_NO_FATAL_FAILURE(startCoordinator({"--listen", "127.0.0.1:" + std::to_string(port)}));
  ASSERT_NO_FATAL_FAILURE(waitForSystems());
  MissionWatcher watcher(coordinator_->address(), "laps-crash");
  const auto last = watcher.waitEnd(seconds(90));
  ASSERT_TRUE(last);
  ASSERT_EQ(last->state(), v1::MISSION_STATE_SUCCEEDED) << json(*last);
  std::vector<std::string> laps;
  for (const auto& r : last->steps()) {
    if (r.name() != "lap") continue;
    laps.push_back(r.node());
    EXPECT_EQ(r.robot_id(), "drone2");
    if (r.node().find("/iteration/1/") != std::string::npos) {
      EXPECT_EQ(r.activation_id(), second_id) << "the same activation, not a new one";
    }
  }
  EXPECT_EQ(laps, (std::vector<std::string>{
                      "steps/0/attempt/1/call/steps/0/attempt/1/iteration/0/steps/0",
                      "steps/0/attempt/1/call/steps/0/attempt/1/iteration/1/steps/0",
                      "steps/0/attempt/1/call/steps/0/attempt/1/iteration/2/steps/0"}));
  EXPECT_EQ(activations("drone2").at("WAIT"), 3) << "each iteration's WAIT once";
  EXPECT_EQ(activations("drone1").count("WAIT"), 0u);
}

// The check before flight looks up each step on its own robot: a robot with
// no registered system is a problem with its line, and each robot's steps
// are planned against that robot.
TEST_F(FleetMissionsTest, TheCheckFindsAnUnregisteredRobotOfAFleetMission) {
  std::string text = together(1.0);
  text.replace(text.find("- robot: drone2\n          steps:"), 15, "- robot: drone3");
  v1::CheckMissionRequest request;
  request.set_text(text);
  request.set_source_name("together.yaml");
  auto checked = unary(*stub_, &v1::Coordinator::Stub::CheckMission, request);
  ASSERT_TRUE(checked.status.ok()) << describe(checked.status);
  ASSERT_EQ(checked.response.problems_size(), 1) << json(checked.response);
  EXPECT_EQ(checked.response.problems(0).description(),
            "together.yaml: robot 'drone3' has no registered behavior system: start its systems "
            "first");
  auto refused = start(text);
  EXPECT_EQ(refused.status.error_code(), grpc::StatusCode::FAILED_PRECONDITION)
      << describe(refused.status);

  request.set_text(together(1.0));
  checked = unary(*stub_, &v1::Coordinator::Stub::CheckMission, request);
  ASSERT_TRUE(checked.status.ok()) << describe(checked.status);
  EXPECT_EQ(checked.response.problems_size(), 0) << json(checked.response);
  std::set<std::string> planned;
  for (const auto& plan : checked.response.plans()) planned.insert(plan.node());
  EXPECT_TRUE(planned.contains("steps/0/attempt/1/branch/1/steps/1")) << json(checked.response);
  EXPECT_TRUE(planned.contains("steps/1/attempt/1/branch/1/steps/0")) << json(checked.response);
}

// docs/missions.md's fleet examples ("<!-- expect: SUCCEEDED (fleet) -->")
// run as documented.
TEST_F(FleetMissionsTest, DocumentedFleetMissionsRunAsDocumented) {
  std::ifstream in(BEHAVIORLIB_MISSIONS_DOC_PATH);
  ASSERT_TRUE(in) << "cannot read " << BEHAVIORLIB_MISSIONS_DOC_PATH;
  std::vector<std::pair<int, std::string>> examples;
  bool fleet = false, in_block = false;
  std::string line;
  for (int number = 1; std::getline(in, line); ++number) {
    if (in_block) {
      if (line == "```") {
        in_block = false;
      } else {
        examples.back().second += line + "\n";
      }
    } else if (line.rfind("<!-- expect: ", 0) == 0) {
      fleet = line == "<!-- expect: SUCCEEDED (fleet) -->";
    } else if (line == "```yaml" && fleet) {
      examples.emplace_back(number, "");
      in_block = true;
      fleet = false;
    }
  }
  ASSERT_GE(examples.size(), 1u) << "the page lost its fleet example";
  for (const auto& [number, yaml] : examples) {
    SCOPED_TRACE("docs/missions.md:" + std::to_string(number));
    auto started = start(yaml);
    ASSERT_TRUE(started.status.ok()) << describe(started.status);
    MissionWatcher watcher(coordinator_->address(), started.response.status().mission_id());
    const auto last = watcher.waitEnd(seconds(90));
    ASSERT_TRUE(last);
    EXPECT_EQ(last->state(), v1::MISSION_STATE_SUCCEEDED) << json(*last);
    std::set<std::string> robots;
    for (const auto& r : last->steps()) robots.insert(r.robot_id());
    EXPECT_EQ(robots, std::set<std::string>(kRobots.begin(), kRobots.end()));
  }
}

}  // namespace
}  // namespace coordinator_test
