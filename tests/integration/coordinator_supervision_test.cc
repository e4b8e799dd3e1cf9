// Integration tests of the coordinator's event intake and supervision with
// real processes on loopback: a behavior system killed with SIGKILL during an
// activation, restarted, frozen with SIGSTOP (its connection stays open), or
// cut off from the coordinator by a TCP proxy (the coordinator reaches the
// system through it, as listed in --systems).

#include <gtest/gtest.h>
#include <signal.h>
#include <unistd.h>

#include <fstream>
#include <memory>
#include <set>
#include <string>
#include <vector>

#include "coordinator_test_support.h"
#include "support/server_process.h"

namespace coordinator_test {
namespace {

constexpr char kCoordinatorBinary[] = BEHAVIORLIB_COORDINATOR_PATH;
constexpr char kSystemBinary[] = BEHAVIORLIB_BASIC_QUADROTOR_BEHAVIORS_PATH;
constexpr char kSystem[] = "basic_quadrotor_behaviors";
constexpr char kRobot[] = "robot-s";

class CoordinatorSupervisionTest : public ::testing::Test {
 protected:
  void TearDown() override {
    system_.reset();
    if (coordinator_ && coordinator_->running()) {
      EXPECT_EQ(coordinator_->terminate(), 0);
    }
    if (!systems_file_.empty()) unlink(systems_file_.c_str());
  }

  void startCoordinator(std::vector<std::string> args) {
    coordinator_ = std::make_unique<support::ServerProcess>(kCoordinatorBinary, std::move(args));
    ASSERT_TRUE(coordinator_->start()) << coordinator_->error();
    client_ = std::make_unique<CoordinatorClient>(coordinator_->address());
  }

  // The behavior system of kRobot, registering with the coordinator.
  void startSystem(std::vector<std::string> extra = {}) {
    std::vector<std::string> args = {"--robot-id", kRobot, "--coordinator",
                                     coordinator_->address()};
    args.insert(args.end(), extra.begin(), extra.end());
    system_ = std::make_unique<support::ServerProcess>(kSystemBinary, args);
    ASSERT_TRUE(system_->start()) << system_->error();
  }

  // A --systems file listing kRobot's system at `address`.
  std::string writeSystemsFile(const std::string& address) {
    char path[] = "/tmp/coordinator-systems-XXXXXX";
    const int fd = mkstemp(path);
    EXPECT_GE(fd, 0);
    close(fd);
    std::ofstream out(path);
    out << "systems:\n  - robot_id: " << kRobot << "\n    address: " << address << "\n";
    systems_file_ = path;
    return path;
  }

  std::string activateWait(double duration_s) {
    auto r =
        client_->activate(kRobot, "WAIT", "{\"duration_s\": " + std::to_string(duration_s) + "}");
    EXPECT_TRUE(r.status.ok()) << describe(r.status);
    return r.response.activation().activation_id();
  }

  std::unique_ptr<support::ServerProcess> coordinator_;
  std::unique_ptr<CoordinatorClient> client_;
  std::unique_ptr<support::ServerProcess> system_;
  std::string systems_file_;
};

TEST_F(CoordinatorSupervisionTest, KilledSystemGivesProcessFailureWithinTwoSecondsThenComesBack) {
  startCoordinator({});  // default grace period: 1 s
  startSystem();
  ASSERT_TRUE(client_->waitForSystem(kRobot, v1::SYSTEM_STATE_UP));
  const std::string old_incarnation = client_->system(kRobot)->incarnation();
  FleetWatcher watcher(coordinator_->address(), FleetWatcher::request(0, "", {}, {"WAIT"}));
  ASSERT_TRUE(watcher.start());
  const std::string id = activateWait(60);
  ASSERT_TRUE(watcher.waitActivated(id));

  system_->kill();  // SIGKILL: no INTERRUPTED event, no unregistration
  const auto killed = SteadyClock::now();
  auto finished = watcher.waitFinished(id, seconds(2));
  ASSERT_TRUE(finished) << "no finished event within 2 s of the kill";
  const double after_s = std::chrono::duration<double>(SteadyClock::now() - killed).count();
  const auto& f = finished->behavior_event();
  EXPECT_EQ(f.finished().cause(), v1::TERMINATION_CAUSE_PROCESS_FAILURE);
  EXPECT_TRUE(finished->synthesized());
  EXPECT_EQ(f.robot_id(), kRobot);
  EXPECT_EQ(f.system(), kSystem);
  EXPECT_EQ(f.behavior(), "WAIT");
  EXPECT_EQ(f.incarnation(), old_incarnation);
  EXPECT_EQ(f.finished().parameters().fields().at("duration_s").number_value(), 60);
  const std::string& message = f.finished().message();
  EXPECT_NE(message.find(kSystem), std::string::npos) << message;
  EXPECT_NE(message.find(kRobot), std::string::npos) << message;
  EXPECT_NE(message.find("health check"), std::string::npos) << message;
  std::printf("PROCESS_FAILURE reached the subscriber %.2f s after SIGKILL\n", after_s);

  auto info = client_->system(kRobot);
  ASSERT_TRUE(info);
  EXPECT_EQ(info->state(), v1::SYSTEM_STATE_DOWN);
  auto refused = client_->activate(kRobot, "WAIT", R"({"duration_s": 1})");
  EXPECT_EQ(refused.status.error_code(), grpc::StatusCode::UNAVAILABLE) << describe(refused.status);
  EXPECT_NE(refused.status.error_message().find(kSystem), std::string::npos)
      << describe(refused.status);
  auto listed = client_->listBehaviors(kRobot, "WAIT");
  ASSERT_EQ(listed.response.behaviors_size(), 1);
  EXPECT_EQ(listed.response.behaviors(0).system_state(), v1::SYSTEM_STATE_DOWN);

  // A new process (new incarnation, new port) registers and is usable at once.
  startSystem();
  ASSERT_TRUE(waitUntil(
      [&] {
        auto s = client_->system(kRobot);
        return s && s->state() == v1::SYSTEM_STATE_UP && s->incarnation() != old_incarnation;
      },
      seconds(10)))
      << "the restarted system did not come back";
  EXPECT_EQ(client_->system(kRobot)->address(), system_->address());
  const std::string next = activateWait(0.1);
  auto done = watcher.waitFinished(next);
  ASSERT_TRUE(done);
  EXPECT_EQ(done->behavior_event().finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED);
  EXPECT_FALSE(done->synthesized());

  // The killed activation got exactly one finished event.
  FleetWatcher history(coordinator_->address());
  ASSERT_TRUE(history.start());
  EXPECT_EQ(finishedCount(history.drain(), id), 1);
}

TEST_F(CoordinatorSupervisionTest, RestartWithinTheGracePeriodEndsTheOldActivationOnce) {
  // A long grace period: the restart is noticed through the new incarnation,
  // not through supervision.
  startCoordinator({"--grace-period-s", "30"});
  startSystem();
  ASSERT_TRUE(client_->waitForSystem(kRobot, v1::SYSTEM_STATE_UP));
  const std::string old_incarnation = client_->system(kRobot)->incarnation();
  const int port = system_->grpcPort();
  FleetWatcher watcher(coordinator_->address());
  ASSERT_TRUE(watcher.start());
  const std::string id = activateWait(60);
  ASSERT_TRUE(watcher.waitActivated(id));

  system_->kill();
  startSystem({"--listen", "127.0.0.1:" + std::to_string(port)});
  auto finished = watcher.waitFinished(id, seconds(10));
  ASSERT_TRUE(finished) << "the old activation was not ended";
  EXPECT_EQ(finished->behavior_event().finished().cause(), v1::TERMINATION_CAUSE_PROCESS_FAILURE);
  EXPECT_TRUE(finished->synthesized());
  EXPECT_NE(finished->behavior_event().finished().message().find("restarted"), std::string::npos)
      << finished->behavior_event().finished().message();
  ASSERT_TRUE(client_->waitForSystem(kRobot, v1::SYSTEM_STATE_UP, seconds(10)));
  EXPECT_NE(client_->system(kRobot)->incarnation(), old_incarnation);

  const std::string next = activateWait(0.05);
  ASSERT_TRUE(watcher.waitFinished(next));
  FleetWatcher history(coordinator_->address());
  ASSERT_TRUE(history.start());
  auto all = history.drain();
  EXPECT_EQ(finishedCount(all, id), 1);
  EXPECT_EQ(finishedCount(all, next), 1);
}

TEST_F(CoordinatorSupervisionTest, AfterANetworkCutTheCoordinatorResumesWithEachEventOnce) {
  // The coordinator reaches the system only through the proxy; the test
  // drives the system directly while the proxy is cut.
  system_ = std::make_unique<support::ServerProcess>(
      kSystemBinary, std::vector<std::string>{"--robot-id", kRobot});
  ASSERT_TRUE(system_->start()) << system_->error();
  TcpProxy proxy(system_->grpcPort());
  startCoordinator({"--systems", writeSystemsFile(proxy.address()), "--grace-period-s", "30"});
  ASSERT_TRUE(client_->waitForSystem(kRobot, v1::SYSTEM_STATE_UP));
  FleetWatcher watcher(coordinator_->address(), FleetWatcher::request(0, "", {}, {"WAIT"}));
  ASSERT_TRUE(watcher.start());
  SystemClient direct(system_->address());

  auto runDirect = [&](double duration_s) {
    auto r = direct.activate("WAIT", "{\"duration_s\": " + std::to_string(duration_s) + "}");
    EXPECT_TRUE(r.status.ok()) << describe(r.status);
    EXPECT_TRUE(
        waitUntil([&] { return !direct.checkActivation("WAIT").response.active(); }, seconds(5)));
    return r.response.activation_id();
  };
  const std::string before = runDirect(0.05);
  ASSERT_TRUE(watcher.waitFinished(before));

  proxy.cut();
  ASSERT_TRUE(client_->waitForSystem(kRobot, v1::SYSTEM_STATE_RECONNECTING, seconds(5)));
  const std::string during1 = runDirect(0.05);
  const std::string during2 = runDirect(0.05);
  EXPECT_FALSE(watcher.nextEvent(milliseconds(200))) << "nothing gets through the cut";
  proxy.restore();
  ASSERT_TRUE(client_->waitForSystem(kRobot, v1::SYSTEM_STATE_UP, seconds(10)));
  const std::string after = runDirect(0.05);
  ASSERT_TRUE(watcher.waitFinished(after, seconds(5)));

  // Every event of the system, in its own order, exactly once.
  FleetWatcher history(coordinator_->address(), FleetWatcher::request(0, "", {}, {"WAIT"}));
  ASSERT_TRUE(history.start());
  auto events = behaviorEvents(history.drain());
  ASSERT_EQ(events.size(), 8u) << "4 activations, activated + finished each";
  for (size_t i = 0; i < events.size(); ++i) {
    EXPECT_EQ(events[i].seq(), i + 1) << events[i].ShortDebugString();
    EXPECT_EQ(events[i].has_activated(), i % 2 == 0);
  }
  EXPECT_EQ(events[2].activation_id(), during1);
  EXPECT_EQ(events[4].activation_id(), during2);
  for (const auto& e : events) {
    if (e.has_finished()) {
      EXPECT_EQ(e.finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED);
    }
  }
  const std::string metrics = support::httpGet(coordinator_->metricsPort(), "/metrics");
  EXPECT_GE(metricValue(metrics, "behaviorlib_coordinator_stream_reconnects_total").value_or(0),
            1.0)
      << metrics;
  EXPECT_EQ(metricValue(metrics, "behaviorlib_coordinator_events_synthesized_total"), 0.0)
      << metrics;
}

TEST_F(CoordinatorSupervisionTest, AnOutageLongerThanTheGraceFailsTheActivationOnceAndEndsIt) {
  system_ = std::make_unique<support::ServerProcess>(
      kSystemBinary, std::vector<std::string>{"--robot-id", kRobot});
  ASSERT_TRUE(system_->start()) << system_->error();
  TcpProxy proxy(system_->grpcPort());
  startCoordinator({"--systems", writeSystemsFile(proxy.address()), "--grace-period-s", "0.5"});
  ASSERT_TRUE(client_->waitForSystem(kRobot, v1::SYSTEM_STATE_UP));
  FleetWatcher watcher(coordinator_->address(), FleetWatcher::request(0, "", {}, {"WAIT"}));
  ASSERT_TRUE(watcher.start());
  const std::string id = activateWait(60);
  ASSERT_TRUE(watcher.waitActivated(id));

  proxy.cut();
  auto failed = watcher.waitFinished(id, seconds(5));
  ASSERT_TRUE(failed);
  EXPECT_EQ(failed->behavior_event().finished().cause(), v1::TERMINATION_CAUSE_PROCESS_FAILURE);
  EXPECT_TRUE(failed->synthesized());
  ASSERT_TRUE(client_->waitForSystem(kRobot, v1::SYSTEM_STATE_DOWN, seconds(5)));
  // The process never stopped: WAIT still runs there.
  SystemClient direct(system_->address());
  EXPECT_TRUE(direct.checkActivation("WAIT").response.active());

  proxy.restore();
  ASSERT_TRUE(client_->waitForSystem(kRobot, v1::SYSTEM_STATE_UP, seconds(10)));
  // The coordinator reported it finished, so it ends it there too.
  EXPECT_TRUE(
      waitUntil([&] { return !direct.checkActivation("WAIT").response.active(); }, seconds(5)))
      << "the activation reported failed is still running on the system";
  EXPECT_FALSE(watcher.nextEvent(milliseconds(500))) << "no second finished event";
  FleetWatcher history(coordinator_->address());
  ASSERT_TRUE(history.start());
  EXPECT_EQ(finishedCount(history.drain(), id), 1);

  // And the system is usable again through the coordinator.
  const std::string next = activateWait(0.05);
  auto done = watcher.waitFinished(next);
  ASSERT_TRUE(done);
  EXPECT_EQ(done->behavior_event().finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED);
}

TEST_F(CoordinatorSupervisionTest, FrozenSystemGivesProcessFailureWithinThreeSecondsThenIsUsable) {
  startCoordinator({});  // default grace period (1 s) and heartbeat interval (1 s)
  startSystem();
  ASSERT_TRUE(client_->waitForSystem(kRobot, v1::SYSTEM_STATE_UP));
  const std::string incarnation = client_->system(kRobot)->incarnation();
  // Two subscribers: one filtered to WAIT, one for everything.
  FleetWatcher watcher(coordinator_->address(), FleetWatcher::request(0, "", {}, {"WAIT"}));
  ASSERT_TRUE(watcher.start());
  FleetWatcher all(coordinator_->address());
  ASSERT_TRUE(all.start());
  const std::string id = activateWait(60);
  ASSERT_TRUE(watcher.waitActivated(id));
  ASSERT_TRUE(all.waitActivated(id));

  // SIGSTOP: the process keeps its TCP connections open, so the event
  // stream never breaks; only missed answers tell.
  const pid_t pid = system_->pid();
  ASSERT_TRUE(system_->freeze()) << system_->error();
  const auto stopped = SteadyClock::now();
  struct Resume {
    pid_t pid;
    bool done = false;
    void operator()() {
      if (!done) ::kill(pid, SIGCONT);
      done = true;
    }
    ~Resume() { (*this)(); }
  } resume{pid};

  auto finished = watcher.waitFinished(id, seconds(3));
  ASSERT_TRUE(finished) << "no finished event within 3 s of SIGSTOP";
  const double after_s = std::chrono::duration<double>(SteadyClock::now() - stopped).count();
  const auto& f = finished->behavior_event();
  EXPECT_EQ(f.finished().cause(), v1::TERMINATION_CAUSE_PROCESS_FAILURE);
  EXPECT_TRUE(finished->synthesized());
  EXPECT_EQ(f.robot_id(), kRobot);
  EXPECT_EQ(f.system(), kSystem);
  EXPECT_EQ(f.incarnation(), incarnation);
  const std::string& message = f.finished().message();
  EXPECT_NE(message.find("stopped answering"), std::string::npos) << message;
  EXPECT_NE(message.find(kSystem), std::string::npos) << message;
  std::printf("PROCESS_FAILURE reached the subscriber %.2f s after SIGSTOP: %s\n", after_s,
              message.c_str());
  auto other = all.waitFinished(id, seconds(1));
  ASSERT_TRUE(other) << "the second subscriber did not get the finished event";
  EXPECT_EQ(other->behavior_event().finished().cause(), v1::TERMINATION_CAUSE_PROCESS_FAILURE);

  auto info = client_->system(kRobot);
  ASSERT_TRUE(info);
  EXPECT_EQ(info->state(), v1::SYSTEM_STATE_DOWN);
  // Calls are refused at once instead of blocking for their deadline.
  const auto call_start = SteadyClock::now();
  auto refused = client_->activate(kRobot, "WAIT", R"({"duration_s": 1})");
  EXPECT_EQ(refused.status.error_code(), grpc::StatusCode::UNAVAILABLE) << describe(refused.status);
  EXPECT_LT(SteadyClock::now() - call_start, milliseconds(500));

  // SIGCONT: the same incarnation comes back, the coordinator reconnects
  // (resuming by seq) and ends there the activation it reported failed.
  resume();
  ASSERT_TRUE(client_->waitForSystem(kRobot, v1::SYSTEM_STATE_UP, seconds(10)))
      << "the resumed system did not come back";
  EXPECT_EQ(client_->system(kRobot)->incarnation(), incarnation);
  SystemClient direct(system_->address());
  EXPECT_TRUE(
      waitUntil([&] { return !direct.checkActivation("WAIT").response.active(); }, seconds(5)))
      << "the activation reported failed is still running on the system";

  // Usable again through the coordinator.
  std::string next;
  ASSERT_TRUE(waitUntil(
      [&] {
        auto r = client_->activate(kRobot, "WAIT", R"({"duration_s": 0.2})");
        if (!r.status.ok()) return false;
        next = r.response.activation().activation_id();
        return true;
      },
      seconds(10)))
      << "the resumed system cannot be activated through the coordinator";
  auto done = watcher.waitFinished(next, seconds(5));
  ASSERT_TRUE(done);
  EXPECT_EQ(done->behavior_event().finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED);
  EXPECT_FALSE(done->synthesized());

  // No activation got two finished events.
  FleetWatcher history(coordinator_->address());
  ASSERT_TRUE(history.start());
  const auto events = history.drain();
  EXPECT_EQ(finishedCount(events, id), 1);
  EXPECT_EQ(finishedCount(events, next), 1);
  std::set<std::string> finished_ids;
  for (const auto& e : behaviorEvents(events)) {
    if (e.has_finished()) {
      EXPECT_TRUE(finished_ids.insert(e.activation_id()).second)
          << "two finished events for " << e.activation_id();
    }
  }
}

}  // namespace
}  // namespace coordinator_test
