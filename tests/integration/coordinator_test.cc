// Integration tests of the coordinator's registry and event stream: the real
// coordinator and basic_quadrotor_behaviors processes (which host WAIT) on
// free loopback ports, talking real gRPC. Systems register themselves with
// --coordinator, or are listed in the coordinator's --systems file.

#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <atomic>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <map>
#include <memory>
#include <set>
#include <string>
#include <thread>
#include <vector>

#include "absl/strings/match.h"
#include "absl/strings/str_split.h"
#include "behaviorlib/error_details.h"
#include "coordinator_test_support.h"
#include "support/run_command.h"
#include "support/server_process.h"

namespace coordinator_test {
namespace {

constexpr char kCoordinatorBinary[] = BEHAVIORLIB_COORDINATOR_PATH;
constexpr char kSystemBinary[] = BEHAVIORLIB_BASIC_QUADROTOR_BEHAVIORS_PATH;
constexpr char kBehaviorctlBinary[] = BEHAVIORLIB_BEHAVIORCTL_PATH;
constexpr char kSystem[] = "basic_quadrotor_behaviors";

class CoordinatorTest : public ::testing::Test {
 protected:
  void SetUp() override { startCoordinator({}); }

  void TearDown() override {
    systems_.clear();  // SIGKILL by ServerProcess's destructor if still running
    if (coordinator_ && coordinator_->running()) {
      EXPECT_EQ(coordinator_->terminate(), 0);
    }
  }

  void startCoordinator(std::vector<std::string> args) {
    coordinator_ = std::make_unique<support::ServerProcess>(kCoordinatorBinary, std::move(args));
    ASSERT_TRUE(coordinator_->start()) << coordinator_->error();
    client_ = std::make_unique<CoordinatorClient>(coordinator_->address());
  }

  // A behavior system of `robot` registering with the coordinator.
  support::ServerProcess& startSystem(const std::string& robot,
                                      std::vector<std::string> extra = {}) {
    std::vector<std::string> args = {"--robot-id", robot, "--coordinator", coordinator_->address()};
    args.insert(args.end(), extra.begin(), extra.end());
    systems_.push_back(std::make_unique<support::ServerProcess>(kSystemBinary, args));
    EXPECT_TRUE(systems_.back()->start()) << systems_.back()->error();
    return *systems_.back();
  }

  std::unique_ptr<support::ServerProcess> coordinator_;
  std::unique_ptr<CoordinatorClient> client_;
  std::vector<std::unique_ptr<support::ServerProcess>> systems_;
};

TEST_F(CoordinatorTest, RegisteredSystemsAreListedWithTheirRealPortsAndBehaviors) {
  auto& a = startSystem("robot-a");
  auto& b = startSystem("robot-b");
  ASSERT_TRUE(client_->waitForSystem("robot-a", v1::SYSTEM_STATE_UP));
  ASSERT_TRUE(client_->waitForSystem("robot-b", v1::SYSTEM_STATE_UP));

  auto systems = client_->listSystems();
  ASSERT_TRUE(systems.status.ok()) << describe(systems.status);
  ASSERT_EQ(systems.response.systems_size(), 2);
  const std::map<std::string, support::ServerProcess*> processes = {{"robot-a", &a},
                                                                    {"robot-b", &b}};
  for (const auto& s : systems.response.systems()) {
    SCOPED_TRACE(s.ShortDebugString());
    ASSERT_TRUE(processes.contains(s.robot_id()));
    const auto& process = *processes.at(s.robot_id());
    EXPECT_EQ(s.system(), kSystem);
    // Started with --listen 127.0.0.1:0: the real bound port is advertised.
    EXPECT_EQ(s.address(), process.address());
    EXPECT_EQ(s.source(), v1::SYSTEM_SOURCE_REGISTRATION);
    auto own = SystemClient(process.address()).listBehaviors();
    ASSERT_TRUE(own.status.ok());
    EXPECT_EQ(s.incarnation(), own.response.incarnation());
    EXPECT_TRUE(s.has_last_heartbeat_time());
    EXPECT_TRUE(s.has_state_time());
    EXPECT_EQ(s.behaviors_size(), own.response.behaviors_size());
    EXPECT_NE(std::find(s.behaviors().begin(), s.behaviors().end(), "WAIT"), s.behaviors().end());
  }
  EXPECT_EQ(systems.response.systems(0).robot_id(), "robot-a") << "sorted by robot";
  EXPECT_EQ(client_->listSystems("robot-b").response.systems_size(), 1);

  auto behaviors = client_->listBehaviors();
  ASSERT_TRUE(behaviors.status.ok()) << describe(behaviors.status);
  std::set<std::string> robots_with_wait;
  for (const auto& fb : behaviors.response.behaviors()) {
    if (fb.description().name() != "WAIT") continue;
    robots_with_wait.insert(fb.robot_id());
    EXPECT_EQ(fb.system(), kSystem);
    EXPECT_EQ(fb.address(), processes.at(fb.robot_id())->address());
    EXPECT_EQ(fb.system_state(), v1::SYSTEM_STATE_UP);
    EXPECT_EQ(fb.description().state(), v1::BEHAVIOR_STATE_INACTIVE);
    EXPECT_TRUE(fb.activation_id().empty());
    // The schema comes from the system's own ListBehaviors.
    ASSERT_GE(fb.description().parameters_size(), 1);
    EXPECT_EQ(fb.description().parameters(0).name(), "duration_s");
    EXPECT_EQ(fb.description().service(), "behaviorlib.v1.Wait");
  }
  EXPECT_EQ(robots_with_wait, (std::set<std::string>{"robot-a", "robot-b"}));

  auto one = client_->listBehaviors("robot-b", "WAIT");
  ASSERT_TRUE(one.status.ok());
  ASSERT_EQ(one.response.behaviors_size(), 1);
  EXPECT_EQ(one.response.behaviors(0).robot_id(), "robot-b");

  const std::string metrics = support::httpGet(coordinator_->metricsPort(), "/metrics");
  EXPECT_EQ(metricValue(metrics, "behaviorlib_coordinator_systems_registered"), 2.0) << metrics;
  EXPECT_EQ(metricValue(metrics, "behaviorlib_coordinator_systems_up"), 2.0) << metrics;
}

TEST_F(CoordinatorTest, EventsOfTwoSystemsArriveInOneStreamFilteredByRobotAndBehavior) {
  startSystem("robot-a");
  startSystem("robot-b");
  ASSERT_TRUE(client_->waitForSystem("robot-a", v1::SYSTEM_STATE_UP));
  ASSERT_TRUE(client_->waitForSystem("robot-b", v1::SYSTEM_STATE_UP));

  FleetWatcher all(coordinator_->address());
  FleetWatcher only_a(coordinator_->address(), FleetWatcher::request(0, "", {"robot-a"}));
  FleetWatcher b_waits(coordinator_->address(),
                       FleetWatcher::request(0, "", {"robot-b"}, {"WAIT"}));
  auto start = all.start();
  ASSERT_TRUE(start);
  ASSERT_TRUE(only_a.start());
  ASSERT_TRUE(b_waits.start());

  auto ra = client_->activate("robot-a", "WAIT", R"({"duration_s": 0.2})");
  ASSERT_TRUE(ra.status.ok()) << describe(ra.status);
  auto rb = client_->activate("robot-b", "WAIT", R"({"duration_s": 0.1})");
  ASSERT_TRUE(rb.status.ok()) << describe(rb.status);
  EXPECT_EQ(ra.response.robot_id(), "robot-a");
  EXPECT_EQ(ra.response.system(), kSystem);
  const std::string id_a = ra.response.activation().activation_id();
  const std::string id_b = rb.response.activation().activation_id();
  ASSERT_FALSE(id_a.empty());

  std::vector<v1::FleetEvent> seen;
  auto fa = all.waitFinished(id_a);
  ASSERT_TRUE(fa) << "robot-a's WAIT did not finish in the stream";
  EXPECT_EQ(fa->behavior_event().finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED);
  EXPECT_FALSE(fa->synthesized());

  // The whole history, from a fresh subscriber: one gap-free sequence.
  FleetWatcher history(coordinator_->address());
  ASSERT_TRUE(history.start());
  auto events = history.drain();
  ASSERT_FALSE(events.empty());
  for (size_t i = 0; i < events.size(); ++i) {
    EXPECT_EQ(events[i].seq(), i + 1) << events[i].ShortDebugString();
    EXPECT_EQ(events[i].incarnation(), start->incarnation());
  }
  for (const std::string robot : {"robot-a", "robot-b"}) {
    const std::string id = robot == "robot-a" ? id_a : id_b;
    auto mine = behaviorEvents(events, robot);
    ASSERT_EQ(mine.size(), 2u) << robot;
    EXPECT_TRUE(mine[0].has_activated());
    EXPECT_TRUE(mine[1].has_finished());
    for (const auto& e : mine) {
      EXPECT_EQ(e.activation_id(), id);
      EXPECT_EQ(e.system(), kSystem);
      EXPECT_EQ(e.behavior(), "WAIT");
    }
    // The system's own numbering and incarnation travel with the event.
    EXPECT_EQ(mine[1].seq(), mine[0].seq() + 1);
    EXPECT_EQ(mine[0].incarnation(), client_->system(robot)->incarnation());
    EXPECT_EQ(finishedCount(events, id), 1);
  }

  auto a_events = only_a.drain();
  EXPECT_EQ(behaviorEvents(a_events, "robot-a").size(), 2u);
  for (const auto& e : a_events) {
    const std::string robot = e.has_behavior_event() ? e.behavior_event().robot_id()
                                                     : e.system_state_changed().system().robot_id();
    EXPECT_EQ(robot, "robot-a") << e.ShortDebugString();
  }
  auto b_events = b_waits.drain();
  ASSERT_EQ(b_events.size(), 2u) << "activated and finished of robot-b, nothing else";
  for (const auto& e : b_events) {
    ASSERT_TRUE(e.has_behavior_event()) << e.ShortDebugString();
    EXPECT_EQ(e.behavior_event().robot_id(), "robot-b");
    EXPECT_EQ(e.behavior_event().activation_id(), id_b);
  }

  const std::string metrics = support::httpGet(coordinator_->metricsPort(), "/metrics");
  EXPECT_EQ(metricValue(metrics, "behaviorlib_coordinator_events_received_total"), 4.0) << metrics;
}

TEST_F(CoordinatorTest, ListShowsTheActiveStateAndDeactivateIsRoutedToTheSystem) {
  auto& a = startSystem("robot-a");
  ASSERT_TRUE(client_->waitForSystem("robot-a", v1::SYSTEM_STATE_UP));
  FleetWatcher watcher(coordinator_->address());
  ASSERT_TRUE(watcher.start());

  auto r = client_->activate("robot-a", "WAIT", R"({"duration_s": 30})", "req-1");
  ASSERT_TRUE(r.status.ok()) << describe(r.status);
  const std::string id = r.response.activation().activation_id();
  ASSERT_TRUE(watcher.waitActivated(id));
  // Idempotent through the coordinator too (the system keeps the request id).
  auto again = client_->activate("robot-a", "WAIT", R"({"duration_s": 30})", "req-1");
  ASSERT_TRUE(again.status.ok()) << describe(again.status);
  EXPECT_TRUE(again.response.activation().replayed());
  EXPECT_EQ(again.response.activation().activation_id(), id);

  auto listed = client_->listBehaviors("robot-a", "WAIT");
  ASSERT_EQ(listed.response.behaviors_size(), 1);
  EXPECT_EQ(listed.response.behaviors(0).description().state(), v1::BEHAVIOR_STATE_ACTIVE);
  EXPECT_EQ(listed.response.behaviors(0).activation_id(), id);
  EXPECT_TRUE(SystemClient(a.address()).checkActivation("WAIT").response.active());

  auto situation = client_->situation("robot-a", "WAIT");
  ASSERT_TRUE(situation.status.ok()) << describe(situation.status);
  EXPECT_EQ(situation.response.system(), kSystem);

  auto d = client_->deactivate("robot-a", "WAIT", id);
  ASSERT_TRUE(d.status.ok()) << describe(d.status);
  EXPECT_EQ(d.response.result().activation_id(), id);
  EXPECT_EQ(d.response.result().cause(), v1::TERMINATION_CAUSE_INTERRUPTED);
  auto finished = watcher.waitFinished(id);
  ASSERT_TRUE(finished);
  EXPECT_EQ(finished->behavior_event().finished().cause(), v1::TERMINATION_CAUSE_INTERRUPTED);
  EXPECT_TRUE(waitUntil(
      [&] {
        auto l = client_->listBehaviors("robot-a", "WAIT");
        return l.response.behaviors_size() == 1 &&
               l.response.behaviors(0).description().state() == v1::BEHAVIOR_STATE_INACTIVE;
      },
      seconds(5)));
  EXPECT_FALSE(SystemClient(a.address()).checkActivation("WAIT").response.active());
}

// Pause, Resume, Modify and CheckActivation by robot: routed to the hosting
// system, which answers (and refuses) as when called directly; its events
// reach the fleet stream.
TEST_F(CoordinatorTest, PauseResumeModifyAndCheckActivationAreRoutedByRobot) {
  auto& a = startSystem("robot-a");
  ASSERT_TRUE(client_->waitForSystem("robot-a", v1::SYSTEM_STATE_UP));
  FleetWatcher watcher(coordinator_->address());
  ASSERT_TRUE(watcher.start());
  auto r = client_->activate("robot-a", "WAIT", R"({"duration_s": 3600})");
  ASSERT_TRUE(r.status.ok()) << describe(r.status);
  const std::string id = r.response.activation().activation_id();
  ASSERT_TRUE(watcher.waitActivated(id));
  auto& stub = client_->stub();
  auto check = [&] {
    v1::CheckFleetBehaviorActivationRequest request;
    request.set_robot_id("robot-a");
    request.set_behavior("WAIT");
    return unary(stub, &v1::Coordinator::Stub::CheckFleetBehaviorActivation, request);
  };
  auto checked = check();
  ASSERT_TRUE(checked.status.ok()) << describe(checked.status);
  EXPECT_EQ(checked.response.robot_id(), "robot-a");
  EXPECT_EQ(checked.response.system(), kSystem);
  EXPECT_EQ(checked.response.activation().state(), v1::BEHAVIOR_STATE_ACTIVE);
  EXPECT_EQ(checked.response.activation().activation_id(), id);

  v1::PauseFleetBehaviorRequest pause;
  pause.set_robot_id("robot-a");
  pause.set_behavior("WAIT");
  pause.set_activation_id(id);
  auto paused = unary(stub, &v1::Coordinator::Stub::PauseFleetBehavior, pause);
  ASSERT_TRUE(paused.status.ok()) << describe(paused.status);
  EXPECT_EQ(paused.response.result().activation_id(), id);
  EXPECT_EQ(paused.response.system(), kSystem);
  EXPECT_EQ(check().response.activation().state(), v1::BEHAVIOR_STATE_PAUSED);
  EXPECT_EQ(SystemClient(a.address()).checkActivation("WAIT").response.state(),
            v1::BEHAVIOR_STATE_PAUSED);
  ASSERT_TRUE(watcher.waitFor([&](const v1::FleetEvent& e) {
    return e.behavior_event().activation_id() == id && e.behavior_event().has_paused();
  }));
  // The system's refusal, relayed with its reason and the robot.
  auto twice = unary(stub, &v1::Coordinator::Stub::PauseFleetBehavior, pause);
  EXPECT_EQ(twice.status.error_code(), grpc::StatusCode::FAILED_PRECONDITION)
      << describe(twice.status);
  auto info = behaviorlib::errors::errorInfo(twice.status);
  ASSERT_TRUE(info);
  EXPECT_EQ(info->reason(), "BEHAVIOR_ALREADY_PAUSED");
  EXPECT_EQ(info->metadata().at("robot"), "robot-a");
  EXPECT_EQ(info->metadata().at("system"), kSystem);

  v1::ResumeFleetBehaviorRequest resume;
  resume.set_robot_id("robot-a");
  resume.set_behavior("WAIT");
  auto resumed = unary(stub, &v1::Coordinator::Stub::ResumeFleetBehavior, resume);
  ASSERT_TRUE(resumed.status.ok()) << describe(resumed.status);
  EXPECT_EQ(resumed.response.result().activation_id(), id);
  EXPECT_EQ(check().response.activation().state(), v1::BEHAVIOR_STATE_ACTIVE);

  v1::ModifyFleetBehaviorRequest modify;
  modify.set_robot_id("robot-a");
  modify.set_behavior("WAIT");
  *modify.mutable_parameters() = structFromJson(R"({"duration_s": 7200})");
  auto modified = unary(stub, &v1::Coordinator::Stub::ModifyFleetBehavior, modify);
  ASSERT_TRUE(modified.status.ok()) << describe(modified.status);
  EXPECT_EQ(modified.response.result().parameters().fields().at("duration_s").number_value(), 7200);
  EXPECT_EQ(check().response.activation().parameters().fields().at("duration_s").number_value(),
            7200);
  *modify.mutable_parameters() = structFromJson(R"({"duration_s": -1})");
  auto refused = unary(stub, &v1::Coordinator::Stub::ModifyFleetBehavior, modify);
  EXPECT_EQ(refused.status.error_code(), grpc::StatusCode::INVALID_ARGUMENT)
      << describe(refused.status);
  auto bad = behaviorlib::errors::badRequest(refused.status);
  ASSERT_TRUE(bad);
  ASSERT_EQ(bad->field_violations_size(), 1);
  EXPECT_NE(bad->field_violations(0).field().find("duration_s"), std::string::npos)
      << bad->ShortDebugString();
  modify.set_activation_id("not-this-one");
  *modify.mutable_parameters() = structFromJson(R"({"duration_s": 10})");
  EXPECT_EQ(unary(stub, &v1::Coordinator::Stub::ModifyFleetBehavior, modify).status.error_code(),
            grpc::StatusCode::ABORTED);

  // Unknown robot and behavior: the coordinator's own refusals.
  pause.set_robot_id("ghost");
  auto ghost = unary(stub, &v1::Coordinator::Stub::PauseFleetBehavior, pause);
  EXPECT_EQ(ghost.status.error_code(), grpc::StatusCode::NOT_FOUND) << describe(ghost.status);
  EXPECT_EQ(behaviorlib::errors::errorInfo(ghost.status)->reason(), "UNKNOWN_ROBOT");
  pause.set_robot_id("robot-a");
  pause.set_behavior("NO_SUCH_BEHAVIOR");
  auto unknown = unary(stub, &v1::Coordinator::Stub::PauseFleetBehavior, pause);
  EXPECT_EQ(unknown.status.error_code(), grpc::StatusCode::NOT_FOUND);
  EXPECT_EQ(behaviorlib::errors::errorInfo(unknown.status)->reason(), "UNKNOWN_BEHAVIOR");

  ASSERT_TRUE(client_->deactivate("robot-a", "WAIT", id).status.ok());
  ASSERT_TRUE(watcher.waitFinished(id));
  EXPECT_FALSE(check().response.activation().active());
}

TEST_F(CoordinatorTest, ResumingFromSinceSeqReplaysTheMissedEventsExactlyOnce) {
  startSystem("robot-a");
  ASSERT_TRUE(client_->waitForSystem("robot-a", v1::SYSTEM_STATE_UP));
  FleetWatcher reference(coordinator_->address());
  auto reference_start = reference.start();
  ASSERT_TRUE(reference_start);
  const std::string incarnation = reference_start->incarnation();
  auto runWait = [&](double duration_s) {
    auto r = client_->activate("robot-a", "WAIT",
                               "{\"duration_s\": " + std::to_string(duration_s) + "}");
    EXPECT_TRUE(r.status.ok()) << describe(r.status);
    EXPECT_TRUE(reference.waitFinished(r.response.activation().activation_id()));
  };

  uint64_t last_seen = 0;
  {
    FleetWatcher a(coordinator_->address());
    ASSERT_TRUE(a.start());
    auto r = client_->activate("robot-a", "WAIT", R"({"duration_s": 0.05})");
    ASSERT_TRUE(r.status.ok());
    auto finished = a.waitFinished(r.response.activation().activation_id());
    ASSERT_TRUE(finished);
    last_seen = finished->seq();
    ASSERT_TRUE(reference.waitFinished(r.response.activation().activation_id()));
  }

  // More happens while A is away.
  runWait(0.05);
  runWait(0.05);
  auto pending = client_->activate("robot-a", "WAIT", R"({"duration_s": 30})");
  ASSERT_TRUE(pending.status.ok());
  ASSERT_TRUE(reference.waitActivated(pending.response.activation().activation_id()));

  std::vector<v1::FleetEvent> missed;
  {
    FleetWatcher everything(coordinator_->address());
    ASSERT_TRUE(everything.start());
    for (const auto& e : everything.drain()) {
      if (e.seq() > last_seen) missed.push_back(e);
    }
  }
  ASSERT_EQ(missed.size(), 5u) << "2 finished WAITs + one activated";

  {
    FleetWatcher a(coordinator_->address(), FleetWatcher::request(last_seen, incarnation));
    auto start = a.start();
    ASSERT_TRUE(start);
    EXPECT_FALSE(start->incarnation_changed());
    EXPECT_FALSE(start->events_dropped());
    EXPECT_EQ(start->latest_seq(), missed.back().seq());
    for (size_t i = 0; i < missed.size(); ++i) {
      auto e = a.nextEvent();
      ASSERT_TRUE(e) << "missed event " << i << " not replayed";
      EXPECT_EQ(e->seq(), last_seen + 1 + i);
      EXPECT_EQ(e->SerializeAsString(), missed[i].SerializeAsString());
    }
    EXPECT_FALSE(a.nextEvent(milliseconds(300))) << "duplicate or extra event";
    // Live events continue the sequence.
    ASSERT_TRUE(client_->deactivate("robot-a", "WAIT").status.ok());
    auto live = a.nextEvent();
    ASSERT_TRUE(live);
    EXPECT_TRUE(live->behavior_event().has_finished());
    EXPECT_EQ(live->seq(), missed.back().seq() + 1);
  }

  FleetWatcher wrong(coordinator_->address(), FleetWatcher::request(last_seen, "another-run"));
  auto start = wrong.start();
  ASSERT_TRUE(start);
  EXPECT_TRUE(start->incarnation_changed());
  auto first = wrong.nextEvent();
  ASSERT_TRUE(first);
  EXPECT_EQ(first->seq(), 1u) << "everything retained is replayed";
}

// max_events_per_message: the same events, in the same order, in batches of
// at most that many (the replay of everything retained comes in full ones).
TEST_F(CoordinatorTest, ASubscriberThatAsksForBatchesGetsTheSameEventsInFewerMessages) {
  startSystem("robot-a");
  ASSERT_TRUE(client_->waitForSystem("robot-a", v1::SYSTEM_STATE_UP));
  FleetWatcher reference(coordinator_->address());
  ASSERT_TRUE(reference.start());
  for (int i = 0; i < 3; ++i) {
    auto r = client_->activate("robot-a", "WAIT", R"({"duration_s": 0.05})");
    ASSERT_TRUE(r.status.ok()) << describe(r.status);
    ASSERT_TRUE(reference.waitFinished(r.response.activation().activation_id()));
  }
  std::vector<v1::FleetEvent> one_by_one;
  {
    FleetWatcher everything(coordinator_->address());
    ASSERT_TRUE(everything.start());
    one_by_one = everything.drain();
  }
  ASSERT_GE(one_by_one.size(), 7u) << "the system's UP and three WAITs";

  v1::WatchFleetEventsRequest request = FleetWatcher::request(0, "");
  request.set_max_events_per_message(4);
  FleetWatcher batched(coordinator_->address(), request);
  ASSERT_TRUE(batched.start());
  std::vector<v1::FleetEvent> received;
  size_t messages = 0;
  while (received.size() < one_by_one.size()) {
    auto message = batched.next();
    ASSERT_TRUE(message) << "after " << received.size() << " events";
    ASSERT_TRUE(message->has_events()) << message->ShortDebugString();
    const auto& events = message->events().events();
    ASSERT_GE(events.size(), 1);
    ASSERT_LE(events.size(), 4);
    received.insert(received.end(), events.begin(), events.end());
    ++messages;
  }
  ASSERT_EQ(received.size(), one_by_one.size());
  for (size_t i = 0; i < received.size(); ++i) {
    EXPECT_EQ(received[i].SerializeAsString(), one_by_one[i].SerializeAsString()) << i;
  }
  EXPECT_EQ(messages, (one_by_one.size() + 3) / 4) << "the replay comes in full batches";

  // Live events continue the sequence, still in batches.
  auto live = client_->activate("robot-a", "WAIT", R"({"duration_s": 0.05})");
  ASSERT_TRUE(live.status.ok());
  uint64_t seq = received.back().seq();
  bool finished = false;
  while (!finished) {
    auto message = batched.next();
    ASSERT_TRUE(message) << "no live event after seq " << seq;
    ASSERT_TRUE(message->has_events());
    for (const v1::FleetEvent& e : message->events().events()) {
      EXPECT_EQ(e.seq(), ++seq);
      finished = finished ||
                 (e.behavior_event().has_finished() &&
                  e.behavior_event().activation_id() == live.response.activation().activation_id());
    }
  }
}

TEST_F(CoordinatorTest, UnknownRobotsAndBehaviorsAndBadRequestsAreRefusedClearly) {
  auto& a = startSystem("robot-a");
  ASSERT_TRUE(client_->waitForSystem("robot-a", v1::SYSTEM_STATE_UP));

  auto r = client_->activate("ghost", "WAIT", R"({"duration_s": 1})");
  EXPECT_EQ(r.status.error_code(), grpc::StatusCode::NOT_FOUND) << describe(r.status);
  EXPECT_NE(r.status.error_message().find("'ghost'"), std::string::npos) << describe(r.status);
  EXPECT_NE(r.status.error_message().find("robot-a"), std::string::npos)
      << "lists the known robots: " << describe(r.status);

  r = client_->activate("robot-a", "FLY", R"({})");
  EXPECT_EQ(r.status.error_code(), grpc::StatusCode::NOT_FOUND) << describe(r.status);
  EXPECT_NE(r.status.error_message().find("'FLY'"), std::string::npos) << describe(r.status);
  EXPECT_NE(r.status.error_message().find("WAIT"), std::string::npos) << describe(r.status);

  r = client_->activate("robot-a", "WAIT", R"({"duration_s": -1})");
  EXPECT_EQ(r.status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << describe(r.status);
  EXPECT_NE(r.status.error_message().find("duration_s"), std::string::npos) << describe(r.status);
  EXPECT_NE(r.status.error_message().find(kSystem), std::string::npos)
      << "names the system that refused: " << describe(r.status);

  r = client_->activate("", "WAIT", R"({})");
  EXPECT_EQ(r.status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << describe(r.status);
  EXPECT_NE(r.status.error_message().find("robot_id"), std::string::npos) << describe(r.status);

  auto d = client_->deactivate("ghost", "WAIT");
  EXPECT_EQ(d.status.error_code(), grpc::StatusCode::NOT_FOUND) << describe(d.status);
  auto s = client_->situation("robot-a", "FLY");
  EXPECT_EQ(s.status.error_code(), grpc::StatusCode::NOT_FOUND) << describe(s.status);

  v1::RegisterSystemRequest reg;
  reg.set_system(kSystem);
  reg.set_address(a.address());
  reg.set_incarnation("x");
  auto g = client_->registerSystem(reg);
  EXPECT_EQ(g.status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << describe(g.status);
  EXPECT_NE(g.status.error_message().find("robot_id"), std::string::npos) << describe(g.status);
  reg.set_robot_id("robot-z");
  reg.set_address("nowhere");
  g = client_->registerSystem(reg);
  EXPECT_EQ(g.status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << describe(g.status);
  EXPECT_NE(g.status.error_message().find("nowhere"), std::string::npos) << describe(g.status);
  reg.set_address("127.0.0.1:1");  // nothing listens there
  g = client_->registerSystem(reg);
  EXPECT_EQ(g.status.error_code(), grpc::StatusCode::UNAVAILABLE) << describe(g.status);
  EXPECT_NE(g.status.error_message().find("127.0.0.1:1"), std::string::npos) << describe(g.status);
  reg.set_address(a.address());  // serves robot-a, not robot-z
  g = client_->registerSystem(reg);
  EXPECT_EQ(g.status.error_code(), grpc::StatusCode::FAILED_PRECONDITION) << describe(g.status);
  EXPECT_NE(g.status.error_message().find("robot-a"), std::string::npos) << describe(g.status);
  EXPECT_EQ(behaviorlib::errors::errorInfo(g.status)->reason(), "IDENTITY_MISMATCH");
  // robot-a's system under another name: its address answers otherwise.
  reg.set_robot_id("robot-a");
  reg.set_system("impostor");
  g = client_->registerSystem(reg);
  EXPECT_EQ(g.status.error_code(), grpc::StatusCode::FAILED_PRECONDITION) << describe(g.status);
  EXPECT_EQ(behaviorlib::errors::errorInfo(g.status)->reason(), "IDENTITY_MISMATCH");

  v1::HeartbeatRequest hb;
  hb.set_robot_id("robot-z");
  hb.set_system(kSystem);
  hb.set_incarnation("x");
  auto h = client_->heartbeat(hb);
  EXPECT_EQ(h.status.error_code(), grpc::StatusCode::NOT_FOUND) << describe(h.status);
  EXPECT_NE(h.status.error_message().find("register again"), std::string::npos)
      << describe(h.status);

  // Nothing was registered by the refused calls, and the coordinator serves on.
  EXPECT_EQ(client_->listSystems().response.systems_size(), 1);
  FleetWatcher watcher(coordinator_->address());
  ASSERT_TRUE(watcher.start());
  r = client_->activate("robot-a", "WAIT", R"({"duration_s": 0.05})");
  ASSERT_TRUE(r.status.ok()) << describe(r.status);
  EXPECT_TRUE(watcher.waitFinished(r.response.activation().activation_id()));
}

TEST_F(CoordinatorTest, SystemsRegisterAgainWithARestartedCoordinator) {
  auto& a = startSystem("robot-a");
  ASSERT_TRUE(client_->waitForSystem("robot-a", v1::SYSTEM_STATE_UP));
  const std::string incarnation = client_->system("robot-a")->incarnation();
  const int port = coordinator_->grpcPort();

  coordinator_->kill();
  startCoordinator({"--listen", "127.0.0.1:" + std::to_string(port)});
  ASSERT_EQ(coordinator_->grpcPort(), port);
  // The heartbeat fails, the system registers again with the new coordinator.
  ASSERT_TRUE(client_->waitForSystem("robot-a", v1::SYSTEM_STATE_UP, seconds(10)))
      << "the system did not register with the restarted coordinator";
  auto s = client_->system("robot-a");
  EXPECT_EQ(s->incarnation(), incarnation) << "the same system process";
  EXPECT_EQ(s->address(), a.address());

  FleetWatcher watcher(coordinator_->address());
  ASSERT_TRUE(watcher.start());
  auto r = client_->activate("robot-a", "WAIT", R"({"duration_s": 0.05})");
  ASSERT_TRUE(r.status.ok()) << describe(r.status);
  auto finished = watcher.waitFinished(r.response.activation().activation_id());
  ASSERT_TRUE(finished);
  EXPECT_EQ(finished->behavior_event().finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED);
}

TEST_F(CoordinatorTest, ARestartedCoordinatorContactsItsJournaledSystemsBeforeTheirNextHeartbeat) {
  char dir[] = "/tmp/coordinator_registry_XXXXXX";
  ASSERT_NE(mkdtemp(dir), nullptr);
  const std::string state_dir = dir;
  // Systems are told to send a heartbeat every 60 s: within this test only
  // the journal can tell a restarted coordinator where they are.
  const std::vector<std::string> args = {"--state-dir", state_dir, "--heartbeat-interval-s", "60"};
  ASSERT_EQ(coordinator_->terminate(), 0);
  startCoordinator(args);
  auto& a = startSystem("robot-a");
  ASSERT_TRUE(client_->waitForSystem("robot-a", v1::SYSTEM_STATE_UP));
  const int port = coordinator_->grpcPort();

  coordinator_->kill();
  std::vector<std::string> again = args;
  again.insert(again.end(), {"--listen", "127.0.0.1:" + std::to_string(port)});
  startCoordinator(again);
  ASSERT_TRUE(client_->waitForSystem("robot-a", v1::SYSTEM_STATE_UP, seconds(5)))
      << "the restarted coordinator did not contact the journaled system";
  EXPECT_EQ(client_->system("robot-a")->address(), a.address());
  auto r = client_->activate("robot-a", "WAIT", R"({"duration_s": 0.05})");
  EXPECT_TRUE(r.status.ok()) << describe(r.status);
  std::filesystem::remove_all(state_dir);
}

TEST_F(CoordinatorTest, ACatalogEntryThatDisagreesWithTheRegistrationIsRefusedWithItsLine) {
  char path[] = "/tmp/catalog_XXXXXX.yaml";
  const int fd = mkstemps(path, 5);
  ASSERT_GE(fd, 0);
  close(fd);
  {
    std::ofstream catalog(path);
    catalog << "behaviors:\n"
               "  TAKE_OFF: {}\n"
               "  WAIT:\n"
               "    defaults: {duration_seconds: 2}\n";  // line 3; WAIT has duration_s
  }
  ASSERT_EQ(coordinator_->terminate(), 0);
  startCoordinator({"--catalog", path});
  // A system that does not register by itself, registered by hand.
  systems_.push_back(std::make_unique<support::ServerProcess>(
      kSystemBinary, std::vector<std::string>{"--robot-id", "robot-a"}));
  ASSERT_TRUE(systems_.back()->start()) << systems_.back()->error();
  auto own = SystemClient(systems_.back()->address()).listBehaviors();
  ASSERT_TRUE(own.status.ok()) << describe(own.status);
  v1::RegisterSystemRequest reg;
  reg.set_robot_id("robot-a");
  reg.set_system(kSystem);
  reg.set_address(systems_.back()->address());
  reg.set_incarnation(own.response.incarnation());
  auto g = client_->registerSystem(reg);
  EXPECT_EQ(g.status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << describe(g.status);
  EXPECT_NE(g.status.error_message().find(std::string(path) + ":3"), std::string::npos)
      << describe(g.status);
  EXPECT_NE(g.status.error_message().find("duration_seconds"), std::string::npos)
      << describe(g.status);
  EXPECT_FALSE(client_->system("robot-a")) << "a refused system is not registered";
  std::remove(path);
}

TEST_F(CoordinatorTest, SigtermOfASystemDeliversItsInterruptedEventsThenUnregistersIt) {
  auto& a = startSystem("robot-a");
  ASSERT_TRUE(client_->waitForSystem("robot-a", v1::SYSTEM_STATE_UP));
  FleetWatcher watcher(coordinator_->address());
  ASSERT_TRUE(watcher.start());
  auto r = client_->activate("robot-a", "WAIT", R"({"duration_s": 30})");
  ASSERT_TRUE(r.status.ok()) << describe(r.status);
  const std::string id = r.response.activation().activation_id();
  ASSERT_TRUE(watcher.waitActivated(id));

  EXPECT_EQ(a.terminate(), 0);
  std::vector<v1::FleetEvent> before;
  auto left = watcher.waitFor(
      [](const v1::FleetEvent& e) {
        return e.has_system_state_changed() &&
               e.system_state_changed().system().state() == v1::SYSTEM_STATE_UNREGISTERED;
      },
      seconds(5), &before);
  ASSERT_TRUE(left) << "no UNREGISTERED state event";
  EXPECT_EQ(finishedCount(before, id), 1);
  for (const auto& e : before) {
    if (e.has_behavior_event() && e.behavior_event().has_finished()) {
      EXPECT_EQ(e.behavior_event().finished().cause(), v1::TERMINATION_CAUSE_INTERRUPTED);
      EXPECT_FALSE(e.synthesized()) << "the system's own event, not a synthesized failure";
    }
  }
  EXPECT_TRUE(
      waitUntil([&] { return client_->listSystems().response.systems_size() == 0; }, seconds(5)))
      << "a registered system that left is removed";
  EXPECT_EQ(finishedCount(watcher.drain(), id), 0) << "nothing more for that activation";
  auto after = client_->activate("robot-a", "WAIT", R"({"duration_s": 1})");
  EXPECT_EQ(after.status.error_code(), grpc::StatusCode::NOT_FOUND) << describe(after.status);
}

TEST_F(CoordinatorTest, ConfiguredSystemsAreContactedAndContactedAgainWhenTheyComeBack) {
  auto system = std::make_unique<support::ServerProcess>(
      kSystemBinary, std::vector<std::string>{"--robot-id", "robot-c"});
  ASSERT_TRUE(system->start()) << system->error();
  const int port = system->grpcPort();
  char path[] = "/tmp/coordinator-systems-XXXXXX";
  const int fd = mkstemp(path);
  ASSERT_GE(fd, 0);
  close(fd);
  {
    std::ofstream out(path);
    out << "systems:\n  - robot_id: robot-c\n    address: " << system->address() << "\n";
  }
  ASSERT_EQ(coordinator_->terminate(), 0);
  startCoordinator({"--systems", path});

  ASSERT_TRUE(client_->waitForSystem("robot-c", v1::SYSTEM_STATE_UP));
  auto s = client_->system("robot-c");
  EXPECT_EQ(s->source(), v1::SYSTEM_SOURCE_CONFIG);
  EXPECT_EQ(s->system(), kSystem) << "learned from the system";
  const std::string first = s->incarnation();

  system->kill();
  ASSERT_TRUE(client_->waitForSystem("robot-c", v1::SYSTEM_STATE_DOWN, seconds(5)));
  system = std::make_unique<support::ServerProcess>(
      kSystemBinary, std::vector<std::string>{"--robot-id", "robot-c", "--listen",
                                              "127.0.0.1:" + std::to_string(port)});
  ASSERT_TRUE(system->start()) << system->error();
  ASSERT_TRUE(waitUntil(
      [&] {
        auto now = client_->system("robot-c");
        return now && now->state() == v1::SYSTEM_STATE_UP && now->incarnation() != first;
      },
      seconds(10)))
      << "the restarted system was not contacted again";
  FleetWatcher watcher(coordinator_->address());
  ASSERT_TRUE(watcher.start());
  auto r = client_->activate("robot-c", "WAIT", R"({"duration_s": 0.05})");
  ASSERT_TRUE(r.status.ok()) << describe(r.status);
  EXPECT_TRUE(watcher.waitFinished(r.response.activation().activation_id()));
  unlink(path);
}

using support::run;
using ::testing::HasSubstr;
using ::testing::MatchesRegex;

TEST_F(CoordinatorTest, ABadSystemsFileStopsTheCoordinatorWithItsLine) {
  char path[] = "/tmp/coordinator-bad-XXXXXX";
  const int fd = mkstemp(path);
  ASSERT_GE(fd, 0);
  close(fd);
  {
    std::ofstream out(path);
    out << "systems:\n  - robot_id: r\n    address: no-port\n";
  }
  std::string output;
  const int code =
      run(std::string(kCoordinatorBinary) + " --listen 127.0.0.1:0 --systems " + path, &output);
  EXPECT_EQ(code, 2) << output;
  EXPECT_NE(output.find(std::string(path) + ":3"), std::string::npos) << output;
  EXPECT_NE(output.find("host:port"), std::string::npos) << output;
  unlink(path);
}

TEST_F(CoordinatorTest, BehaviorctlListsActivatesAndWatchesThroughTheCoordinator) {
  startSystem("robot-a");
  ASSERT_TRUE(client_->waitForSystem("robot-a", v1::SYSTEM_STATE_UP));
  const std::string ctl =
      std::string(kBehaviorctlBinary) + " --coordinator " + coordinator_->address();
  std::string output;
  // The listings print aligned tables, as kubectl does: a header, then a row
  // per item, each column starting where its header does.
  ASSERT_EQ(run(ctl + " list --robot robot-a", &output), 0) << output;
  {
    const std::vector<std::string> lines = absl::StrSplit(output, '\n', absl::SkipEmpty());
    ASSERT_GE(lines.size(), 2u) << output;
    EXPECT_THAT(lines[0], MatchesRegex("ROBOT +SYSTEM +BEHAVIOR +STATE +ACTIVATION")) << output;
    bool wait = false;
    for (size_t i = 1; i < lines.size(); ++i) {
      EXPECT_EQ(lines[i].find("robot-a"), 0u) << lines[i];
      if (absl::StrContains(lines[i], " WAIT ")) {
        wait = true;
        EXPECT_EQ(lines[i].substr(lines[0].find("SYSTEM"), 25), "basic_quadrotor_behaviors");
        EXPECT_EQ(lines[i].substr(lines[0].find("STATE"), 8), "INACTIVE") << output;
      }
    }
    EXPECT_TRUE(wait) << output;
  }
  // -o wide adds the schemas; -o json and -o yaml print the reply itself.
  output.clear();
  ASSERT_EQ(run(ctl + " list --robot robot-a -o wide", &output), 0) << output;
  EXPECT_THAT(output, HasSubstr("PARAMETERS"));
  EXPECT_THAT(output, HasSubstr("duration_s"));
  output.clear();
  ASSERT_EQ(run(ctl + " list --robot robot-a -o json", &output), 0) << output;
  EXPECT_NE(output.find("\"robot_id\":\"robot-a\""), std::string::npos) << output;
  EXPECT_NE(output.find("\"name\":\"WAIT\""), std::string::npos) << output;
  output.clear();
  ASSERT_EQ(run(ctl + " list --robot robot-a --output=yaml", &output), 0) << output;
  EXPECT_THAT(output, HasSubstr("robot_id: robot-a"));
  output.clear();
  EXPECT_EQ(run(ctl + " list -o xml", &output), 2) << output;
  EXPECT_THAT(output, HasSubstr("table, wide, json, yaml"));

  output.clear();
  ASSERT_EQ(run(ctl + " systems", &output), 0) << output;
  EXPECT_THAT(
      output,
      MatchesRegex(
          "ROBOT +SYSTEM +STATE +ADDRESS +BEHAVIORS +AGE\n"
          "robot-a +basic_quadrotor_behaviors +UP +127\\.0\\.0\\.1:[0-9]+ +[0-9]+ +[0-9]+s\n"))
      << output;
  output.clear();
  ASSERT_EQ(run(ctl + " systems -o json", &output), 0) << output;
  EXPECT_THAT(output, HasSubstr("SYSTEM_STATE_UP"));

  // An error says the reason and the field.
  output.clear();
  EXPECT_EQ(run(ctl + " --robot robot-a activate WAIT '{\"duration_s\": -1}'", &output), 1)
      << output;
  EXPECT_THAT(output, HasSubstr("behaviorctl: INVALID_ARGUMENT: "));
  EXPECT_THAT(output, HasSubstr("\n  field parameters.duration_s: "));

  output.clear();
  ASSERT_EQ(run(ctl + " --robot robot-a activate WAIT '{\"duration_s\": 0.05}'", &output), 0)
      << output;
  EXPECT_NE(output.find("activation_id"), std::string::npos) << output;

  output.clear();
  ASSERT_EQ(run(ctl + " watch --robot robot-a --behavior WAIT --until-finished WAIT --timeout-s 10",
                &output),
            0)
      << output;
  EXPECT_NE(output.find("TERMINATION_CAUSE_GOAL_ACHIEVED"), std::string::npos) << output;

  // Pause, resume, modify and the activation's state, by robot.
  output.clear();
  ASSERT_EQ(run(ctl + " --robot robot-a activate WAIT '{\"duration_s\": 3600}'", &output), 0)
      << output;
  for (const char* command : {"pause WAIT", "activation WAIT", "resume WAIT",
                              "modify WAIT '{\"duration_s\": 60}'", "activation WAIT"}) {
    output.clear();
    ASSERT_EQ(run(ctl + " --robot robot-a " + command, &output), 0) << command << ": " << output;
    EXPECT_NE(output.find("\"system\":\"basic_quadrotor_behaviors\""), std::string::npos)
        << command << ": " << output;
    if (std::string(command) == "pause WAIT") {
      output.clear();
      ASSERT_EQ(run(ctl + " --robot robot-a activation WAIT", &output), 0) << output;
      EXPECT_NE(output.find("BEHAVIOR_STATE_PAUSED"), std::string::npos) << output;
    }
  }
  EXPECT_NE(output.find("\"duration_s\":60"), std::string::npos) << output;
  output.clear();
  ASSERT_EQ(run(ctl + " --robot robot-a deactivate WAIT", &output), 0) << output;
  output.clear();
  EXPECT_EQ(run(ctl + " pause WAIT", &output), 2) << "needs --robot: " << output;

  output.clear();
  EXPECT_EQ(run(ctl + " --robot ghost activate WAIT", &output), 1) << output;
  EXPECT_NE(output.find("ghost"), std::string::npos) << output;
  output.clear();
  EXPECT_EQ(run(ctl + " activate WAIT", &output), 2) << "needs --robot: " << output;
}

// ActivateBehavior is serialized per robot, not across robots: while a plan
// of robot-a waits for its system (stopped with SIGSTOP, so that the call
// cannot be answered), an activation on robot-b is applied and runs to its
// end; robot-a's completes once its system runs again.
TEST_F(CoordinatorTest, APlanWaitingOnOneRobotDoesNotHoldUpAnotherRobot) {
  auto& a = startSystem("robot-a");
  startSystem("robot-b");
  ASSERT_TRUE(client_->waitForSystem("robot-a", v1::SYSTEM_STATE_UP));
  ASSERT_TRUE(client_->waitForSystem("robot-b", v1::SYSTEM_STATE_UP));
  FleetWatcher watcher(coordinator_->address());
  ASSERT_TRUE(watcher.start());

  ASSERT_TRUE(a.freeze()) << a.error();
  std::atomic<bool> a_returned{false};
  Reply<v1::ActivateFleetBehaviorResponse> ra;
  const auto a_sent = SteadyClock::now();
  double a_took_s = 0;
  std::thread caller([&] {
    ra = client_->activate("robot-a", "WAIT", R"({"duration_s": 0.05})");
    a_took_s = std::chrono::duration<double>(SteadyClock::now() - a_sent).count();
    a_returned = true;
  });
  std::this_thread::sleep_for(milliseconds(300));  // robot-a's plan is under way
  EXPECT_FALSE(a_returned) << "robot-a's system is stopped: its call cannot have been answered";

  const auto b_sent = SteadyClock::now();
  auto rb = client_->activate("robot-b", "WAIT", R"({"duration_s": 0.05})");
  const double b_took_s = std::chrono::duration<double>(SteadyClock::now() - b_sent).count();
  // robot-b's activation returned, and applied, while robot-a's system is
  // still stopped (robot-a's call below had not returned): had it waited for
  // robot-a, it would not have returned at all. How long it took is printed,
  // not bounded: that depends on how busy the machine is.
  EXPECT_TRUE(rb.status.ok()) << describe(rb.status);
  auto b_done = watcher.waitFinished(rb.response.activation().activation_id());
  EXPECT_TRUE(b_done) << "robot-b's WAIT did not run to its end";
  if (b_done) {
    EXPECT_EQ(b_done->behavior_event().finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED);
  }
  EXPECT_FALSE(a_returned) << "robot-a's call returned while its system was stopped";

  EXPECT_TRUE(a.thaw());
  caller.join();
  ASSERT_TRUE(ra.status.ok()) << describe(ra.status);
  EXPECT_EQ(ra.response.robot_id(), "robot-a");
  auto a_done = watcher.waitFinished(ra.response.activation().activation_id());
  ASSERT_TRUE(a_done);
  EXPECT_EQ(a_done->behavior_event().finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED);
  std::printf("robot-b's activation: %.3f s while robot-a's waited; robot-a's: %.3f s\n", b_took_s,
              a_took_s);
}

}  // namespace
}  // namespace coordinator_test
