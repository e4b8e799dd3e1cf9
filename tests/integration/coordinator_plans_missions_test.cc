// The coordinator's activation plans and missions against the real stack:
// the channel broker, the simulator at 5x (fixed seed; fault injection on, for
// a battery drop), basic_quadrotor_behaviors
// and quadrotor_motion_with_pid_control (each registering with --coordinator),
// and the coordinator with the shipped behavior catalog and a --state-dir,
// every one a real process on free loopback ports, driven over gRPC (and
// behaviorctl). Behavior times are simulated time; every wait is bounded in
// wall time. Retention by age is tested on the mission manager built
// in-process, with a clock of the test.

#include <google/protobuf/util/time_util.h>
#include <gtest/gtest.h>
#include <prometheus/registry.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <array>
#include <condition_variable>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <map>
#include <memory>
#include <set>
#include <string>
#include <thread>
#include <tuple>
#include <vector>

#include "absl/strings/str_split.h"
#include "behaviorlib/error_details.h"
#include "behaviorlib/v1/simulator.grpc.pb.h"
#include "coordinator/belief/belief_store.h"
#include "coordinator/control/fleet_control.h"
#include "coordinator/control/mission_manager.h"
#include "coordinator/events/fleet_event_log.h"
#include "coordinator/metrics/coordinator_metrics.h"
#include "coordinator/registry/registry.h"
#include "coordinator_test_support.h"
#include "mission_test_support.h"
#include "support/deterministic.h"
#include "support/run_command.h"
#include "support/server_process.h"

namespace coordinator_test {
namespace {

constexpr char kRobot[] = "drone1";
constexpr char kCatalog[] = BEHAVIORLIB_CATALOG_PATH;
constexpr char kDemoMission[] = BEHAVIORLIB_DEMO_MISSION_PATH;
constexpr char kSeed[] = "7";
constexpr char kSelfLocalize[] = "SELF_LOCALIZE_WITH_GROUND_TRUTH";
// The shipped demo's localization (multi_sensor_fusion).
constexpr char kDemoLocalize[] = "SELF_LOCALIZE_WITH_EKF_SENSOR_FUSION";
constexpr char kPid[] = "QUADROTOR_PID_MOTION_CONTROL";
constexpr char kReckon[] = "ESTIMATE_POSITION_WITH_LINEAR_SPEED";
// A mission's start: drone1 localized, landed by its safety step, settled.
constexpr char kDemoPreamble[] =
    "robot: drone1\n"
    "recurrent: [{behavior: SELF_LOCALIZE_WITH_GROUND_TRUTH}]\n"
    "safety: [{behavior: LAND}]\n"
    "steps:\n"
    "  - {name: settle, behavior: WAIT, parameters: {duration_s: 1.0}}\n";

/// The behavior events of kRobot in the coordinator's WatchEvents, kept in
/// order; waits look at the whole history, so the order of the waits does
/// not matter.
class FleetRecorder {
 public:
  explicit FleetRecorder(const std::string& address)
      : stub_(v1::Coordinator::NewStub(
            grpc::CreateChannel(address, grpc::InsecureChannelCredentials()))) {
    context_.set_deadline(std::chrono::system_clock::now() + seconds(120));
    v1::WatchFleetEventsRequest request;
    request.add_robot_ids(kRobot);
    reader_ = stub_->WatchEvents(&context_, request);
    thread_ = std::thread([this] {
      v1::WatchFleetEventsResponse message;
      while (reader_->Read(&message)) {
        std::lock_guard lock(mutex_);
        if (message.has_start()) started_ = true;
        if (message.has_event() && message.event().has_behavior_event()) {
          events_.push_back(message.event().behavior_event());
        }
        cv_.notify_all();
      }
      reader_->Finish();
      std::lock_guard lock(mutex_);
      ended_ = true;
      cv_.notify_all();
    });
  }
  ~FleetRecorder() {
    context_.TryCancel();
    thread_.join();
  }
  FleetRecorder(const FleetRecorder&) = delete;
  FleetRecorder& operator=(const FleetRecorder&) = delete;

  bool waitStarted(milliseconds timeout = kEventTimeout) {
    std::unique_lock lock(mutex_);
    return cv_.wait_for(lock, timeout, [&] { return started_; });
  }

  /// The first event matching `predicate`, waiting up to `timeout`.
  std::optional<v1::BehaviorEvent> waitFor(
      const std::function<bool(const v1::BehaviorEvent&)>& predicate,
      milliseconds timeout = kEventTimeout) {
    std::unique_lock lock(mutex_);
    std::optional<v1::BehaviorEvent> found;
    cv_.wait_for(lock, timeout, [&] {
      for (const auto& e : events_) {
        if (predicate(e)) {
          found = e;
          return true;
        }
      }
      return ended_;
    });
    return found;
  }
  std::optional<v1::BehaviorEvent> finished(const std::string& activation_id,
                                            milliseconds timeout = kEventTimeout) {
    return waitFor(
        [&](const v1::BehaviorEvent& e) {
          return e.activation_id() == activation_id && e.has_finished();
        },
        timeout);
  }
  std::optional<v1::BehaviorEvent> activated(const std::string& activation_id,
                                             milliseconds timeout = kEventTimeout) {
    return waitFor(
        [&](const v1::BehaviorEvent& e) {
          return e.activation_id() == activation_id && e.has_activated();
        },
        timeout);
  }
  std::vector<v1::BehaviorEvent> events() {
    std::lock_guard lock(mutex_);
    return events_;
  }

 private:
  std::unique_ptr<v1::Coordinator::Stub> stub_;
  grpc::ClientContext context_;
  std::unique_ptr<grpc::ClientReader<v1::WatchFleetEventsResponse>> reader_;
  std::thread thread_;
  std::mutex mutex_;
  std::condition_variable cv_;
  std::vector<v1::BehaviorEvent> events_;
  bool started_ = false;
  bool ended_ = false;
};

using support::run;

// JSON of a path_m value: [{"x": .., "y": .., "z": ..}, ...].
std::string pathJson(const std::vector<std::array<double, 3>>& points) {
  std::string out = "[";
  for (size_t i = 0; i < points.size(); ++i) {
    out += (i ? ", " : "") + std::string("{\"x\": ") + std::to_string(points[i][0]) +
           ", \"y\": " + std::to_string(points[i][1]) + ", \"z\": " + std::to_string(points[i][2]) +
           "}";
  }
  return out + "]";
}

// The points of a path_m value: {x, y, z} objects, an absent coordinate
// being 0 (a system's Struct of its parameter message leaves zeros out).
std::vector<std::array<double, 3>> pointsOf(const google::protobuf::Value& value) {
  std::vector<std::array<double, 3>> points;
  for (const auto& item : value.list_value().values()) {
    std::array<double, 3> point{};
    const auto& fields = item.struct_value().fields();
    const char* const axes[] = {"x", "y", "z"};
    for (size_t i = 0; i < 3; ++i) {
      if (auto it = fields.find(axes[i]); it != fields.end()) point[i] = it->second.number_value();
    }
    points.push_back(point);
  }
  return points;
}

std::string causeOf(const v1::BehaviorEvent& e) {
  return v1::TerminationCause_Name(e.finished().cause()) + " " + e.finished().message();
}

class CoordinatorPlansMissionsTest : public ::testing::Test {
 protected:
  void SetUp() override {
    char dir[] = "/tmp/coordinator_plans_XXXXXX";
    ASSERT_NE(mkdtemp(dir), nullptr);
    state_dir_ = dir;
    // The coordinator reads StartMission.file_path only in its --mission-dir.
    char missions[] = "/tmp/coordinator_missions_XXXXXX";
    ASSERT_NE(mkdtemp(missions), nullptr);
    mission_dir_ = missions;
    demo_mission_ = mission_dir_ + "/demo_square.yaml";
    std::filesystem::copy_file(kDemoMission, demo_mission_);
    ASSERT_TRUE(broker_.start()) << broker_.error();
    simulator_ = std::make_unique<support::ServerProcess>(
        BEHAVIORLIB_SIMULATOR_PATH,
        support::deterministicSimulatorArgs({"--channel", broker_.address(), "--vehicles", kRobot,
                                             "--seed", kSeed, "--enable-fault-injection"},
                                            1));
    ASSERT_TRUE(simulator_->start()) << simulator_->error();
    ASSERT_NO_FATAL_FAILURE(startCoordinator({}));
    basic_ = startSystem(BEHAVIORLIB_BASIC_QUADROTOR_BEHAVIORS_PATH, BEHAVIORLIB_BASIC_CONFIG_PATH);
    pid_ = startSystem(BEHAVIORLIB_PID_SYSTEM_PATH, BEHAVIORLIB_PID_CONFIG_PATH);
    // The demo's localization: the EKF on GPS, IMU, barometer and flow.
    fusion_ = startSystem(BEHAVIORLIB_MULTI_SENSOR_FUSION_PATH, BEHAVIORLIB_FUSION_CONFIG_PATH);
    ASSERT_TRUE(basic_ && pid_ && fusion_);
    ASSERT_NO_FATAL_FAILURE(waitForSystems());
  }

  void TearDown() override {
    recorder_.reset();
    for (auto* p : {&fusion_, &pid_, &basic_}) {
      if (*p && (*p)->running()) (*p)->kill();
    }
    if (coordinator_ && coordinator_->running()) {
      EXPECT_EQ(coordinator_->terminate(), 0) << "the coordinator exits 0 on SIGTERM";
    }
    if (simulator_ && simulator_->running()) simulator_->kill();
    std::filesystem::remove_all(state_dir_);
    std::filesystem::remove_all(mission_dir_);
  }

  void startCoordinator(std::vector<std::string> extra) {
    std::vector<std::string> args = {"--catalog", kCatalog, "--state-dir", state_dir_,
                                     "--mission-dir", mission_dir_, "--heartbeat-interval-s",
                                     "0.25",
                                     // The vehicles' topics, for the missions' `when:`.
                                     "--channel", broker_.address()};
    args.insert(args.end(), extra.begin(), extra.end());
    coordinator_ = std::make_unique<support::ServerProcess>(BEHAVIORLIB_COORDINATOR_PATH, args);
    ASSERT_TRUE(coordinator_->start()) << coordinator_->error();
    client_ = std::make_unique<CoordinatorClient>(coordinator_->address());
    stub_ = v1::Coordinator::NewStub(
        grpc::CreateChannel(coordinator_->address(), grpc::InsecureChannelCredentials()));
  }

  std::unique_ptr<support::ServerProcess> startSystem(const std::string& binary,
                                                      const std::string& config) {
    auto system = std::make_unique<support::ServerProcess>(
        binary,
        support::followTimeArgs({"--robot-id", kRobot, "--channel", broker_.address(), "--clock",
                                 "sim", "--flight-controller", simulator_->address(), "--config",
                                 config, "--coordinator", coordinator_->address()},
                                simulator_->address()));
    if (!system->start()) {
      ADD_FAILURE() << binary << ": " << system->error();
      return nullptr;
    }
    return system;
  }

  // The three systems of kRobot registered and UP.
  void waitForSystems() {
    ASSERT_TRUE(waitUntil(
        [&] {
          auto reply = client_->listSystems(kRobot);
          if (!reply.status.ok() || reply.response.systems_size() != 3) return false;
          for (const auto& s : reply.response.systems()) {
            if (s.state() != v1::SYSTEM_STATE_UP) return false;
          }
          return true;
        },
        seconds(10)))
        << json(client_->listSystems(kRobot).response);
  }

  // The recorder of the coordinator's event stream (started now).
  FleetRecorder& recorder() {
    recorder_ = std::make_unique<FleetRecorder>(coordinator_->address());
    EXPECT_TRUE(recorder_->waitStarted());
    return *recorder_;
  }

  Reply<v1::ActivateFleetBehaviorResponse> activate(const std::string& behavior,
                                                    const std::string& parameters_json,
                                                    bool dry_run = false) {
    v1::ActivateFleetBehaviorRequest request;
    request.set_robot_id(kRobot);
    request.set_behavior(behavior);
    *request.mutable_parameters() = structFromJson(parameters_json);
    request.set_dry_run(dry_run);
    // A plan waits for events and retries situation checks: more than kCallTimeout.
    grpc::ClientContext context;
    context.set_deadline(std::chrono::system_clock::now() + seconds(20));
    Reply<v1::ActivateFleetBehaviorResponse> reply;
    reply.status = stub_->ActivateBehavior(&context, request, &reply.response);
    return reply;
  }

  // The behavior's state and activation id as the coordinator lists them.
  std::pair<v1::BehaviorState, std::string> stateOf(const std::string& behavior) {
    auto reply = client_->listBehaviors(kRobot, behavior);
    EXPECT_TRUE(reply.status.ok()) << describe(reply.status);
    if (reply.response.behaviors_size() != 1) {
      ADD_FAILURE() << behavior << " listed " << reply.response.behaviors_size() << " times";
      return {v1::BEHAVIOR_STATE_UNSPECIFIED, ""};
    }
    const auto& b = reply.response.behaviors(0);
    return {b.description().state(), b.activation_id()};
  }

  // The names of kRobot's active (or paused) behaviors.
  std::set<std::string> activeBehaviors() {
    auto reply = client_->listBehaviors(kRobot);
    EXPECT_TRUE(reply.status.ok()) << describe(reply.status);
    std::set<std::string> active;
    for (const auto& b : reply.response.behaviors()) {
      if (b.description().state() == v1::BEHAVIOR_STATE_ACTIVE ||
          b.description().state() == v1::BEHAVIOR_STATE_PAUSED) {
        active.insert(b.description().name());
      }
    }
    return active;
  }

  Reply<v1::StartMissionResponse> startMissionText(const std::string& text,
                                                   const std::string& mission_id = "") {
    v1::StartMissionRequest request;
    request.set_text(text);
    request.set_mission_id(mission_id);
    return unary(*stub_, &v1::Coordinator::Stub::StartMission, request);
  }
  Reply<v1::StartMissionResponse> startMissionFile(const std::string& path,
                                                   const std::string& mission_id = "") {
    v1::StartMissionRequest request;
    request.set_file_path(path);
    request.set_mission_id(mission_id);
    return unary(*stub_, &v1::Coordinator::Stub::StartMission, request);
  }
  Reply<v1::MissionControlResponse> control(
      grpc::Status (v1::Coordinator::Stub::*method)(grpc::ClientContext*,
                                                    const v1::MissionControlRequest&,
                                                    v1::MissionControlResponse*),
      const std::string& mission_id, const std::string& reason = "") {
    v1::MissionControlRequest request;
    request.set_mission_id(mission_id);
    request.set_reason(reason);
    return unary(*stub_, method, request);
  }
  Reply<v1::WriteBeliefResponse> writeBelief(const std::string& key,
                                             const std::string& value_json) {
    v1::WriteBeliefRequest request;
    request.set_key(key);
    EXPECT_TRUE(
        google::protobuf::util::JsonStringToMessage(value_json, request.mutable_value()).ok())
        << value_json;
    request.set_writer("operator");
    return unary(*stub_, &v1::Coordinator::Stub::WriteBelief, request);
  }

  // Runs the mission `text` to its end (bounded); its final status.
  v1::MissionStatus runMission(const std::string& text, milliseconds timeout = seconds(30)) {
    auto started = startMissionText(text);
    EXPECT_TRUE(started.status.ok()) << describe(started.status);
    if (!started.status.ok()) return {};
    MissionWatcher watcher(coordinator_->address(), started.response.status().mission_id());
    return watcher.waitEnd(timeout).value_or(v1::MissionStatus());
  }

  std::string state_dir_;
  std::string mission_dir_;
  std::string demo_mission_;  // the shipped demo, copied into mission_dir_
  support::ServerProcess broker_{BEHAVIORLIB_CHANNEL_BROKER_PATH, {}};
  std::unique_ptr<support::ServerProcess> simulator_;
  std::unique_ptr<support::ServerProcess> coordinator_;
  std::unique_ptr<support::ServerProcess> basic_;
  std::unique_ptr<support::ServerProcess> pid_;
  std::unique_ptr<support::ServerProcess> fusion_;
  std::unique_ptr<CoordinatorClient> client_;
  std::unique_ptr<v1::Coordinator::Stub> stub_;
  std::unique_ptr<FleetRecorder> recorder_;
};

// Issue items: a dry run returns the plan and activates nothing; requirements
// are activated by the plan; a failing step rolls the plan back; an
// incompatible activation deactivates the other (INTERRUPTED).
TEST_F(CoordinatorPlansMissionsTest, PlansActivateRequirementsRollBackAndInterruptConflicts) {
  FleetRecorder& events = recorder();
  const std::string path = pathJson({{3.0, 0.0, 1.0}, {3.0, 3.0, 1.0}});

  // 1. Dry run of FOLLOW_PATH on a robot with nothing active: the plan, and
  // nothing activated.
  auto dry = activate("FOLLOW_PATH", "{\"path_m\": " + path + ", \"speed_m_s\": 0.5}", true);
  ASSERT_TRUE(dry.status.ok()) << describe(dry.status);
  EXPECT_TRUE(dry.response.activation().activation_id().empty());
  EXPECT_EQ(dry.response.system(), "quadrotor_motion_with_pid_control");
  using Step = v1::ActivationPlanStep;
  const std::vector<std::pair<Step::Kind, std::string>> expected = {
      {Step::KIND_CHECK_SITUATION, kSelfLocalize}, {Step::KIND_ACTIVATE, kSelfLocalize},
      {Step::KIND_CHECK_SITUATION, kPid},          {Step::KIND_ACTIVATE, kPid},
      {Step::KIND_CHECK_SITUATION, "FOLLOW_PATH"}, {Step::KIND_ACTIVATE, "FOLLOW_PATH"}};
  ASSERT_EQ(dry.response.plan_size(), static_cast<int>(expected.size())) << json(dry.response);
  for (size_t i = 0; i < expected.size(); ++i) {
    const auto& step = dry.response.plan(static_cast<int>(i));
    EXPECT_EQ(step.kind(), expected[i].first) << json(step);
    EXPECT_EQ(step.behavior(), expected[i].second) << json(step);
  }
  EXPECT_EQ(dry.response.plan(1).reason(), "provides self_localization required by FOLLOW_PATH");
  EXPECT_EQ(dry.response.plan(3).reason(), "provides motion_control required by FOLLOW_PATH");
  EXPECT_EQ(dry.response.plan(5).reason(), "the target");
  EXPECT_EQ(dry.response.plan(5).parameters().fields().at("speed_m_s").number_value(), 0.5)
      << "the caller's parameters in the target's step";
  EXPECT_EQ(dry.response.plan(5).parameters().fields().at("path_m").list_value().values_size(), 2);
  EXPECT_TRUE(activeBehaviors().empty()) << "a dry run activates nothing";
  EXPECT_FALSE(events.waitFor([](const v1::BehaviorEvent&) { return true; }, milliseconds(300)))
      << "a dry run activates nothing: " << json(events.events().front());

  // 2a. TAKE_OFF: the plan activates its requirement, self-localization.
  auto take_off = activate("TAKE_OFF", R"({"altitude_m": 1.0})");
  ASSERT_TRUE(take_off.status.ok()) << describe(take_off.status);
  ASSERT_EQ(take_off.response.plan_size(), 4) << json(take_off.response);
  EXPECT_EQ(take_off.response.plan(1).kind(), Step::KIND_ACTIVATE);
  EXPECT_EQ(take_off.response.plan(1).behavior(), kSelfLocalize);
  EXPECT_EQ(take_off.response.plan(1).reason(), "provides self_localization required by TAKE_OFF");
  const auto [localize_state, localize_id] = stateOf(kSelfLocalize);
  EXPECT_EQ(localize_state, v1::BEHAVIOR_STATE_ACTIVE);
  ASSERT_TRUE(events.activated(localize_id)) << "activated by the plan, seen in the stream";
  const std::string take_off_id = take_off.response.activation().activation_id();
  auto took_off = events.finished(take_off_id, seconds(20));
  ASSERT_TRUE(took_off) << "TAKE_OFF did not finish";
  ASSERT_EQ(took_off->finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED)
      << causeOf(*took_off);

  // 4. A failing step rolls the plan back: the PID controller is activated
  // as FOLLOW_PATH's requirement, FOLLOW_PATH refuses its parameters, the
  // controller is stopped again; self-localization (not started by this
  // plan) stays.
  auto refused = activate("FOLLOW_PATH", "{\"path_m\": " + path + ", \"speed_m_s\": 50}");
  ASSERT_EQ(refused.status.error_code(), grpc::StatusCode::INVALID_ARGUMENT)
      << describe(refused.status);
  const std::string message = refused.status.error_message();
  EXPECT_NE(message.find("step 4 of 4 (activate FOLLOW_PATH)"), std::string::npos) << message;
  EXPECT_NE(message.find("speed_m_s"), std::string::npos) << message;
  EXPECT_NE(message.find("what the plan activated was stopped"), std::string::npos) << message;
  EXPECT_EQ(stateOf(kPid).first, v1::BEHAVIOR_STATE_INACTIVE) << "rolled back";
  EXPECT_EQ(stateOf("FOLLOW_PATH").first, v1::BEHAVIOR_STATE_INACTIVE);
  EXPECT_EQ(stateOf(kSelfLocalize), std::make_pair(v1::BEHAVIOR_STATE_ACTIVE, localize_id));
  auto rolled_back = events.waitFor(
      [](const v1::BehaviorEvent& e) { return e.behavior() == kPid && e.has_finished(); });
  ASSERT_TRUE(rolled_back) << "the controller the plan started was not stopped";
  EXPECT_EQ(rolled_back->finished().cause(), v1::TERMINATION_CAUSE_INTERRUPTED);
  EXPECT_TRUE(events.activated(rolled_back->activation_id())) << "it had been activated";

  // 2b. FOLLOW_PATH: the plan activates the PID controller (self-localization
  // is active already).
  auto follow = activate("FOLLOW_PATH", "{\"path_m\": " + path + ", \"speed_m_s\": 0.5}");
  ASSERT_TRUE(follow.status.ok()) << describe(follow.status);
  ASSERT_EQ(follow.response.plan_size(), 4) << json(follow.response);
  EXPECT_EQ(follow.response.plan(1).behavior(), kPid);
  EXPECT_EQ(follow.response.plan(1).kind(), Step::KIND_ACTIVATE);
  EXPECT_EQ(follow.response.plan(1).reason(), "provides motion_control required by FOLLOW_PATH");
  const std::string follow_id = follow.response.activation().activation_id();
  const auto [pid_state, pid_id] = stateOf(kPid);
  ASSERT_EQ(pid_state, v1::BEHAVIOR_STATE_ACTIVE);
  EXPECT_NE(pid_id, rolled_back->activation_id()) << "a new activation";
  EXPECT_EQ(stateOf("FOLLOW_PATH"), std::make_pair(v1::BEHAVIOR_STATE_ACTIVE, follow_id));

  // 3. HOVER_WITH_FLIGHT_ACTION_CONTROL holds the platform's commands and
  // the motion reference: FOLLOW_PATH, then its controller, are deactivated
  // and finish INTERRUPTED.
  auto hover = activate("HOVER_WITH_FLIGHT_ACTION_CONTROL", "{}");
  ASSERT_TRUE(hover.status.ok()) << describe(hover.status);
  ASSERT_GE(hover.response.plan_size(), 4) << json(hover.response);
  EXPECT_EQ(hover.response.plan(0).kind(), Step::KIND_DEACTIVATE);
  EXPECT_EQ(hover.response.plan(0).behavior(), "FOLLOW_PATH") << "users before what they use";
  EXPECT_EQ(hover.response.plan(0).reason(),
            "holds motion_reference, which HOVER_WITH_FLIGHT_ACTION_CONTROL needs");
  EXPECT_EQ(hover.response.plan(1).kind(), Step::KIND_DEACTIVATE);
  EXPECT_EQ(hover.response.plan(1).behavior(), kPid);
  EXPECT_EQ(hover.response.plan(1).reason(),
            "holds platform_commands, which HOVER_WITH_FLIGHT_ACTION_CONTROL needs");
  for (const std::string& id : {follow_id, pid_id}) {
    auto finished = events.finished(id);
    ASSERT_TRUE(finished) << id << " did not finish in the coordinator's stream";
    EXPECT_EQ(finished->finished().cause(), v1::TERMINATION_CAUSE_INTERRUPTED)
        << causeOf(*finished);
  }
  EXPECT_EQ(activeBehaviors(),
            (std::set<std::string>{kSelfLocalize, "HOVER_WITH_FLIGHT_ACTION_CONTROL"}));

  // LAND takes over from the hover the same way, and lands.
  auto land = activate("LAND", "{}");
  ASSERT_TRUE(land.status.ok()) << describe(land.status);
  auto hovered = events.finished(hover.response.activation().activation_id());
  ASSERT_TRUE(hovered);
  EXPECT_EQ(hovered->finished().cause(), v1::TERMINATION_CAUSE_INTERRUPTED);
  auto landed = events.finished(land.response.activation().activation_id(), seconds(20));
  ASSERT_TRUE(landed) << "LAND did not finish";
  EXPECT_EQ(landed->finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED) << causeOf(*landed);

  // Each activation of the stream finished exactly once.
  std::map<std::string, int> finished_count;
  for (const auto& e : events.events()) finished_count[e.activation_id()] += e.has_finished();
  for (const auto& [id, n] : finished_count) {
    if (id != localize_id) {
      EXPECT_EQ(n, 1) << id;
    }
  }
}

// The shipped demo mission (take off, 4 m square, rotate, land) through
// StartMission + WatchMission: every step GOAL_ACHIEVED.
TEST_F(CoordinatorPlansMissionsTest, TheDemoMissionSucceedsWithEveryStepGoalAchieved) {
  FleetRecorder& events = recorder();
  auto started = startMissionFile(demo_mission_, "demo-1");
  ASSERT_TRUE(started.status.ok()) << describe(started.status);
  EXPECT_EQ(started.response.status().mission_id(), "demo-1");
  EXPECT_EQ(started.response.status().name(), "demo_square");
  EXPECT_EQ(started.response.status().robot_id(), kRobot);
  EXPECT_EQ(started.response.status().file(), demo_mission_);
  MissionWatcher watcher(coordinator_->address(), "demo-1");
  const auto last = watcher.waitEnd(seconds(45));
  ASSERT_TRUE(last);
  ASSERT_EQ(last->state(), v1::MISSION_STATE_SUCCEEDED) << json(*last);
  const std::vector<std::string> behaviors = {"WAIT", "TAKE_OFF", "FOLLOW_PATH",
                                              "ROTATE_WITH_PID_CONTROL", "LAND"};
  ASSERT_EQ(last->steps_size(), static_cast<int>(behaviors.size())) << json(*last);
  for (int i = 0; i < last->steps_size(); ++i) {
    const auto& step = last->steps(i);
    SCOPED_TRACE(json(step));
    EXPECT_EQ(step.behavior(), behaviors[static_cast<size_t>(i)]);
    EXPECT_EQ(step.path_size(), 1);
    EXPECT_EQ(step.attempt(), 1);
    EXPECT_EQ(step.state(), v1::MISSION_STEP_STATE_FINISHED);
    EXPECT_EQ(step.cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED);
    EXPECT_EQ(step.request_id(), "demo-1/steps/" + std::to_string(i) + "/attempt/1");
    auto finished = events.finished(step.activation_id(), seconds(2));
    ASSERT_TRUE(finished) << "the step's activation is in the coordinator's stream";
    EXPECT_EQ(finished->behavior(), step.behavior());
  }
  EXPECT_TRUE(last->has_end_time());
  EXPECT_FALSE(last->in_safety_steps());
  // The stream showed the progress: RUNNING first, then each step.
  const auto statuses = watcher.statuses();
  ASSERT_GE(statuses.size(), 6u);
  EXPECT_EQ(statuses.front().state(), v1::MISSION_STATE_RUNNING);
  // The recurrent self-localization ends with the mission; LAND's plan
  // stopped the controller FOLLOW_PATH's plan had started.
  EXPECT_TRUE(waitUntil([&] { return activeBehaviors().empty(); }, seconds(5)))
      << "still active after the mission: " << activeBehaviors().size();
  auto controller = events.waitFor(
      [](const v1::BehaviorEvent& e) { return e.behavior() == kPid && e.has_finished(); });
  ASSERT_TRUE(controller);
  EXPECT_EQ(controller->finished().cause(), v1::TERMINATION_CAUSE_INTERRUPTED);

  auto got = unary(*stub_, &v1::Coordinator::Stub::GetMission, [] {
    v1::GetMissionRequest r;
    r.set_mission_id("demo-1");
    return r;
  }());
  ASSERT_TRUE(got.status.ok()) << describe(got.status);
  EXPECT_EQ(got.response.status().state(), v1::MISSION_STATE_SUCCEEDED);
  auto listed = unary(*stub_, &v1::Coordinator::Stub::ListMissions, v1::ListMissionsRequest());
  ASSERT_TRUE(listed.status.ok());
  ASSERT_EQ(listed.response.missions_size(), 1);
  EXPECT_EQ(listed.response.missions(0).mission_id(), "demo-1");
  // Starting the same id again returns that mission (idempotent).
  auto again = startMissionFile(demo_mission_, "demo-1");
  ASSERT_TRUE(again.status.ok()) << describe(again.status);
  EXPECT_EQ(again.response.status().state(), v1::MISSION_STATE_SUCCEEDED);
}

// A mission branches on termination causes (REFUSED -> continue, TIME_OUT ->
// retry then fallback, a condition on belief memory, remember); a refusal
// with no branch aborts it and runs its safety step; a bad mission file is
// refused before anything runs, naming its line.
TEST_F(CoordinatorPlansMissionsTest, MissionsBranchOnTerminationCausesAndBadFilesAreRefused) {
  FleetRecorder& events = recorder();

  // Bad mission text: the line of the unknown parameter.
  const std::string bad_text =
      "name: bad\n"
      "robot: drone1\n"
      "steps:\n"
      "  - name: wait\n"
      "    behavior: WAIT\n"
      "    parameters: {duration: 1.0}\n";
  auto bad = startMissionText(bad_text);
  ASSERT_EQ(bad.status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << describe(bad.status);
  EXPECT_NE(bad.status.error_message().find("<mission text>:6: WAIT has no parameter 'duration'"),
            std::string::npos)
      << bad.status.error_message();
  EXPECT_NE(bad.status.error_message().find("duration_s"), std::string::npos)
      << "names the parameters it has: " << bad.status.error_message();
  // A mission file outside --mission-dir, by its path or through "..": refused
  // naming the directory, before it is read.
  const std::string outside = state_dir_ + "/outside.yaml";
  std::ofstream(outside) << "name: outside\nrobot: drone1\nsteps: [{behavior: LAND}]\n";
  for (const std::string& path :
       {outside, "../" + std::filesystem::path(state_dir_).filename().string() + "/outside.yaml",
        std::string("/dev/zero")}) {
    bad = startMissionFile(path);
    ASSERT_EQ(bad.status.error_code(), grpc::StatusCode::PERMISSION_DENIED) << describe(bad.status);
    EXPECT_NE(bad.status.error_message().find(mission_dir_), std::string::npos)
        << bad.status.error_message();
  }
  // A bad mission file: its path and line.
  const std::string bad_file = mission_dir_ + "/bad_mission.yaml";
  std::ofstream(bad_file) << "name: bad_file\n"
                             "robot: drone1\n"
                             "steps:\n"
                             "  - behavior: WAIT\n"
                             "    parameters: {duration_s: 1.0}\n"
                             "    on:\n"
                             "      TIME_OUT: retry_forever\n";
  bad = startMissionFile(bad_file);
  ASSERT_EQ(bad.status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << describe(bad.status);
  EXPECT_NE(bad.status.error_message().find(bad_file + ":7:"), std::string::npos)
      << bad.status.error_message();
  EXPECT_NE(bad.status.error_message().find("unknown action 'retry_forever'"), std::string::npos)
      << bad.status.error_message();
  // A behavior no system of the robot hosts.
  bad = startMissionText("robot: drone1\nsteps:\n  - behavior: FLY_TO_THE_MOON\n");
  ASSERT_EQ(bad.status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << describe(bad.status);
  EXPECT_NE(bad.status.error_message().find("<mission text>:3: behavior FLY_TO_THE_MOON is not "
                                            "hosted"),
            std::string::npos)
      << bad.status.error_message();
  // Every problem at once, before anything flies: a parameter out of its
  // range (the issue's TAKE_OFF at 500 m, which used to fly the WAIT before
  // it) and a behavior nobody hosts, each with its line.
  bad = startMissionText(
      "robot: drone1\nsteps:\n  - behavior: WAIT\n    parameters: {duration_s: 1}\n"
      "  - behavior: TAKE_OFF\n    parameters: {altitude_m: 500}\n"
      "  - behavior: FLY_TO_THE_MOON\n");
  ASSERT_EQ(bad.status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << describe(bad.status);
  for (const char* part : {"2 problems in the mission",
                           "<mission text>:6: TAKE_OFF parameter 'altitude_m' = 500 is out of "
                           "range [0.2, 30]",
                           "<mission text>:7: behavior FLY_TO_THE_MOON is not hosted"}) {
    EXPECT_NE(bad.status.error_message().find(part), std::string::npos)
        << part << " in " << bad.status.error_message();
  }
  auto listed = unary(*stub_, &v1::Coordinator::Stub::ListMissions, v1::ListMissionsRequest());
  ASSERT_TRUE(listed.status.ok());
  EXPECT_EQ(listed.response.missions_size(), 0) << "no mission was started";
  EXPECT_FALSE(events.waitFor([](const v1::BehaviorEvent&) { return true; }, milliseconds(200)))
      << "nothing was activated";

  // REFUSED: WAIT beyond its range -> continue. A literal out of range is
  // refused at StartMission (above); a belief's value is known only when
  // its step starts, and the system refuses it then.
  ASSERT_TRUE(writeBelief("drone1/too_long_s", "100000").status.ok());
  ASSERT_TRUE(writeBelief("drone1/negative_s", "-1").status.ok());
  // TIME_OUT: the dead reckoning with a 0.3 s limit, retried once, then a
  // fallback. WRONG_PROGRESS: the dead reckoning's drift bound (5 mm/s)
  // passes a 5 cm limit after 10 s -> continue. A step whose condition does
  // not hold is skipped.
  const std::string branches =
      "name: branches\n"
      "robot: drone1\n"
      "steps:\n"
      "  - name: too_long\n"
      "    behavior: WAIT\n"
      "    parameters: {duration_s: \"${belief.drone1/too_long_s}\"}\n"
      "    on:\n"
      "      REFUSED: continue\n"
      "  - name: reckon\n"
      "    behavior: ESTIMATE_POSITION_WITH_LINEAR_SPEED\n"
      "    parameters: {initial_x_m: 0, initial_y_m: 0, initial_z_m: 0, max_duration_s: 0.3}\n"
      "    on:\n"
      "      TIME_OUT:\n"
      "        retry: 1\n"
      "        then: {fallback: [{name: instead, behavior: WAIT, parameters: {duration_s: 0.2}}]}\n"
      "  - name: drift\n"
      "    behavior: ESTIMATE_POSITION_WITH_LINEAR_SPEED\n"
      "    parameters: {initial_x_m: 0, initial_y_m: 0, initial_z_m: 0, max_drift_m: 0.05}\n"
      "    on:\n"
      "      WRONG_PROGRESS: continue\n"
      "  - name: after\n"
      "    behavior: WAIT\n"
      "    parameters: {duration_s: 0.1}\n"
      "    remember: {drone1/branches_done: true}\n"
      "  - name: only_if_told\n"
      "    if: {belief: drone1/never_written, exists: true}\n"
      "    behavior: WAIT\n"
      "    parameters: {duration_s: 0.1}\n";
  const v1::MissionStatus done = runMission(branches);
  ASSERT_EQ(done.state(), v1::MISSION_STATE_SUCCEEDED) << json(done);
  ASSERT_EQ(done.steps_size(), 7) << json(done);
  struct Expected {
    std::vector<int> path;
    std::string name;
    int attempt;
    v1::MissionStepState state;
    v1::TerminationCause cause;
  };
  const std::vector<Expected> expected = {
      {{0}, "too_long", 1, v1::MISSION_STEP_STATE_REFUSED, v1::TERMINATION_CAUSE_UNSPECIFIED},
      {{1}, "reckon", 1, v1::MISSION_STEP_STATE_FINISHED, v1::TERMINATION_CAUSE_TIME_OUT},
      {{1}, "reckon", 2, v1::MISSION_STEP_STATE_FINISHED, v1::TERMINATION_CAUSE_TIME_OUT},
      {{1, 0}, "instead", 1, v1::MISSION_STEP_STATE_FINISHED, v1::TERMINATION_CAUSE_GOAL_ACHIEVED},
      {{2}, "drift", 1, v1::MISSION_STEP_STATE_FINISHED, v1::TERMINATION_CAUSE_WRONG_PROGRESS},
      {{3}, "after", 1, v1::MISSION_STEP_STATE_FINISHED, v1::TERMINATION_CAUSE_GOAL_ACHIEVED},
      {{4}, "only_if_told", 0, v1::MISSION_STEP_STATE_SKIPPED, v1::TERMINATION_CAUSE_UNSPECIFIED}};
  for (size_t i = 0; i < expected.size(); ++i) {
    const auto& step = done.steps(static_cast<int>(i));
    SCOPED_TRACE(json(step));
    EXPECT_EQ(std::vector<int>(step.path().begin(), step.path().end()), expected[i].path);
    EXPECT_EQ(step.name(), expected[i].name);
    EXPECT_EQ(step.attempt(), expected[i].attempt);
    EXPECT_EQ(step.state(), expected[i].state);
    EXPECT_EQ(step.cause(), expected[i].cause);
  }
  EXPECT_NE(done.steps(0).message().find("duration_s"), std::string::npos)
      << "the refusal names the parameter";
  // The two attempts were two activations, each ended by its time limit.
  EXPECT_NE(done.steps(1).activation_id(), done.steps(2).activation_id());
  for (int i : {1, 2}) {
    auto timed_out = events.finished(done.steps(i).activation_id(), seconds(2));
    ASSERT_TRUE(timed_out);
    EXPECT_EQ(timed_out->finished().cause(), v1::TERMINATION_CAUSE_TIME_OUT);
  }
  v1::ReadBeliefRequest read;
  read.set_key("drone1/branches_done");
  auto remembered = unary(*stub_, &v1::Coordinator::Stub::ReadBelief, read);
  ASSERT_TRUE(remembered.status.ok()) << describe(remembered.status);
  EXPECT_TRUE(remembered.response.belief().value().bool_value());
  EXPECT_EQ(remembered.response.belief().writer(), "mission:" + done.mission_id());

  // A refusal without a branch aborts the mission (FAILED) and its safety
  // step runs.
  const v1::MissionStatus failed = runMission(
      "name: refused\n"
      "robot: drone1\n"
      "safety:\n"
      "  - behavior: WAIT\n"
      "    parameters: {duration_s: 0.15}\n"
      "steps:\n"
      "  - name: too_long\n"
      "    behavior: WAIT\n"
      "    parameters: {duration_s: \"${belief.drone1/negative_s}\"}\n"
      "  - name: never\n"
      "    behavior: WAIT\n"
      "    parameters: {duration_s: 0.1}\n");
  ASSERT_EQ(failed.state(), v1::MISSION_STATE_FAILED) << json(failed);
  EXPECT_NE(failed.message().find("step 'too_long' (WAIT) was refused"), std::string::npos)
      << failed.message();
  ASSERT_EQ(failed.steps_size(), 1) << "nothing after the refusal: " << json(failed);
  // The safety step is the only WAIT of 0.15 s.
  auto safety = events.waitFor([&](const v1::BehaviorEvent& e) {
    const auto& parameters = e.finished().parameters().fields();
    return e.behavior() == "WAIT" && e.has_finished() && parameters.contains("duration_s") &&
           parameters.at("duration_s").number_value() == 0.15;
  });
  ASSERT_TRUE(safety) << "the safety step did not run";
  EXPECT_EQ(safety->finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED);
}

// docs/missions.md, the grammar's one page: each ```yaml block is a whole
// mission, and the comment above it says what it does (SUCCEEDED, FAILED,
// or refused at StartMission, with the lines of the ```text block that
// follows in its message). Every example is run here, as the page says.
TEST_F(CoordinatorPlansMissionsTest, DocumentedMissionsRunAsDocumented) {
  std::ifstream in(BEHAVIORLIB_MISSIONS_DOC_PATH);
  ASSERT_TRUE(in) << "cannot read " << BEHAVIORLIB_MISSIONS_DOC_PATH;
  struct Example {
    int line = 0;
    std::string expect;
    std::string yaml;
    std::vector<std::string> refusal;
  };
  std::vector<Example> examples;
  // A text block that starts with "$ behaviorctl --coordinator ADDR ...":
  // the command, run from the repository's root, prints the block's lines.
  struct Command {
    int line = 0;
    std::string arguments;
    std::vector<std::string> output;
  };
  std::vector<Command> commands;
  const std::string prompt = "$ behaviorctl --coordinator 127.0.0.1:50060 ";
  std::string expect;
  std::string line;
  enum class In { kProse, kYaml, kText, kCommand } in_block = In::kProse;
  bool block_start = false;
  for (int number = 1; std::getline(in, line); ++number) {
    if (in_block != In::kProse) {
      const bool first = block_start;
      block_start = false;
      if (line == "```") {
        in_block = In::kProse;
      } else if (in_block == In::kYaml) {
        examples.back().yaml += line + "\n";
      } else if (in_block == In::kText && first && line.rfind(prompt, 0) == 0) {
        in_block = In::kCommand;
        commands.push_back({number, line.substr(prompt.size()), {}});
      } else if (in_block == In::kCommand) {
        commands.back().output.push_back(line);
      } else if (!examples.empty() && examples.back().expect == "refused" &&
                 line.find_first_not_of(' ') != std::string::npos) {
        examples.back().refusal.push_back(line.substr(line.find_first_not_of(' ')));
      }
      continue;
    }
    if (line.rfind("<!-- expect: ", 0) == 0) {
      expect = line.substr(13, line.find(" -->") - 13);
    } else if (line == "```yaml") {
      ASSERT_FALSE(expect.empty()) << "docs/missions.md:" << number << ": no expect comment above";
      examples.push_back({number, expect, "", {}});
      expect.clear();
      in_block = In::kYaml;
    } else if (line == "```text") {
      in_block = In::kText;
      block_start = true;
    }
  }
  ASSERT_GE(examples.size(), 6u) << "the page lost its examples";
  ASSERT_GE(commands.size(), 1u) << "the page lost its mission check";
  const std::string demo = kDemoMission;
  const std::string root = demo.substr(0, demo.rfind("/deploy/missions/"));
  for (const Command& command : commands) {
    SCOPED_TRACE("docs/missions.md:" + std::to_string(command.line));
    std::string output;
    run("cd '" + root + "' && " + std::string(BEHAVIORLIB_BEHAVIORCTL_PATH) + " --coordinator " +
            coordinator_->address() + " " + command.arguments,
        &output);
    std::vector<std::string> printed = absl::StrSplit(output, '\n');
    while (!printed.empty() && printed.back().empty()) printed.pop_back();
    EXPECT_EQ(printed, command.output) << output;
  }
  for (const Example& example : examples) {
    SCOPED_TRACE("docs/missions.md:" + std::to_string(example.line) + " (" + example.expect + ")");
    // A fleet mission needs two vehicles: fleet_missions_test runs those.
    if (example.expect.find("(fleet)") != std::string::npos) continue;
    if (example.expect == "refused") {
      auto refused = startMissionText(example.yaml);
      EXPECT_EQ(refused.status.error_code(), grpc::StatusCode::INVALID_ARGUMENT)
          << describe(refused.status);
      EXPECT_FALSE(example.refusal.empty()) << "a refused example shows its refusal";
      for (const std::string& part : example.refusal) {
        EXPECT_NE(refused.status.error_message().find(part), std::string::npos)
            << part << " in " << refused.status.error_message();
      }
      continue;
    }
    v1::MissionState state = v1::MISSION_STATE_UNSPECIFIED;
    ASSERT_TRUE(v1::MissionState_Parse("MISSION_STATE_" + example.expect, &state))
        << example.expect;
    const v1::MissionStatus done = runMission(example.yaml, seconds(60));
    EXPECT_EQ(done.state(), state) << json(done);
  }
}

// ${belief.key} in a step's parameters takes the belief's value (a path
// written by an operator, flown by FOLLOW_PATH); WatchBeliefs streams the
// current beliefs, then new ones (the mission's own `remember` included).
TEST_F(CoordinatorPlansMissionsTest, FollowPathFliesThePathABeliefHoldsAndWatchBeliefsStreamsIt) {
  FleetRecorder& events = recorder();
  ASSERT_TRUE(writeBelief("drone1/home", "\"pad 1\"").status.ok());
  ASSERT_TRUE(writeBelief("other/home", "\"pad 2\"").status.ok());

  grpc::ClientContext watch_context;
  watch_context.set_deadline(std::chrono::system_clock::now() + seconds(60));
  v1::WatchBeliefsRequest watch_request;
  watch_request.set_prefix("drone1/");
  auto beliefs = stub_->WatchBeliefs(&watch_context, watch_request);
  v1::WatchBeliefsResponse change;
  ASSERT_TRUE(beliefs->Read(&change)) << "the current belief first";
  EXPECT_EQ(change.belief().key(), "drone1/home");
  EXPECT_EQ(change.belief().value().string_value(), "pad 1");
  EXPECT_EQ(change.belief().version(), 1u);

  const std::vector<std::array<double, 3>> points = {{1.5, 0.0, 1.0}, {1.5, 1.5, 1.0}};
  const std::string path = pathJson(points);
  auto written = writeBelief("drone1/path", path);
  ASSERT_TRUE(written.status.ok()) << describe(written.status);
  ASSERT_TRUE(beliefs->Read(&change)) << "then the new one";
  EXPECT_EQ(change.belief().key(), "drone1/path");
  EXPECT_EQ(change.belief().version(), 3u) << "other/home was version 2, outside the prefix";
  EXPECT_EQ(change.belief().value().list_value().values_size(), 2);

  const v1::MissionStatus done = runMission(
      "name: follow_a_belief\n"
      "robot: drone1\n"
      "recurrent:\n"
      "  - behavior: SELF_LOCALIZE_WITH_GROUND_TRUTH\n"
      "safety:\n"
      "  - behavior: LAND\n"
      "steps:\n"
      "  - name: settle\n"
      "    behavior: WAIT\n"
      "    parameters: {duration_s: 1.0}\n"
      "  - name: take_off\n"
      "    behavior: TAKE_OFF\n"
      "    parameters: {altitude_m: 1.0}\n"
      "    on: {REFUSED: {retry: 2}}\n"
      "  - name: follow\n"
      "    behavior: FOLLOW_PATH\n"
      "    parameters: {path_m: \"${belief.drone1/path}\", speed_m_s: 1.0}\n"
      "    remember: {drone1/followed: \"${belief.drone1/home}\"}\n"
      "  - name: land\n"
      "    behavior: LAND\n");
  ASSERT_EQ(done.state(), v1::MISSION_STATE_SUCCEEDED) << json(done);
  ASSERT_EQ(done.steps_size(), 4) << json(done);
  const auto& follow = done.steps(2);
  EXPECT_EQ(follow.behavior(), "FOLLOW_PATH");
  EXPECT_EQ(follow.cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED) << json(follow);
  // The record and the behavior's own activated event carry the belief's path.
  ASSERT_EQ(pointsOf(written.response.belief().value()), points);
  EXPECT_EQ(pointsOf(follow.parameters().fields().at("path_m")), points);
  auto activated = events.activated(follow.activation_id(), seconds(2));
  ASSERT_TRUE(activated);
  EXPECT_EQ(pointsOf(activated->activated().parameters().fields().at("path_m")), points);

  // The mission's `remember` reaches the watcher.
  ASSERT_TRUE(beliefs->Read(&change));
  EXPECT_EQ(change.belief().key(), "drone1/followed");
  EXPECT_EQ(change.belief().value().string_value(), "pad 1");
  EXPECT_EQ(change.belief().writer(), "mission:" + done.mission_id());
  watch_context.TryCancel();
  beliefs->Finish();
}

// PauseMission pauses the current behavior, ResumeMission resumes it;
// AbortMission interrupts it and runs the safety step (LAND).
TEST_F(CoordinatorPlansMissionsTest, PauseResumeAndAbortWhichRunsTheSafetyStepLand) {
  FleetRecorder& events = recorder();
  auto started = startMissionText(
      "name: hold\n"
      "robot: drone1\n"
      "recurrent:\n"
      "  - behavior: SELF_LOCALIZE_WITH_GROUND_TRUTH\n"
      "safety:\n"
      "  - behavior: LAND\n"
      "steps:\n"
      "  - name: settle\n"
      "    behavior: WAIT\n"
      "    parameters: {duration_s: 1.0}\n"
      "  - name: take_off\n"
      "    behavior: TAKE_OFF\n"
      "    parameters: {altitude_m: 1.0}\n"
      "    on: {REFUSED: {retry: 2}}\n"
      "  - name: hold\n"
      "    behavior: WAIT\n"
      "    parameters: {duration_s: 600}\n"
      "  - name: never\n"
      "    behavior: WAIT\n"
      "    parameters: {duration_s: 0.1}\n",
      "hold-1");
  ASSERT_TRUE(started.status.ok()) << describe(started.status);
  MissionWatcher watcher(coordinator_->address(), "hold-1");
  auto holding = watcher.waitFor(
      [](const v1::MissionStatus& s) {
        return s.steps_size() == 3 && !s.steps(2).activation_id().empty();
      },
      seconds(30));
  ASSERT_TRUE(holding) << "the mission did not reach its third step";
  const std::string hold_id = holding->steps(2).activation_id();
  ASSERT_TRUE(events.activated(hold_id));
  // One mission per robot at a time.
  auto second = startMissionText(
      "robot: drone1\nsteps:\n  - behavior: WAIT\n    parameters: {duration_s: 1}\n");
  EXPECT_EQ(second.status.error_code(), grpc::StatusCode::FAILED_PRECONDITION)
      << describe(second.status);
  EXPECT_NE(second.status.error_message().find("hold-1"), std::string::npos)
      << second.status.error_message();
  {
    MissionWatcher unknown(coordinator_->address(), "no-such-mission");
    const auto end = unknown.endStatus(seconds(5));
    ASSERT_TRUE(end) << "WatchMission of an unknown mission did not end";
    EXPECT_EQ(end->error_code(), grpc::StatusCode::NOT_FOUND) << describe(*end);
    EXPECT_TRUE(unknown.statuses().empty());
  }

  auto paused = control(&v1::Coordinator::Stub::PauseMission, "hold-1");
  ASSERT_TRUE(paused.status.ok()) << describe(paused.status);
  ASSERT_TRUE(watcher.waitFor(
      [](const v1::MissionStatus& s) { return s.state() == v1::MISSION_STATE_PAUSED; }, seconds(5)))
      << "no PAUSED status";
  ASSERT_TRUE(events.waitFor([&](const v1::BehaviorEvent& e) {
    return e.activation_id() == hold_id && e.has_paused();
  })) << "the current behavior was not paused";
  EXPECT_EQ(stateOf("WAIT").first, v1::BEHAVIOR_STATE_PAUSED);
  auto twice = control(&v1::Coordinator::Stub::PauseMission, "hold-1");
  EXPECT_EQ(twice.status.error_code(), grpc::StatusCode::FAILED_PRECONDITION)
      << describe(twice.status);

  auto resumed = control(&v1::Coordinator::Stub::ResumeMission, "hold-1");
  ASSERT_TRUE(resumed.status.ok()) << describe(resumed.status);
  ASSERT_TRUE(events.waitFor([&](const v1::BehaviorEvent& e) {
    return e.activation_id() == hold_id && e.has_resumed();
  })) << "the current behavior was not resumed";
  EXPECT_TRUE(
      waitUntil([&] { return stateOf("WAIT").first == v1::BEHAVIOR_STATE_ACTIVE; }, seconds(5)));

  auto aborted = control(&v1::Coordinator::Stub::AbortMission, "hold-1", "operator said stop");
  ASSERT_TRUE(aborted.status.ok()) << describe(aborted.status);
  const auto last = watcher.waitEnd(seconds(30));
  ASSERT_TRUE(last);
  EXPECT_EQ(last->state(), v1::MISSION_STATE_ABORTED) << json(*last);
  EXPECT_NE(last->message().find("operator said stop"), std::string::npos) << last->message();
  EXPECT_FALSE(last->in_safety_steps());
  ASSERT_EQ(last->steps_size(), 3) << json(*last);
  EXPECT_EQ(last->steps(2).cause(), v1::TERMINATION_CAUSE_INTERRUPTED);
  auto interrupted = events.finished(hold_id, seconds(2));
  ASSERT_TRUE(interrupted);
  EXPECT_EQ(interrupted->finished().cause(), v1::TERMINATION_CAUSE_INTERRUPTED);
  // The safety step: LAND, to the ground.
  auto land = events.waitFor(
      [](const v1::BehaviorEvent& e) { return e.behavior() == "LAND" && e.has_finished(); },
      seconds(2));
  ASSERT_TRUE(land) << "the safety step LAND did not run";
  EXPECT_EQ(land->finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED) << causeOf(*land);
  EXPECT_TRUE(watcher.waitFor(
      [](const v1::MissionStatus& s) {
        return s.in_safety_steps() && s.state() == v1::MISSION_STATE_ABORTED;
      },
      seconds(2)))
      << "the stream showed the safety steps running";
  EXPECT_TRUE(waitUntil([&] { return activeBehaviors().empty(); }, seconds(5)))
      << "the recurrent behavior ends with the mission";
  auto again = control(&v1::Coordinator::Stub::AbortMission, "hold-1");
  EXPECT_EQ(again.status.error_code(), grpc::StatusCode::FAILED_PRECONDITION)
      << describe(again.status);
  auto unknown = control(&v1::Coordinator::Stub::PauseMission, "no-such-mission");
  EXPECT_EQ(unknown.status.error_code(), grpc::StatusCode::NOT_FOUND) << describe(unknown.status);
}

// kill -9 of the coordinator while the demo flies its square; a new
// coordinator with the same --state-dir (and port, where the systems
// register again) resumes the mission, which succeeds, and the systems' own
// event histories show every behavior activated exactly once.
TEST_F(CoordinatorPlansMissionsTest,
       AKilledCoordinatorResumesTheMissionWithoutDoublingActivations) {
  auto started = startMissionFile(demo_mission_, "demo-crash");
  ASSERT_TRUE(started.status.ok()) << describe(started.status);
  std::string follow_id;
  {
    MissionWatcher watcher(coordinator_->address(), "demo-crash");
    auto flying = watcher.waitFor(
        [](const v1::MissionStatus& s) {
          return s.steps_size() == 3 && s.steps(2).behavior() == "FOLLOW_PATH" &&
                 !s.steps(2).activation_id().empty();
        },
        seconds(30));
    ASSERT_TRUE(flying) << "the demo did not reach FOLLOW_PATH";
    follow_id = flying->steps(2).activation_id();
  }
  // Mid-path: 3 s of simulated time into the 16 s square (past the time its
  // controller is given to start following).
  SystemClient pid_system(pid_->address());
  ASSERT_TRUE(waitUntil(
      [&] {
        auto check = pid_system.checkActivation("FOLLOW_PATH");
        return check.status.ok() && check.response.active_duration().seconds() >= 3;
      },
      seconds(10)))
      << json(pid_system.checkActivation("FOLLOW_PATH").response);
  const int port = coordinator_->grpcPort();
  coordinator_->kill();
  // FOLLOW_PATH goes on without the coordinator.
  auto check = pid_system.checkActivation("FOLLOW_PATH");
  ASSERT_TRUE(check.status.ok()) << describe(check.status);
  EXPECT_TRUE(check.response.active());
  EXPECT_EQ(check.response.activation_id(), follow_id);

  ASSERT_NO_FATAL_FAILURE(startCoordinator({"--listen", "127.0.0.1:" + std::to_string(port)}));
  ASSERT_EQ(coordinator_->grpcPort(), port);
  ASSERT_NO_FATAL_FAILURE(waitForSystems());
  MissionWatcher watcher(coordinator_->address(), "demo-crash");
  const auto last = watcher.waitEnd(seconds(45));
  ASSERT_TRUE(last);
  ASSERT_EQ(last->state(), v1::MISSION_STATE_SUCCEEDED) << json(*last);
  ASSERT_EQ(last->steps_size(), 5) << "each step once: " << json(*last);
  for (int i = 0; i < last->steps_size(); ++i) {
    SCOPED_TRACE(json(last->steps(i)));
    EXPECT_EQ(last->steps(i).path(0), i);
    EXPECT_EQ(last->steps(i).attempt(), 1);
    EXPECT_EQ(last->steps(i).cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED);
  }
  EXPECT_EQ(last->steps(2).activation_id(), follow_id) << "the same activation, not a new one";

  // Every behavior the mission used was activated once, and finished once,
  // as each behavior system itself recorded it.
  std::map<std::string, int> activated, finished;
  for (const auto* system : {basic_.get(), pid_.get(), fusion_.get()}) {
    for (const auto& e : systemHistory(system->address())) {
      activated[e.behavior()] += e.has_activated();
      finished[e.behavior()] += e.has_finished();
    }
  }
  const std::map<std::string, int> once = {
      {"WAIT", 1}, {"TAKE_OFF", 1},    {"FOLLOW_PATH", 1}, {"ROTATE_WITH_PID_CONTROL", 1},
      {"LAND", 1}, {kDemoLocalize, 1}, {kPid, 1}};
  EXPECT_EQ(activated, once);
  EXPECT_TRUE(waitUntil([&] { return activeBehaviors().empty(); }, seconds(5)));
  finished.clear();
  for (const auto* system : {basic_.get(), pid_.get(), fusion_.get()}) {
    for (const auto& e : systemHistory(system->address()))
      finished[e.behavior()] += e.has_finished();
  }
  EXPECT_EQ(finished, once);
}

// Ended missions are kept by count (--max-ended-missions): starting a mission
// forgets the oldest ended ones beyond it.
TEST_F(CoordinatorPlansMissionsTest, EndedMissionsBeyondTheRetentionCountAreForgotten) {
  const int port = coordinator_->grpcPort();
  ASSERT_EQ(coordinator_->terminate(), 0);
  ASSERT_NO_FATAL_FAILURE(startCoordinator(
      {"--listen", "127.0.0.1:" + std::to_string(port), "--max-ended-missions", "1"}));
  ASSERT_NO_FATAL_FAILURE(waitForSystems());
  const std::string quick =
      "name: quick\nrobot: drone1\nsteps:\n  - behavior: WAIT\n    parameters: {duration_s: 0.1}\n";
  for (const std::string id : {"quick-1", "quick-2", "quick-3"}) {
    auto started = startMissionText(quick, id);
    ASSERT_TRUE(started.status.ok()) << describe(started.status);
    MissionWatcher watcher(coordinator_->address(), id);
    const auto last = watcher.waitEnd(seconds(30));
    ASSERT_TRUE(last);
    ASSERT_EQ(last->state(), v1::MISSION_STATE_SUCCEEDED) << json(*last);
  }
  // quick-3's start found two ended missions: quick-1, the older, went.
  v1::GetMissionRequest get;
  get.set_mission_id("quick-1");
  EXPECT_EQ(unary(*stub_, &v1::Coordinator::Stub::GetMission, get).status.error_code(),
            grpc::StatusCode::NOT_FOUND);
  for (const std::string id : {"quick-2", "quick-3"}) {
    get.set_mission_id(id);
    EXPECT_TRUE(unary(*stub_, &v1::Coordinator::Stub::GetMission, get).status.ok()) << id;
  }
  // An ended mission keeps only its status: quick-2's runner (its thread and
  // parsed mission) was released when quick-3 started, and quick-3's, ended
  // since, waits for the next start.
  const std::string metrics = support::httpGet(coordinator_->metricsPort(), "/metrics");
  EXPECT_EQ(metricValue(metrics, "behaviorlib_coordinator_missions_retained"), 2.0) << metrics;
  EXPECT_EQ(metricValue(metrics, "behaviorlib_coordinator_mission_runners"), 1.0) << metrics;
  for (const std::string id : {"quick-2", "quick-3"}) {
    auto again = control(&v1::Coordinator::Stub::AbortMission, id);
    EXPECT_EQ(again.status.error_code(), grpc::StatusCode::FAILED_PRECONDITION)
        << describe(again.status);
    EXPECT_NE(again.status.error_message().find("already ended (MISSION_STATE_SUCCEEDED)"),
              std::string::npos)
        << describe(again.status);
  }
}

// Ended missions are kept by age too (--max-ended-mission-age-s): those that
// ended longer ago than the age, by the coordinator's clock, are forgotten
// after a restart (and when a mission starts); the younger ones are kept.
// The mission manager itself, with a clock of the test: the missions ended
// in 2023, so a manager that read the real clock would forget them all.
TEST(MissionRetentionTest, EndedMissionsOlderThanTheRetentionAgeAreForgotten) {
  namespace bc = behaviorlib::coordinator;
  prometheus::Registry prometheus;
  bc::CoordinatorMetrics metrics(prometheus);
  bc::FleetEventLog log;
  bc::Registry registry(log, metrics, {});
  bc::BeliefStore beliefs;
  bc::FleetControl fleet(registry, log, nullptr);
  constexpr int64_t kNowS = 1700000000;  // 2023-11-14T22:13:20Z
  bc::MissionManagerOptions options;
  options.max_ended_age = std::chrono::hours(24);
  options.now = [] { return google::protobuf::util::TimeUtil::SecondsToTimestamp(kNowS); };
  bc::MissionManager missions(fleet, registry, beliefs, nullptr, options);
  const std::map<std::string, int64_t> ended_ago_s = {{"two-days-ago", 2 * 86400},
                                                      {"a-day-and-a-second-ago", 86400 + 1},
                                                      {"a-day-ago", 86400},
                                                      {"an-hour-ago", 3600}};
  for (const auto& [id, ago_s] : ended_ago_s) {
    v1::MissionStatus status;  // as the journal gives it back after a restart
    status.set_mission_id(id);
    status.set_robot_id(kRobot);
    status.set_state(v1::MISSION_STATE_SUCCEEDED);
    status.mutable_start_time()->set_seconds(kNowS - ago_s - 60);
    status.mutable_end_time()->set_seconds(kNowS - ago_s);
    missions.restore(status);
  }
  missions.resumeRestored();
  std::set<std::string> kept;
  for (const auto& status : missions.list()) kept.insert(status.mission_id());
  EXPECT_EQ(kept, (std::set<std::string>{"a-day-ago", "an-hour-ago"}))
      << "ended exactly max_ended_age ago is still kept";
  for (const std::string id : {"two-days-ago", "a-day-and-a-second-ago"}) {
    EXPECT_EQ(missions.get(id).status().code(), absl::StatusCode::kNotFound) << id;
  }
}

// A robot's behavior names are unique across its systems: a second system
// hosting one of them is refused with ALREADY_HOSTED, naming both systems.
// The registry itself: no shipped system shares a behavior name with
// another, so no real process could answer for the second one.
TEST(RegistryTest, ASecondSystemHostingABehaviorOfTheRobotIsAlreadyHosted) {
  namespace bc = behaviorlib::coordinator;
  prometheus::Registry prometheus;
  bc::CoordinatorMetrics metrics(prometheus);
  bc::FleetEventLog log;
  bc::RegistryOptions options;
  // Nothing listens at the systems' address: the first one's link keeps
  // reconnecting, and stays registered, for the grace period.
  options.link.grace = std::chrono::hours(1);
  bc::Registry registry(log, metrics, options);
  auto registration = [](const std::string& system, std::vector<std::string> behaviors) {
    v1::RegisterSystemRequest request;
    request.set_robot_id(kRobot);
    request.set_system(system);
    request.set_address("127.0.0.1:1");
    request.set_incarnation(system + "-1");
    v1::ListBehaviorsResponse description;
    description.set_robot_id(kRobot);
    description.set_system(system);
    for (const auto& name : behaviors) description.add_behaviors()->set_name(name);
    return std::make_pair(request, description);
  };
  const auto [first, first_description] = registration("motion", {"FOLLOW_PATH", "HOVER"});
  ASSERT_TRUE(registry.registerSystem(first, first_description).ok());
  const auto [second, second_description] = registration("other_motion", {"LAND", "HOVER"});
  const grpc::Status refused = registry.registerSystem(second, second_description);
  EXPECT_EQ(refused.error_code(), grpc::StatusCode::FAILED_PRECONDITION);
  const auto info = behaviorlib::errors::errorInfo(refused);
  ASSERT_TRUE(info.has_value()) << refused.error_message();
  EXPECT_EQ(info->reason(), "ALREADY_HOSTED");
  EXPECT_EQ(info->metadata().at("behavior"), "HOVER");
  EXPECT_EQ(info->metadata().at("system"), "other_motion");
  EXPECT_EQ(info->metadata().at("hosted_by"), "motion");
  const auto [third, third_description] = registration("other_motion", {"LAND"});
  EXPECT_TRUE(registry.registerSystem(third, third_description).ok());
}

// behaviorctl against the coordinator: health, a dry run, and `mission run`
// of the demo (exit 0 when it SUCCEEDED).
// CheckMission: every problem StartMission would refuse the mission for, as
// data with its file, line and field; a robot without systems or without a
// name is a problem too; a good mission gets each step's plan, each planned
// against what the steps before it leave active. Nothing is activated.
TEST_F(CoordinatorPlansMissionsTest, CheckMissionListsEveryProblemAndPlansEveryStep) {
  FleetRecorder& events = recorder();
  auto check = [&](const std::string& text, const std::string& robot = "") {
    v1::CheckMissionRequest request;
    request.set_text(text);
    request.set_source_name("check.yaml");
    request.set_robot_id(robot);
    return unary(*stub_, &v1::Coordinator::Stub::CheckMission, request);
  };
  // Three problems on three lines, found at once.
  auto checked = check(
      "name: three\nrobot: drone1\nsteps:\n"
      "  - behavior: WAIT\n    parameters: {duration_s: 1, duration: 1}\n"
      "  - behavior: TAKE_OFF\n    parameters: {altitude_m: 500}\n"
      "  - behavior: FLY_TO_THE_MOON\n");
  ASSERT_TRUE(checked.status.ok()) << describe(checked.status);
  const v1::CheckMissionResponse& three = checked.response;
  EXPECT_EQ(three.name(), "three");
  EXPECT_EQ(three.robot_id(), kRobot);
  ASSERT_EQ(three.problems_size(), 3) << json(three);
  const std::vector<std::tuple<uint32_t, std::string, std::string>> expected = {
      {5, "steps[0].parameters.duration", "check.yaml:5: WAIT has no parameter 'duration'"},
      {7, "steps[1].parameters.altitude_m",
       "check.yaml:7: TAKE_OFF parameter 'altitude_m' = 500 is out of range [0.2, 30]"},
      {8, "steps[2].behavior", "check.yaml:8: behavior FLY_TO_THE_MOON is not hosted"}};
  for (int i = 0; i < 3; ++i) {
    const auto& [line, field, description] = expected[i];
    EXPECT_EQ(three.problems(i).file(), "check.yaml");
    EXPECT_EQ(three.problems(i).line(), line) << json(three.problems(i));
    EXPECT_EQ(three.problems(i).field(), field) << json(three.problems(i));
    EXPECT_EQ(three.problems(i).description().rfind(description, 0), 0u) << json(three.problems(i));
  }
  // A file that does not parse: one problem, with its line.
  checked = check("robot: drone1\nsteps:\n  - behavior: WAIT\n    on: {TIME_OUT: forever}\n");
  ASSERT_TRUE(checked.status.ok()) << describe(checked.status);
  ASSERT_EQ(checked.response.problems_size(), 1) << json(checked.response);
  EXPECT_EQ(checked.response.problems(0).line(), 4u) << json(checked.response);
  EXPECT_TRUE(checked.response.plans().empty());
  // No robot, and a robot with no registered system.
  checked = check("steps: [{behavior: LAND}]\n");
  ASSERT_EQ(checked.response.problems_size(), 1) << json(checked.response);
  EXPECT_NE(checked.response.problems(0).description().find("no robot"), std::string::npos);
  checked = check("robot: drone1\nsteps: [{behavior: LAND}]\n", "drone9");
  ASSERT_EQ(checked.response.problems_size(), 1) << json(checked.response);
  EXPECT_EQ(checked.response.problems(0).field(), "robot");
  EXPECT_EQ(checked.response.problems(0).line(), 1u) << "the line of `robot:`";
  EXPECT_NE(checked.response.problems(0).description().find("'drone9' has no registered"),
            std::string::npos)
      << json(checked.response);
  // The request's own errors stay errors.
  auto no_source = unary(*stub_, &v1::Coordinator::Stub::CheckMission, v1::CheckMissionRequest());
  EXPECT_EQ(no_source.status.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  v1::CheckMissionRequest outside;
  outside.set_file_path("/etc/passwd");
  EXPECT_EQ(unary(*stub_, &v1::Coordinator::Stub::CheckMission, outside).status.error_code(),
            grpc::StatusCode::PERMISSION_DENIED);

  // The demo mission: no problem, and a plan for every step in file order.
  v1::CheckMissionRequest demo;
  demo.set_file_path(std::filesystem::path(demo_mission_).filename().string());
  checked = unary(*stub_, &v1::Coordinator::Stub::CheckMission, demo);
  ASSERT_TRUE(checked.status.ok()) << describe(checked.status);
  EXPECT_EQ(checked.response.problems_size(), 0) << json(checked.response);
  std::vector<std::string> nodes;
  std::map<std::string, std::vector<std::string>> plans;  // node -> "kind behavior"
  for (const auto& plan : checked.response.plans()) {
    nodes.push_back(plan.node());
    EXPECT_TRUE(plan.no_plan().empty()) << json(plan);
    ASSERT_FALSE(plan.plan().empty()) << json(plan);
    EXPECT_EQ(plan.plan(plan.plan_size() - 1).kind(), v1::ActivationPlanStep::KIND_ACTIVATE);
    EXPECT_EQ(plan.plan(plan.plan_size() - 1).behavior(), plan.behavior()) << "the target last";
    for (const auto& step : plan.plan()) {
      plans[plan.node()].push_back(v1::ActivationPlanStep::Kind_Name(step.kind()) + " " +
                                   step.behavior());
    }
  }
  EXPECT_EQ(nodes, (std::vector<std::string>{"recurrent/0", "steps/0", "steps/1", "steps/2",
                                             "steps/3", "steps/4", "safety/0"}));
  // FOLLOW_PATH's plan activates the motion controller it needs; the
  // recurrent localization, active from recurrent/0 on, is never planned
  // again.
  const auto has = [&](const std::string& node, const std::string& what) {
    const auto& steps = plans[node];
    return std::find(steps.begin(), steps.end(), what) != steps.end();
  };
  EXPECT_TRUE(has("steps/2", std::string("KIND_ACTIVATE ") + kPid)) << json(checked.response);
  for (const std::string& node : nodes) {
    if (node == "recurrent/0") continue;
    EXPECT_FALSE(has(node, std::string("KIND_ACTIVATE ") + kSelfLocalize)) << node;
  }
  EXPECT_TRUE(activeBehaviors().empty()) << "a check activates nothing";
  EXPECT_FALSE(events.waitFor([](const v1::BehaviorEvent&) { return true; }, milliseconds(200)))
      << "nothing was activated";
  auto listed = unary(*stub_, &v1::Coordinator::Stub::ListMissions, v1::ListMissionsRequest());
  ASSERT_TRUE(listed.status.ok());
  EXPECT_EQ(listed.response.missions_size(), 0) << "no mission was started";
}

TEST_F(CoordinatorPlansMissionsTest, BehaviorctlRunsTheDemoMissionAndChecksHealth) {
  const std::string ctl =
      std::string(BEHAVIORLIB_BEHAVIORCTL_PATH) + " --coordinator " + coordinator_->address();
  std::string output;
  ASSERT_EQ(run(ctl + " health", &output), 0) << output;
  EXPECT_NE(output.find("SERVING"), std::string::npos) << output;

  output.clear();
  ASSERT_EQ(run(ctl + " --robot drone1 activate FOLLOW_PATH "
                      "'{\"path_m\": [{\"x\": 1, \"y\": 0, \"z\": 1}]}' --dry-run",
                &output),
            0)
      << output;
  EXPECT_NE(output.find("KIND_ACTIVATE"), std::string::npos) << output;
  EXPECT_NE(output.find(kPid), std::string::npos) << output;
  EXPECT_TRUE(activeBehaviors().empty()) << "a dry run activates nothing";

  // mission check: 0 and each step's plan for a good mission, 1 and each
  // problem with its file and line for a bad one.
  output.clear();
  ASSERT_EQ(run(ctl + " mission check " + std::string(kDemoMission), &output), 0) << output;
  EXPECT_NE(output.find("mission 'demo_square' for robot 'drone1': no problem found"),
            std::string::npos)
      << output;
  EXPECT_NE(output.find("steps/2"), std::string::npos) << output;
  EXPECT_NE(output.find(std::string("activate ") + kPid), std::string::npos) << output;
  const std::string bad_file = state_dir_ + "/check_bad.yaml";
  std::ofstream(bad_file) << "robot: drone1\nsteps:\n  - behavior: TAKE_OFF\n"
                             "    parameters: {altitude_m: 500}\n  - behavior: NOPE\n";
  output.clear();
  ASSERT_EQ(run(ctl + " mission check " + bad_file, &output), 1) << output;
  EXPECT_NE(output.find(bad_file + ":4: TAKE_OFF parameter 'altitude_m' = 500"), std::string::npos)
      << output;
  EXPECT_NE(output.find(bad_file + ":5: behavior NOPE is not hosted"), std::string::npos) << output;
  EXPECT_NE(output.find("2 problems"), std::string::npos) << output;

  output.clear();
  const int code = run("timeout 60 " + ctl + " mission run " + kDemoMission, &output);
  ASSERT_EQ(code, 0) << output;
  EXPECT_NE(output.find("MISSION_STATE_SUCCEEDED"), std::string::npos) << output;
  EXPECT_NE(output.find("fly_square"), std::string::npos) << "progress lines: " << output;

  // Not serving: exit 1.
  output.clear();
  EXPECT_EQ(coordinator_->terminate(), 0);
  EXPECT_EQ(run(ctl + " health --timeout-s 1", &output), 1) << output;
}

// Two ActivateBehavior calls on one robot at the same moment whose plans
// conflict: SELF_LOCALIZE_WITH_GROUND_TRUTH and the dead reckoning both hold
// the exclusive pose_estimate. The robot's plans are serialized: one plan is
// applied, then the other, made afterwards, deactivates its behavior
// (INTERRUPTED) and activates its own. Never both active, no interleaved
// steps: in the stream, the first's activation, its end, the second's
// activation. Unserialized, both plans would see no estimator active and
// both would activate.
TEST_F(CoordinatorPlansMissionsTest, ConcurrentConflictingActivationsOnOneRobotAreSerialized) {
  FleetRecorder& events = recorder();
  const std::map<std::string, std::string> parameters = {
      {kSelfLocalize, "{}"},
      {kReckon, R"({"initial_x_m": 0, "initial_y_m": 0, "initial_z_m": 0, "max_duration_s": 0})"}};
  constexpr int kRounds = 4;
  for (int round = 0; round < kRounds; ++round) {
    SCOPED_TRACE("round " + std::to_string(round));
    const size_t from = events.events().size();
    const std::array<std::string, 2> behaviors = {round % 2 ? kReckon : kSelfLocalize,
                                                  round % 2 ? kSelfLocalize : kReckon};
    std::array<Reply<v1::ActivateFleetBehaviorResponse>, 2> replies;
    std::array<double, 2> took_s{};
    {
      std::mutex mutex;
      std::condition_variable cv;
      int ready = 0;
      bool go = false;
      std::vector<std::thread> callers;
      for (size_t i = 0; i < 2; ++i) {
        callers.emplace_back([&, i] {
          {
            std::unique_lock lock(mutex);
            ++ready;
            cv.notify_all();
            cv.wait(lock, [&] { return go; });
          }
          const auto sent = SteadyClock::now();
          replies[i] = activate(behaviors[i], parameters.at(behaviors[i]));
          took_s[i] = std::chrono::duration<double>(SteadyClock::now() - sent).count();
        });
      }
      {
        std::unique_lock lock(mutex);
        cv.wait(lock, [&] { return ready == 2; });
        go = true;
      }
      cv.notify_all();
      for (auto& caller : callers) caller.join();
    }

    int ok = 0;
    for (const auto& reply : replies) ok += reply.status.ok();
    ASSERT_GE(ok, 1) << describe(replies[0].status) << " / " << describe(replies[1].status);
    const auto active = activeBehaviors();
    EXPECT_EQ(active.contains(kSelfLocalize) + active.contains(kReckon), 1)
        << "exactly one holder of pose_estimate";
    if (ok == 2) {
      // Exactly one of the plans deactivated the other's behavior.
      std::vector<size_t> deactivating;
      for (size_t i = 0; i < 2; ++i) {
        for (const auto& step : replies[i].response.plan()) {
          if (step.kind() == v1::ActivationPlanStep::KIND_DEACTIVATE) deactivating.push_back(i);
        }
      }
      ASSERT_EQ(deactivating.size(), 1u) << json(replies[0].response) << "\n"
                                         << json(replies[1].response);
      const size_t second = deactivating[0];
      const size_t first = 1 - second;
      const auto& plan = replies[second].response.plan();
      ASSERT_GE(plan.size(), 1);
      EXPECT_EQ(plan[0].behavior(), behaviors[first]) << json(replies[second].response);
      EXPECT_EQ(plan[0].reason(), "holds pose_estimate, which " + behaviors[second] + " needs");
      const std::string first_id = replies[first].response.activation().activation_id();
      const std::string second_id = replies[second].response.activation().activation_id();
      EXPECT_EQ(stateOf(behaviors[second]), std::make_pair(v1::BEHAVIOR_STATE_ACTIVE, second_id));
      ASSERT_TRUE(events.finished(first_id));
      ASSERT_TRUE(events.activated(second_id));
      // The two plans' events, in the stream's order.
      std::vector<std::string> order;
      const auto all = events.events();
      for (size_t i = from; i < all.size(); ++i) {
        const auto& e = all[i];
        if (e.activation_id() != first_id && e.activation_id() != second_id) continue;
        order.push_back(e.behavior() + (e.has_activated() ? " activated" : "") +
                        (e.has_finished() ? " finished " + causeOf(e) : ""));
      }
      const std::vector<std::string> expected = {
          behaviors[first] + " activated",
          behaviors[first] + " finished TERMINATION_CAUSE_INTERRUPTED ",
          behaviors[second] + " activated"};
      ASSERT_EQ(order.size(), expected.size()) << ::testing::PrintToString(order);
      for (size_t i = 0; i < order.size(); ++i) {
        EXPECT_EQ(order[i].substr(0, expected[i].size()), expected[i])
            << ::testing::PrintToString(order);
      }
      std::printf("round %d: %s first (%.3f s), then %s deactivated it (%.3f s)\n", round,
                  behaviors[first].c_str(), took_s[first], behaviors[second].c_str(),
                  took_s[second]);
    } else {
      // One was refused: nothing of it was activated.
      const size_t refused = replies[0].status.ok() ? 1 : 0;
      std::printf("round %d: %s refused: %s\n", round, behaviors[refused].c_str(),
                  describe(replies[refused].status).c_str());
      EXPECT_TRUE(active.contains(behaviors[1 - refused]));
      const auto all = events.events();
      for (size_t i = from; i < all.size(); ++i) {
        EXPECT_FALSE(all[i].behavior() == behaviors[refused] && all[i].has_activated())
            << json(all[i]);
      }
    }
    // Back to no estimator for the next round.
    for (const std::string& behavior : {std::string(kSelfLocalize), std::string(kReckon)}) {
      if (!active.contains(behavior)) continue;
      const std::string id = stateOf(behavior).second;
      auto stopped = client_->deactivate(kRobot, behavior);
      ASSERT_TRUE(stopped.status.ok()) << describe(stopped.status);
      ASSERT_TRUE(events.finished(id));
    }
    ASSERT_TRUE(waitUntil([&] { return activeBehaviors().empty(); }, seconds(5)));
  }
}

// A mission branches on SITUATION_CHANGE: hovering with the flight action,
// the battery drops below the behavior's minimum (the simulator's fault
// injection); the hover ends SITUATION_CHANGE and the mission takes the
// branch its file says (fallback: LAND, remembering it), then goes on.
TEST_F(CoordinatorPlansMissionsTest, AMissionBranchesOnSituationChangeWhenTheBatteryDrops) {
  FleetRecorder& events = recorder();
  auto started = startMissionText(
      "name: low_battery\n"
      "robot: drone1\n"
      "recurrent:\n"
      "  - behavior: SELF_LOCALIZE_WITH_GROUND_TRUTH\n"
      "safety:\n"
      "  - behavior: LAND\n"
      "steps:\n"
      "  - name: settle\n"
      "    behavior: WAIT\n"
      "    parameters: {duration_s: 1.0}\n"
      "  - name: take_off\n"
      "    behavior: TAKE_OFF\n"
      "    parameters: {altitude_m: 1.0}\n"
      "    on: {REFUSED: {retry: 2}}\n"
      "  - name: hover\n"
      "    behavior: HOVER_WITH_FLIGHT_ACTION_CONTROL\n"
      "    on:\n"
      "      SITUATION_CHANGE:\n"
      "        fallback:\n"
      "          - name: land_on_low_battery\n"
      "            behavior: LAND\n"
      "            remember: {drone1/branches/situation_change: true}\n"
      "      otherwise: abort\n"
      "  - name: after\n"
      "    remember: {drone1/branches/after_hover: true}\n",
      "battery-1");
  ASSERT_TRUE(started.status.ok()) << describe(started.status);
  MissionWatcher watcher(coordinator_->address(), "battery-1");
  auto hovering = watcher.waitFor(
      [](const v1::MissionStatus& s) {
        return s.steps_size() == 3 && !s.steps(2).activation_id().empty();
      },
      seconds(30));
  ASSERT_TRUE(hovering) << "the mission did not reach its hover";
  const std::string hover_id = hovering->steps(2).activation_id();
  ASSERT_TRUE(events.activated(hover_id));
  ASSERT_FALSE(events.finished(hover_id, milliseconds(300))) << "hovering";

  // The battery loses 85 % of its full charge at once: below the hover's
  // min_battery_ratio (0.2).
  auto simulator = v1::Simulator::NewStub(
      grpc::CreateChannel(simulator_->address(), grpc::InsecureChannelCredentials()));
  v1::InjectFailureRequest drop;
  drop.set_robot_id(kRobot);
  drop.set_component(v1::FAILURE_COMPONENT_BATTERY);
  drop.set_type(v1::FAILURE_TYPE_DEGRADED);
  drop.set_intensity(0.85);
  auto injected = unary(*simulator, &v1::Simulator::Stub::InjectFailure, drop);
  ASSERT_TRUE(injected.status.ok()) << describe(injected.status);

  auto hover_end = events.finished(hover_id);
  ASSERT_TRUE(hover_end) << "the hover did not end";
  EXPECT_EQ(hover_end->finished().cause(), v1::TERMINATION_CAUSE_SITUATION_CHANGE)
      << causeOf(*hover_end);
  const auto last = watcher.waitEnd(seconds(30));
  ASSERT_TRUE(last);
  ASSERT_EQ(last->state(), v1::MISSION_STATE_SUCCEEDED) << json(*last);
  ASSERT_EQ(last->steps_size(), 4) << json(*last);
  const auto& hover = last->steps(2);
  EXPECT_EQ(hover.name(), "hover");
  EXPECT_EQ(hover.cause(), v1::TERMINATION_CAUSE_SITUATION_CHANGE) << json(hover);
  EXPECT_NE(hover.message().find("battery"), std::string::npos) << hover.message();
  const auto& fallback = last->steps(3);
  EXPECT_EQ(std::vector<int>(fallback.path().begin(), fallback.path().end()),
            (std::vector<int>{2, 0}))
      << json(fallback);
  EXPECT_EQ(fallback.name(), "land_on_low_battery");
  EXPECT_EQ(fallback.behavior(), "LAND");
  EXPECT_EQ(fallback.cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED) << json(fallback);
  for (const std::string key :
       {"drone1/branches/situation_change", "drone1/branches/after_hover"}) {
    v1::ReadBeliefRequest read;
    read.set_key(key);
    auto belief = unary(*stub_, &v1::Coordinator::Stub::ReadBelief, read);
    ASSERT_TRUE(belief.status.ok()) << key << ": " << describe(belief.status);
    EXPECT_TRUE(belief.response.belief().value().bool_value()) << key;
    EXPECT_EQ(belief.response.belief().writer(), "mission:battery-1") << key;
  }
  std::printf("battery drop while hovering: %s; fallback %s %s\n", causeOf(*hover_end).c_str(),
              fallback.behavior().c_str(), v1::TerminationCause_Name(fallback.cause()).c_str());
}

// A step bound to a belief that is not in memory, that no step of the mission
// writes and that it does not wait for is a problem of the check (and of
// StartMission) with its line and field; a `remember` of an earlier step, a
// behavior's catalog `writes`, a wait_for or an `if` on the same belief
// provide it.
TEST_F(CoordinatorPlansMissionsTest, TheCheckFindsBindingsToBeliefsNothingWrites) {
  auto check = [&](const std::string& steps) {
    v1::CheckMissionRequest request;
    request.set_text("name: bound\nrobot: drone1\nsteps:\n" + steps);
    request.set_source_name("bound.yaml");
    auto checked = unary(*stub_, &v1::Coordinator::Stub::CheckMission, request);
    EXPECT_TRUE(checked.status.ok()) << describe(checked.status);
    std::vector<std::string> problems;
    for (const auto& p : checked.response.problems()) {
      problems.push_back(p.field() + " " + p.description());
    }
    return problems;
  };
  const std::string wait_bound =
      "  - behavior: WAIT\n"
      "    parameters:\n"
      "      duration_s: \"${belief.drone1/check_wait_s}\"\n";
  const auto nothing = check(wait_bound);
  ASSERT_EQ(nothing.size(), 1u);
  EXPECT_EQ(nothing[0],
            "steps[0].parameters.duration_s bound.yaml:6: ${belief.drone1/check_wait_s}: belief "
            "'drone1/check_wait_s' is not in memory, and no step of the mission writes it (its "
            "`remember`, or a behavior whose catalog entry lists it under `writes`) or waits for "
            "it");
  auto refused = startMissionText("name: bound\nrobot: drone1\nsteps:\n" + wait_bound);
  EXPECT_EQ(refused.status.error_code(), grpc::StatusCode::INVALID_ARGUMENT)
      << describe(refused.status);
  // Remembered by an earlier step; waited for; guarded by its own `if`.
  EXPECT_TRUE(check("  - remember: {drone1/check_wait_s: 0.1}\n" + wait_bound).empty());
  EXPECT_TRUE(check("  - wait_for: {belief: drone1/check_wait_s, exists: true, timeout_s: 5}\n" +
                    wait_bound)
                  .empty());
  EXPECT_TRUE(check(wait_bound + "    if: {belief: drone1/check_wait_s, exists: true}\n").empty());
  // In memory already.
  ASSERT_TRUE(writeBelief("drone1/check_wait_s", "0.1").status.ok());
  EXPECT_TRUE(check(wait_bound).empty());
}

// `when:` conditions on the vehicle, read from its topics while a step runs:
// a TAKE_OFF to 4 m ends GOAL_ACHIEVED as it passes 1.5 m (its condition,
// not its goal), and a long WAIT ends SITUATION_CHANGE when the battery
// drops below 0.5, which its fallback lands on. Neither behavior looks at
// what its condition reads.
TEST_F(CoordinatorPlansMissionsTest, ConditionsOnTheVehicleEndAStepWhileItRuns) {
  // After the usual localization, safety step and settling WAIT:
  const std::string settled = std::string(kDemoPreamble);
  auto started = startMissionText(settled +
                                      "  - name: take_off\n"
                                      "    behavior: TAKE_OFF\n"
                                      "    parameters: {altitude_m: 4.0}\n"
                                      "    when:\n"
                                      "      - {near: {point_m: [0, 0, 1.5], radius_m: 0.6}, "
                                      "ends: GOAL_ACHIEVED}\n"
                                      "    on: {REFUSED: {retry: 2}}\n"
                                      "  - name: hold\n"
                                      "    behavior: WAIT\n"
                                      "    parameters: {duration_s: 600}\n"
                                      "    when: [{battery_below: 0.5}]\n"
                                      "    on:\n"
                                      "      SITUATION_CHANGE: {fallback: [{name: "
                                      "land_on_low_battery, behavior: LAND}]}\n",
                                  "conditions-1");
  ASSERT_TRUE(started.status.ok()) << describe(started.status);
  MissionWatcher watcher(coordinator_->address(), "conditions-1");
  // The hold activated: the take-off ended before it.
  auto holding = watcher.waitFor(
      [](const v1::MissionStatus& s) {
        for (const auto& r : s.steps()) {
          if (r.name() == "hold" && !r.activation_id().empty()) return true;
        }
        return false;
      },
      seconds(60));
  ASSERT_TRUE(holding) << "the mission did not reach its hold";
  const auto& take_off = holding->steps(1);
  EXPECT_EQ(take_off.cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED) << json(take_off);
  EXPECT_EQ(take_off.message().rfind("condition on the vehicle: ", 0), 0u) << take_off.message();
  EXPECT_NE(take_off.message().find("from (0, 0, 1.5), within 0.6 m"), std::string::npos)
      << take_off.message();
  // Still below 4 m: the condition, not the goal, ended it.
  auto simulator = v1::Simulator::NewStub(
      grpc::CreateChannel(simulator_->address(), grpc::InsecureChannelCredentials()));
  {
    grpc::ClientContext context;
    context.set_deadline(std::chrono::system_clock::now() + kCallTimeout);
    v1::WatchStateRequest request;
    request.add_robot_ids(kRobot);
    auto reader = simulator->WatchState(&context, request);
    v1::WatchStateResponse now;
    ASSERT_TRUE(reader->Read(&now)) << "the vehicle's current state first";
    EXPECT_LT(now.state().pose().position_m().z(), 3.0);
    context.TryCancel();
    (void)reader->Finish();
  }

  v1::InjectFailureRequest drop;
  drop.set_robot_id(kRobot);
  drop.set_component(v1::FAILURE_COMPONENT_BATTERY);
  drop.set_type(v1::FAILURE_TYPE_DEGRADED);
  drop.set_intensity(0.85);
  auto injected = unary(*simulator, &v1::Simulator::Stub::InjectFailure, drop);
  ASSERT_TRUE(injected.status.ok()) << describe(injected.status);
  const auto last = watcher.waitEnd(seconds(60));
  ASSERT_TRUE(last);
  ASSERT_EQ(last->state(), v1::MISSION_STATE_SUCCEEDED) << json(*last);
  ASSERT_EQ(last->steps_size(), 4) << json(*last);
  const auto& hold = last->steps(2);
  EXPECT_EQ(hold.cause(), v1::TERMINATION_CAUSE_SITUATION_CHANGE) << json(hold);
  EXPECT_EQ(hold.message().rfind("condition on the vehicle: battery ", 0), 0u) << hold.message();
  EXPECT_NE(hold.message().find(" below 0.5"), std::string::npos) << hold.message();
  EXPECT_EQ(last->steps(3).name(), "land_on_low_battery");
  EXPECT_EQ(last->steps(3).cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED) << json(last->steps(3));
}

// A mission branches on INTERRUPTED (its WAIT deactivated through the
// coordinator: a fallback WAIT runs and remembers it) and on PROCESS_FAILURE
// (the system hosting its next WAIT killed with SIGKILL: the coordinator's
// supervision ends the WAIT with PROCESS_FAILURE, the branch remembers it);
// without the branches either cause would abort the mission.
TEST_F(CoordinatorPlansMissionsTest, AMissionBranchesOnInterruptedAndOnProcessFailure) {
  FleetRecorder& events = recorder();
  auto started = startMissionText(
      "name: interrupted_then_failed\n"
      "robot: drone1\n"
      "steps:\n"
      "  - name: hold\n"
      "    behavior: WAIT\n"
      "    parameters: {duration_s: 600}\n"
      "    on:\n"
      "      INTERRUPTED:\n"
      "        fallback:\n"
      "          - name: after_interrupt\n"
      "            behavior: WAIT\n"
      "            parameters: {duration_s: 0.1}\n"
      "            remember: {drone1/branches/interrupted: true}\n"
      "  - name: hold_again\n"
      "    behavior: WAIT\n"
      "    parameters: {duration_s: 600}\n"
      "    on:\n"
      "      PROCESS_FAILURE:\n"
      "        fallback:\n"
      "          - name: after_failure\n"
      "            remember: {drone1/branches/process_failure: true}\n",
      "causes-1");
  ASSERT_TRUE(started.status.ok()) << describe(started.status);
  MissionWatcher watcher(coordinator_->address(), "causes-1");

  // INTERRUPTED: the first WAIT deactivated through the coordinator.
  auto holding = watcher.waitFor(
      [](const v1::MissionStatus& s) {
        return s.steps_size() == 1 && !s.steps(0).activation_id().empty();
      },
      seconds(10));
  ASSERT_TRUE(holding);
  const std::string hold_id = holding->steps(0).activation_id();
  ASSERT_TRUE(events.activated(hold_id));
  auto deactivated = client_->deactivate(kRobot, "WAIT", hold_id);
  ASSERT_TRUE(deactivated.status.ok()) << describe(deactivated.status);
  auto interrupted = events.finished(hold_id);
  ASSERT_TRUE(interrupted);
  EXPECT_EQ(interrupted->finished().cause(), v1::TERMINATION_CAUSE_INTERRUPTED);

  // PROCESS_FAILURE: the system of the second WAIT killed.
  auto holding_again = watcher.waitFor(
      [](const v1::MissionStatus& s) {
        return s.steps_size() == 3 && !s.steps(2).activation_id().empty();
      },
      seconds(10));
  ASSERT_TRUE(holding_again) << json(watcher.statuses().back());
  const std::string again_id = holding_again->steps(2).activation_id();
  ASSERT_TRUE(events.activated(again_id));
  const auto killed_at = SteadyClock::now();
  basic_->kill();
  auto failed = events.finished(again_id);
  ASSERT_TRUE(failed) << "no PROCESS_FAILURE after the kill";
  const double reported_s = std::chrono::duration<double>(SteadyClock::now() - killed_at).count();
  EXPECT_EQ(failed->finished().cause(), v1::TERMINATION_CAUSE_PROCESS_FAILURE) << causeOf(*failed);

  const auto last = watcher.waitEnd(seconds(10));
  ASSERT_TRUE(last);
  ASSERT_EQ(last->state(), v1::MISSION_STATE_SUCCEEDED) << json(*last);
  struct Expected {
    std::vector<int> path;
    std::string name;
    v1::TerminationCause cause;
  };
  const std::vector<Expected> expected = {
      {{0}, "hold", v1::TERMINATION_CAUSE_INTERRUPTED},
      {{0, 0}, "after_interrupt", v1::TERMINATION_CAUSE_GOAL_ACHIEVED},
      {{1}, "hold_again", v1::TERMINATION_CAUSE_PROCESS_FAILURE}};
  ASSERT_EQ(last->steps_size(), static_cast<int>(expected.size())) << json(*last);
  for (size_t i = 0; i < expected.size(); ++i) {
    const auto& step = last->steps(static_cast<int>(i));
    SCOPED_TRACE(json(step));
    EXPECT_EQ(std::vector<int>(step.path().begin(), step.path().end()), expected[i].path);
    EXPECT_EQ(step.name(), expected[i].name);
    EXPECT_EQ(step.state(), v1::MISSION_STEP_STATE_FINISHED);
    EXPECT_EQ(step.cause(), expected[i].cause);
  }
  for (const std::string key : {"drone1/branches/interrupted", "drone1/branches/process_failure"}) {
    v1::ReadBeliefRequest read;
    read.set_key(key);
    auto belief = unary(*stub_, &v1::Coordinator::Stub::ReadBelief, read);
    ASSERT_TRUE(belief.status.ok()) << key << ": " << describe(belief.status);
    EXPECT_TRUE(belief.response.belief().value().bool_value()) << key;
    EXPECT_EQ(belief.response.belief().writer(), "mission:causes-1") << key;
  }
  std::printf("SIGKILL of basic_quadrotor_behaviors: PROCESS_FAILURE after %.2f s (%s)\n",
              reported_s, failed->finished().message().c_str());
}

}  // namespace
}  // namespace coordinator_test
