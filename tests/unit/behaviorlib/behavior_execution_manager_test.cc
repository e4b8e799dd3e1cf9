#include "behaviorlib/behavior_execution_manager.h"

#include <gmock/gmock.h>
#include <google/protobuf/struct.pb.h>
#include <gtest/gtest.h>

#include <condition_variable>
#include <future>
#include <mutex>
#include <stdexcept>

#include "behaviorlib/behavior_host.h"
#include "behaviorlib/clock.h"
#include "behaviorlib/errors/status_details.h"
#include "test_behaviors.h"
#include "test_parameters.pb.h"

namespace behaviorlib {
namespace {

using std::chrono::milliseconds;
using std::chrono::seconds;
using ::testing::ElementsAre;
using testing::EventCollector;
using testing::eventually;
using ::testing::HasSubstr;
using testing::ScriptedBehavior;
using testing::waitParams;

class BehaviorExecutionManagerTest : public ::testing::Test {
 protected:
  ScriptedBehavior& start(BehaviorOptions options = {}) {
    auto behavior = std::make_unique<ScriptedBehavior>("SCRIPTED", options);
    behavior_ = behavior.get();
    host_.add(std::move(behavior));
    EXPECT_TRUE(host_.start().ok());
    return *behavior_;
  }
  // The engine that holds the behavior start() made.
  BehaviorExecutionManager& engine() { return detail::engineOf(*behavior_); }
  // Activates and waits for the first tick's onExecute, which runs right
  // after onActivate without any clock advance.
  v1::ActivateResponse activate(double duration_s = 1.0, std::string request_id = {}) {
    const int executed = behavior_->count("onExecute");
    auto r = engine().activateAndWait(waitParams(duration_s), std::move(request_id));
    EXPECT_TRUE(r.ok()) << r.status();
    EXPECT_TRUE(eventually([&] { return behavior_->count("onExecute") > executed; }));
    return r.ok() ? *r : v1::ActivateResponse();
  }
  // Advances fake time by one 100 Hz period and waits for the tick.
  void tick() {
    const int before = behavior_->count("checkProcesses");
    clock_.advance(milliseconds(10));
    ASSERT_TRUE(eventually([&] { return behavior_->count("checkProcesses") > before; }));
  }

  FakeClock clock_;
  BehaviorHost host_{testing::hostOptions("drone1", "test"), clock_};
  EventCollector events_{host_.events()};
  ScriptedBehavior* behavior_ = nullptr;
};

// A behavior's name comes from its parameters' declaration in the proto.
class DeclaredWait final : public Behavior<v1::WaitParameters> {};
class Undeclared final : public Behavior<google::protobuf::Struct> {};

// The engine is the library's own: a behavior's class has none of its host
// interface, threads or queues, and no way to reach them.
template <class T>
concept ReachesTheEngine = requires(T& behavior) {
  behavior.activateAndWait(nullptr);
  behavior.watchdogCheck(std::chrono::steady_clock::now());
  behavior.execute();
};
static_assert(!std::is_base_of_v<BehaviorExecutionManager, DeclaredWait>);
static_assert(!ReachesTheEngine<DeclaredWait>);
static_assert(ReachesTheEngine<BehaviorExecutionManager>);

TEST(BehaviorEngineTest, AnEngineHoldsOneBehaviorAndHelpersNeedIt) {
  auto owned = std::make_unique<DeclaredWait>();
  DeclaredWait& behavior = *owned;
  try {
    detail::engineOf(behavior);
    ADD_FAILURE() << "a behavior no engine holds gave an engine";
  } catch (const std::logic_error& e) {
    EXPECT_THAT(e.what(), HasSubstr("no engine holds it yet"));
  }
  BehaviorExecutionManager engine(std::move(owned));
  EXPECT_EQ(&detail::engineOf(behavior), &engine);
  EXPECT_EQ(&engine.behavior(), &behavior);
  EXPECT_EQ(engine.name(), "WAIT");
  EXPECT_THROW(BehaviorExecutionManager(std::unique_ptr<BehaviorBase>()), std::logic_error);
}

TEST(BehaviorDeclarationTest, TheNameComesFromTheParametersDeclaration) {
  EXPECT_EQ(DeclaredWait().name(), "WAIT");
  EXPECT_EQ(declaredBehaviorName(v1::WaitParameters::descriptor()), "WAIT");
  EXPECT_EQ(declaredBehaviorName(google::protobuf::Struct::descriptor()), "");
  try {
    Undeclared undeclared;
    ADD_FAILURE() << "a behavior without a declaration was built as " << undeclared.name();
  } catch (const std::logic_error& e) {
    EXPECT_THAT(e.what(), ::testing::HasSubstr("google.protobuf.Struct declares no behavior"));
  }
}

TEST_F(BehaviorExecutionManagerTest, FirstTickRunsAtActivationWithoutWaitingForTheClock) {
  auto& b = start();
  activate();
  // Time never advanced: the first tick must still happen.
  ASSERT_TRUE(eventually([&] { return b.count("onExecute") == 1; }));
  EXPECT_THAT(b.calls(), ElementsAre("checkSituation", "onActivate", "checkProcesses",
                                     "checkSituation", "checkGoal", "checkProgress", "onExecute"));
  std::this_thread::sleep_for(milliseconds(30));
  EXPECT_EQ(b.count("onExecute"), 1) << "no further tick until the clock advances";
  tick();
  EXPECT_TRUE(eventually([&] { return b.count("onExecute") == 2; }));
}

TEST_F(BehaviorExecutionManagerTest, CheckProcessesRunsEveryTickBeforeTheGoal) {
  auto& b = start();
  activate();
  tick();
  tick();
  EXPECT_EQ(b.count("checkProcesses"), 3);
  // tick() returns once checkProcesses has run; checkGoal follows it on the
  // worker thread.
  EXPECT_TRUE(eventually([&] { return b.count("checkGoal") == 3; })) << b.count("checkGoal");
}

TEST_F(BehaviorExecutionManagerTest, InactiveBehaviorDoesNotTick) {
  auto& b = start();
  clock_.advance(seconds(1));
  std::this_thread::sleep_for(milliseconds(20));
  EXPECT_EQ(b.count("checkProcesses"), 0);
}

// ---- The time gate (deterministic mode) ---------------------------------------

// A before_command gate that holds commands while closed.
class ClosableGate {
 public:
  void operator()() {
    std::unique_lock lock(mutex_);
    ++waiting_;
    cv_.notify_all();
    cv_.wait(lock, [this] { return open_; });
    --waiting_;
  }
  void setOpen(bool open) {
    {
      std::lock_guard lock(mutex_);
      open_ = open;
    }
    cv_.notify_all();
  }
  bool waitForWaiter() {
    std::unique_lock lock(mutex_);
    return cv_.wait_for(lock, seconds(5), [this] { return waiting_ > 0; });
  }

 private:
  std::mutex mutex_;
  std::condition_variable cv_;
  bool open_ = true;
  int waiting_ = 0;
};

TEST(BehaviorTimeGateTest, ACommandHeldAtTheGateIsCaughtUpButNotIdleAndRunsAtTheLaterTime) {
  FakeClock clock;
  ClosableGate gate;
  BehaviorHostOptions options = testing::hostOptions("drone1", "test");
  options.before_command = [&gate] { gate(); };
  BehaviorHost host(options, clock);
  auto owned = std::make_unique<ScriptedBehavior>("SCRIPTED");
  ScriptedBehavior& b = *owned;
  host.add(std::move(owned));
  ASSERT_TRUE(host.start().ok());                        // configuring passes the open gate
  EXPECT_TRUE(eventually([&] { return host.idle(); }));  // once the configure command returned

  // onActivate blocks until released: a running command is neither caught
  // up nor idle.
  std::mutex m;
  std::condition_variable cv;
  bool in_activate = false, release = false;
  TimePoint activated_at{};
  b.on_activate = [&] {
    std::unique_lock lock(m);
    activated_at = clock.now();
    in_activate = true;
    cv.notify_all();
    cv.wait(lock, [&] { return release; });
    return absl::OkStatus();
  };

  gate.setOpen(false);
  std::promise<absl::StatusOr<v1::ActivateResponse>> reply;
  detail::engineOf(b).activate(
      waitParams(10.0), "",
      [&reply](absl::StatusOr<v1::ActivateResponse> r) { reply.set_value(std::move(r)); });
  ASSERT_TRUE(gate.waitForWaiter());
  // Held at the gate: it waits for time, so the system is caught up with
  // any time (the follower may apply the next grant), but it is not idle
  // (the simulator must wait for it from the next grant on).
  const TimePoint t0 = clock.now();
  EXPECT_TRUE(host.caughtUp(t0 + seconds(1)));
  EXPECT_FALSE(host.idle());
  EXPECT_EQ(b.count("onActivate"), 0);

  // The grant moves the clock, then the gate opens: the activation starts at
  // the new time.
  clock.advance(milliseconds(700));
  gate.setOpen(true);
  {
    std::unique_lock lock(m);
    ASSERT_TRUE(cv.wait_for(lock, seconds(5), [&] { return in_activate; }));
  }
  EXPECT_EQ(activated_at, t0 + milliseconds(700));
  EXPECT_FALSE(host.caughtUp(clock.now())) << "time must not move under a running command";
  EXPECT_FALSE(host.idle());
  {
    std::lock_guard lock(m);
    release = true;
  }
  cv.notify_all();
  auto future = reply.get_future();
  ASSERT_EQ(future.wait_for(seconds(5)), std::future_status::ready);
  EXPECT_TRUE(future.get().ok());
  EXPECT_TRUE(eventually([&] { return host.caughtUp(clock.now()); }));
  EXPECT_FALSE(host.idle()) << "active";
  host.stop();
}

// ---- Every termination cause ----------------------------------------------

struct CauseCase {
  std::string name;
  v1::TerminationCause cause;
  std::function<void(ScriptedBehavior&)> script;
  std::string message;
};

class TerminationCauseTest : public BehaviorExecutionManagerTest,
                             public ::testing::WithParamInterface<CauseCase> {};

TEST_P(TerminationCauseTest, EndsActivationWithCauseThenDeactivates) {
  BehaviorOptions options;
  options.maximum_execution_time = seconds(1);
  auto& b = start(options);
  const auto& param = GetParam();
  // Scripts trigger from the second tick on, after a successful activation.
  param.script(b);
  const auto activation = activate();
  if (param.cause == v1::TERMINATION_CAUSE_INTERRUPTED) {
    ASSERT_TRUE(engine().deactivateAndWait(activation.activation_id()).ok());
  } else if (param.cause == v1::TERMINATION_CAUSE_TIME_OUT) {
    clock_.advance(milliseconds(1500));
  } else {
    tick();
  }
  const auto finished = events_.waitFinished();
  ASSERT_TRUE(finished.has_finished());
  EXPECT_EQ(finished.finished().cause(), param.cause);
  EXPECT_THAT(finished.finished().message(), HasSubstr(param.message));
  EXPECT_EQ(finished.activation_id(), activation.activation_id());
  EXPECT_EQ(finished.behavior(), "SCRIPTED");
  EXPECT_EQ(finished.finished().parameters().fields().at("duration_s").number_value(), 1.0);
  EXPECT_EQ(b.count("onDeactivate"), 1);
  // onDeactivate runs before the event is emitted.
  EXPECT_EQ(b.calls().back(), "onDeactivate");
  EXPECT_EQ(engine().state(), v1::BEHAVIOR_STATE_INACTIVE);
  EXPECT_FALSE(engine().checkActivation().active());
}

int ticksSeen(ScriptedBehavior& b) { return b.count("onExecute"); }

INSTANTIATE_TEST_SUITE_P(
    AllCauses, TerminationCauseTest,
    ::testing::Values(CauseCase{"GoalAchieved", v1::TERMINATION_CAUSE_GOAL_ACHIEVED,
                                [](ScriptedBehavior& b) {
                                  b.goal = [&b] {
                                    return ticksSeen(b) >= 1 ? Verdict::finish("reached")
                                                             : Verdict::keepGoing();
                                  };
                                },
                                "reached"},
                      CauseCase{"TimeOut", v1::TERMINATION_CAUSE_TIME_OUT, [](ScriptedBehavior&) {},
                                "maximum_execution_time"},
                      CauseCase{"WrongProgress", v1::TERMINATION_CAUSE_WRONG_PROGRESS,
                                [](ScriptedBehavior& b) {
                                  b.progress = [&b] {
                                    return ticksSeen(b) >= 1 ? Verdict::finish("moving away")
                                                             : Verdict::keepGoing();
                                  };
                                },
                                "moving away"},
                      CauseCase{"SituationChange", v1::TERMINATION_CAUSE_SITUATION_CHANGE,
                                [](ScriptedBehavior& b) {
                                  b.situation = [&b] {
                                    return ticksSeen(b) >= 1
                                               ? Situation::infeasible(
                                                     v1::SITUATION_REASON_UNSPECIFIED, "too dark")
                                               : Situation::ok();
                                  };
                                },
                                "too dark"},
                      CauseCase{"ProcessFailure", v1::TERMINATION_CAUSE_PROCESS_FAILURE,
                                [](ScriptedBehavior& b) {
                                  b.processes = [&b] {
                                    return ticksSeen(b) >= 1 ? Verdict::finish("planner died")
                                                             : Verdict::keepGoing();
                                  };
                                },
                                "planner died"},
                      CauseCase{"ProcessFailureFromException",
                                v1::TERMINATION_CAUSE_PROCESS_FAILURE,
                                [](ScriptedBehavior& b) {
                                  b.on_execute = [&b] {
                                    if (ticksSeen(b) >= 2)
                                      throw std::runtime_error("division by zero");
                                  };
                                },
                                "onExecute threw: division by zero"},
                      CauseCase{"Interrupted", v1::TERMINATION_CAUSE_INTERRUPTED,
                                [](ScriptedBehavior&) {}, "deactivation requested"}),
    [](const auto& info) { return info.param.name; });

// ---- Lifecycle errors ------------------------------------------------------

TEST_F(BehaviorExecutionManagerTest, RejectsInvalidParametersNamingTheField) {
  auto& b = start();
  auto missing = engine().activateAndWait(std::make_unique<v1::WaitParameters>());
  EXPECT_EQ(missing.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(missing.status().message(), HasSubstr("duration_s"));
  EXPECT_EQ(errors::reasonOf(missing.status()), "PARAMETER_INVALID");
  auto negative = engine().activateAndWait(waitParams(-1));
  EXPECT_EQ(negative.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(negative.status().message(), HasSubstr("duration_s"));
  // Machine-readable: the reason, the behavior, and the request's field.
  EXPECT_EQ(errors::reasonOf(negative.status()), "PARAMETER_OUT_OF_RANGE");
  EXPECT_EQ(errors::errorInfo(negative.status())->metadata().at("behavior"), "SCRIPTED");
  ASSERT_TRUE(errors::badRequest(negative.status()).has_value());
  EXPECT_EQ(errors::badRequest(negative.status())->field_violations(0).field(),
            "parameters.duration_s");
  EXPECT_EQ(b.count("onActivate"), 0);
}

TEST_F(BehaviorExecutionManagerTest, RefusesSecondActivationWhileActive) {
  start();
  activate();
  auto again = engine().activateAndWait(waitParams(2));
  EXPECT_EQ(again.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(again.status().message(), HasSubstr("already active"));
  EXPECT_EQ(errors::reasonOf(again.status()), "BEHAVIOR_ALREADY_ACTIVE");
  EXPECT_FALSE(errors::errorInfo(again.status())->metadata().at("current_activation_id").empty());
}

TEST_F(BehaviorExecutionManagerTest, RefusesActivationWhenSituationIsInfeasible) {
  auto& b = start();
  b.situation = [] {
    Situation s =
        Situation::infeasible(v1::SITUATION_REASON_FLIGHT_STATE, "the robot is not flying");
    s.add(v1::SITUATION_REASON_BATTERY_LOW, "battery at 0.10");
    return s;
  };
  auto r = engine().activateAndWait(waitParams(1));
  EXPECT_EQ(r.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(r.status().message(), HasSubstr("the robot is not flying"));
  EXPECT_EQ(errors::reasonOf(r.status()), "SITUATION_NOT_SUITABLE");
  EXPECT_EQ(errors::errorInfo(r.status())->metadata().at("situation_reasons"),
            "SITUATION_REASON_FLIGHT_STATE,SITUATION_REASON_BATTERY_LOW");
  auto situation = engine().checkSituationAndWait();
  ASSERT_TRUE(situation.ok());
  EXPECT_FALSE(situation->feasible());
  EXPECT_THAT(situation->reasons(), ElementsAre("the robot is not flying", "battery at 0.10"));
  EXPECT_THAT(situation->reason_codes(),
              ElementsAre(v1::SITUATION_REASON_FLIGHT_STATE, v1::SITUATION_REASON_BATTERY_LOW));
}

TEST_F(BehaviorExecutionManagerTest, OnActivateErrorRefusesActivation) {
  auto& b = start();
  b.on_activate = [] { return absl::FailedPreconditionError("no map loaded"); };
  auto r = engine().activateAndWait(waitParams(1));
  EXPECT_EQ(r.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(r.status().message(), HasSubstr("no map loaded"));
  EXPECT_EQ(engine().state(), v1::BEHAVIOR_STATE_INACTIVE);
  EXPECT_EQ(events_.countKind(v1::BehaviorEvent::kActivated), 0);
}

TEST_F(BehaviorExecutionManagerTest, DeactivateWhenInactiveIsFailedPrecondition) {
  start();
  auto r = engine().deactivateAndWait();
  EXPECT_EQ(r.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_EQ(engine().pauseAndWait().status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_EQ(engine().resumeAndWait().status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_EQ(engine().modifyAndWait(waitParams(2)).status().code(),
            absl::StatusCode::kFailedPrecondition);
}

TEST_F(BehaviorExecutionManagerTest, SameRequestIdReturnsTheSameActivation) {
  auto& b = start();
  const auto first = activate(1.0, "req-1");
  auto retry = engine().activateAndWait(waitParams(1.0), "req-1");
  ASSERT_TRUE(retry.ok()) << retry.status();
  EXPECT_EQ(retry->activation_id(), first.activation_id());
  EXPECT_TRUE(retry->replayed());
  EXPECT_FALSE(first.replayed());
  EXPECT_EQ(b.count("onActivate"), 1);
  EXPECT_EQ(events_.countKind(v1::BehaviorEvent::kActivated), 1);
  // A different id is a new request, refused because already active.
  EXPECT_EQ(engine().activateAndWait(waitParams(1.0), "req-2").status().code(),
            absl::StatusCode::kFailedPrecondition);
  // After the activation ended, the old id still replays (within the window).
  ASSERT_TRUE(engine().deactivateAndWait().ok());
  auto late = engine().activateAndWait(waitParams(1.0), "req-1");
  ASSERT_TRUE(late.ok());
  EXPECT_EQ(late->activation_id(), first.activation_id());
  EXPECT_EQ(engine().state(), v1::BEHAVIOR_STATE_INACTIVE);
}

TEST_F(BehaviorExecutionManagerTest, StaleActivationIdNeverStopsANewerActivation) {
  start();
  const auto old_activation = activate();
  ASSERT_TRUE(engine().deactivateAndWait(old_activation.activation_id()).ok());
  // Retrying the deactivation of a finished activation reports how it ended.
  auto retry = engine().deactivateAndWait(old_activation.activation_id());
  ASSERT_TRUE(retry.ok()) << retry.status();
  EXPECT_TRUE(retry->already_finished());
  EXPECT_EQ(retry->cause(), v1::TERMINATION_CAUSE_INTERRUPTED);

  const auto current = activate();
  ASSERT_NE(current.activation_id(), old_activation.activation_id());
  for (auto code :
       {engine().deactivateAndWait(old_activation.activation_id()).status().code(),
        engine().pauseAndWait(old_activation.activation_id()).status().code(),
        engine().resumeAndWait(old_activation.activation_id()).status().code(),
        engine().modifyAndWait(waitParams(3), old_activation.activation_id()).status().code()}) {
    EXPECT_EQ(code, absl::StatusCode::kAborted);
  }
  EXPECT_EQ(engine().checkActivation().activation_id(), current.activation_id());
  EXPECT_TRUE(engine().checkActivation().active());
}

TEST_F(BehaviorExecutionManagerTest, ABehaviorEndingThroughTheTimeOutGivesItsReason) {
  BehaviorOptions options;
  options.maximum_execution_time = seconds(1);
  auto& b = start(options);
  std::atomic<bool> give_up{true};
  b.time_out_reason = [&] { return give_up ? std::string("planning timed out 3 times") : ""; };
  activate();
  // The limit set to the active time so far ends the activation at the next
  // tick on which time has passed.
  clock_.advance(milliseconds(10));
  auto finished = events_.waitFinished();
  EXPECT_EQ(finished.finished().cause(), v1::TERMINATION_CAUSE_TIME_OUT);
  EXPECT_EQ(finished.finished().message(), "planning timed out 3 times");

  // The next activation times out on its own limit, with the library's message.
  give_up = false;
  const auto second = activate();
  clock_.advance(milliseconds(1100));
  ASSERT_TRUE(eventually([&] { return engine().state() == v1::BEHAVIOR_STATE_INACTIVE; }));
  finished = events_.waitFinished(/*skip=*/1);
  EXPECT_EQ(finished.activation_id(), second.activation_id());
  EXPECT_EQ(finished.finished().cause(), v1::TERMINATION_CAUSE_TIME_OUT);
  EXPECT_NE(finished.finished().message().find("maximum_execution_time 1"), std::string::npos)
      << finished.finished().message();
}

// ---- Pause, resume, modify -------------------------------------------------

TEST_F(BehaviorExecutionManagerTest, PauseStopsMonitoringAndTheTimeOutCountsActiveTimeOnly) {
  BehaviorOptions options;
  options.maximum_execution_time = seconds(2);
  auto& b = start(options);
  const auto activation = activate();
  clock_.advance(milliseconds(1500));
  ASSERT_TRUE(eventually([&] { return b.lastActiveTime() >= milliseconds(1500); }));
  ASSERT_TRUE(engine().pauseAndWait(activation.activation_id()).ok());
  EXPECT_EQ(engine().state(), v1::BEHAVIOR_STATE_PAUSED);
  EXPECT_EQ(engine().pauseAndWait().status().code(), absl::StatusCode::kFailedPrecondition);
  const int checks = b.count("checkProcesses");
  clock_.advance(seconds(10));
  std::this_thread::sleep_for(milliseconds(30));
  EXPECT_EQ(b.count("checkProcesses"), checks) << "no monitoring while paused";
  EXPECT_EQ(engine().state(), v1::BEHAVIOR_STATE_PAUSED) << "paused time must not time out";
  const auto paused_status = engine().checkActivation();
  EXPECT_TRUE(paused_status.active());
  EXPECT_EQ(paused_status.active_duration().seconds(), 1);

  ASSERT_TRUE(engine().resumeAndWait(activation.activation_id()).ok());
  ASSERT_TRUE(eventually([&] { return b.count("checkProcesses") > checks; }))
      << "resume ticks at once";
  clock_.advance(milliseconds(400));
  std::this_thread::sleep_for(milliseconds(20));
  EXPECT_EQ(engine().state(), v1::BEHAVIOR_STATE_ACTIVE);
  clock_.advance(milliseconds(200));
  const auto finished = events_.waitFinished();
  EXPECT_EQ(finished.finished().cause(), v1::TERMINATION_CAUSE_TIME_OUT);
  EXPECT_NEAR(finished.finished().active_duration().seconds() +
                  finished.finished().active_duration().nanos() * 1e-9,
              2.1, 0.01);
  EXPECT_EQ(b.count("onPause"), 1);
  EXPECT_EQ(b.count("onResume"), 1);
  EXPECT_EQ(events_.countKind(v1::BehaviorEvent::kPaused), 1);
  EXPECT_EQ(events_.countKind(v1::BehaviorEvent::kResumed), 1);
}

TEST_F(BehaviorExecutionManagerTest, ModifyMergesValidatesAndNotifies) {
  auto& b = start();
  // onModify gets the merged parameters typed, before they take effect.
  std::vector<std::pair<double, double>> seen;  // (new, current) duration_s
  b.on_modify = [&](const v1::WaitParameters& p) {
    seen.emplace_back(p.duration_s(), b.durationParameterNow());
    return absl::OkStatus();
  };
  const auto activation = activate(5.0);
  auto modified = engine().modifyAndWait(waitParams(7.0), activation.activation_id());
  ASSERT_TRUE(modified.ok()) << modified.status();
  ASSERT_EQ(seen.size(), 1u);
  EXPECT_EQ(seen[0].first, 7.0);
  EXPECT_EQ(seen[0].second, 5.0);
  EXPECT_EQ(modified->parameters().fields().at("duration_s").number_value(), 7.0);
  tick();
  EXPECT_TRUE(eventually([&] { return b.durationParameter() == 7.0; }));
  EXPECT_EQ(engine().checkActivation().parameters().fields().at("duration_s").number_value(), 7.0);

  auto bad = engine().modifyAndWait(waitParams(-3.0));
  EXPECT_EQ(bad.status().code(), absl::StatusCode::kInvalidArgument);
  // An empty update keeps everything.
  ASSERT_TRUE(engine().modifyAndWait(std::make_unique<v1::WaitParameters>()).ok());
  EXPECT_EQ(engine().checkActivation().parameters().fields().at("duration_s").number_value(), 7.0);

  b.on_modify = [](const v1::WaitParameters&) {
    return absl::FailedPreconditionError("cannot shorten now");
  };
  auto refused = engine().modifyAndWait(waitParams(1.0));
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(refused.status().message(), HasSubstr("cannot shorten now"));
  EXPECT_EQ(engine().checkActivation().parameters().fields().at("duration_s").number_value(), 7.0);
  EXPECT_EQ(events_.countKind(v1::BehaviorEvent::kModified), 2);
}

TEST_F(BehaviorExecutionManagerTest, PerformanceChangeEmitsSituationChanged) {
  auto& b = start();
  std::atomic<double> performance{1.0};
  b.situation = [&] { return Situation::ok(performance.load()); };
  activate();
  tick();
  performance = 0.95;  // below the 0.1 threshold
  tick();
  EXPECT_EQ(events_.countKind(v1::BehaviorEvent::kSituationChanged), 0);
  performance = 0.5;
  tick();
  ASSERT_TRUE(
      eventually([&] { return events_.countKind(v1::BehaviorEvent::kSituationChanged) == 1; }));
  for (const auto& e : events_.events()) {
    if (e.has_situation_changed()) {
      EXPECT_DOUBLE_EQ(e.situation_changed().performance_ratio(), 0.5);
    }
  }
}

// ---- Watchdog, exceptions, shutdown ----------------------------------------

TEST_F(BehaviorExecutionManagerTest, StuckOnExecuteEndsWithProcessFailureAndProcessKeepsServing) {
  BehaviorOptions options;
  options.watchdog_timeout = milliseconds(100);
  auto& b = start(options);
  std::mutex m;
  std::condition_variable cv;
  bool release = false;
  b.on_execute = [&] {
    std::unique_lock lock(m);
    cv.wait(lock, [&] { return release; });
  };
  const auto activation = activate();
  const auto finished = events_.waitFinished();
  ASSERT_TRUE(finished.has_finished());
  EXPECT_EQ(finished.finished().cause(), v1::TERMINATION_CAUSE_PROCESS_FAILURE);
  EXPECT_THAT(finished.finished().message(), HasSubstr("onExecute did not return"));
  EXPECT_EQ(engine().state(), v1::BEHAVIOR_STATE_BLOCKED);
  auto refused = engine().activateAndWait(waitParams(1), {}, milliseconds(200));
  EXPECT_FALSE(refused.ok());

  {
    std::lock_guard lock(m);
    release = true;
  }
  cv.notify_all();
  ASSERT_TRUE(eventually([&] { return engine().state() == v1::BEHAVIOR_STATE_INACTIVE; }));
  EXPECT_EQ(b.count("onDeactivate"), 1);
  b.on_execute = [] {};
  activate();
  EXPECT_EQ(engine().state(), v1::BEHAVIOR_STATE_ACTIVE);
  EXPECT_EQ(events_.countKind(v1::BehaviorEvent::kFinished), 1);
}

class RecordingObserver final : public BehaviorObserver {
 public:
  std::atomic<int> activated{0}, finished{0}, first_execute{0}, monitoring{0}, cpu_above_wall{0};
  std::atomic<int> blocked{0}, unblocked{0};
  void onActivated(std::chrono::nanoseconds) override { ++activated; }
  void onFirstExecute(std::chrono::nanoseconds) override { ++first_execute; }
  void onFinished(v1::TerminationCause) override { ++finished; }
  void onMonitoring(std::chrono::nanoseconds wall, std::chrono::nanoseconds cpu) override {
    ++monitoring;
    if (cpu > wall + std::chrono::milliseconds(1)) ++cpu_above_wall;
  }
  void onBlocked(bool b) override { ++(b ? blocked : unblocked); }
};

TEST_F(BehaviorExecutionManagerTest, ObserverSeesActivationTicksBlockAndRecovery) {
  RecordingObserver* observer = nullptr;
  host_.setObserverFactory([&](const BehaviorExecutionManager&) {
    auto o = std::make_unique<RecordingObserver>();
    observer = o.get();
    return o;
  });
  BehaviorOptions options;
  options.watchdog_timeout = milliseconds(100);
  auto& b = start(options);
  ASSERT_NE(observer, nullptr);
  std::atomic<bool> stuck{false};
  b.on_execute = [&] {
    while (stuck) std::this_thread::sleep_for(milliseconds(1));
  };
  activate();
  EXPECT_EQ(observer->activated, 1);
  EXPECT_EQ(observer->first_execute, 1);
  EXPECT_GE(observer->monitoring, 1);
  EXPECT_EQ(observer->cpu_above_wall, 0) << "a thread cannot spend more CPU than wall time";
  stuck = true;
  tick();
  ASSERT_TRUE(eventually([&] { return observer->blocked == 1; }));
  EXPECT_EQ(observer->finished, 1);
  EXPECT_EQ(observer->unblocked, 0);
  stuck = false;
  ASSERT_TRUE(eventually([&] { return observer->unblocked == 1; }));
  EXPECT_EQ(engine().state(), v1::BEHAVIOR_STATE_INACTIVE);
}

TEST_F(BehaviorExecutionManagerTest, HookThatThrowsWhilePausingEndsTheActivation) {
  auto& b = start();
  b.on_pause = [] { throw std::runtime_error("brake stuck"); };
  const auto activation = activate();
  auto paused = engine().pauseAndWait(activation.activation_id());
  EXPECT_EQ(paused.status().code(), absl::StatusCode::kAborted);
  EXPECT_THAT(paused.status().message(), HasSubstr("onPause threw: brake stuck"));
  const auto finished = events_.waitFinished();
  EXPECT_EQ(finished.finished().cause(), v1::TERMINATION_CAUSE_PROCESS_FAILURE);
  EXPECT_EQ(engine().state(), v1::BEHAVIOR_STATE_INACTIVE);
  EXPECT_EQ(events_.countKind(v1::BehaviorEvent::kPaused), 0);
}

TEST_F(BehaviorExecutionManagerTest, ExceptionInMonitoringIsProcessFailure) {
  auto& b = start();
  b.goal = []() -> Verdict { throw std::out_of_range("bad index"); };
  ASSERT_TRUE(engine().activateAndWait(waitParams(1)).ok());
  const auto finished = events_.waitFinished();
  EXPECT_EQ(finished.finished().cause(), v1::TERMINATION_CAUSE_PROCESS_FAILURE);
  EXPECT_THAT(finished.finished().message(), HasSubstr("checkGoal threw: bad index"));
}

TEST_F(BehaviorExecutionManagerTest, HostStopInterruptsActiveBehaviors) {
  auto& b = start();
  const auto activation = activate();
  host_.stop();
  const auto finished = events_.waitFinished();
  EXPECT_EQ(finished.finished().cause(), v1::TERMINATION_CAUSE_INTERRUPTED);
  EXPECT_EQ(finished.activation_id(), activation.activation_id());
  EXPECT_EQ(b.count("onDeactivate"), 1);
  // Calls after stop get an answer, not a hang.
  EXPECT_EQ(engine().activateAndWait(waitParams(1)).status().code(),
            absl::StatusCode::kUnavailable);
}

TEST_F(BehaviorExecutionManagerTest, EventsCarryHostIdentityAndIncreasingSeq) {
  start();
  const auto activation = activate();
  ASSERT_TRUE(engine().deactivateAndWait().ok());
  const auto events = events_.events();
  ASSERT_EQ(events.size(), 2u);
  EXPECT_TRUE(events[0].has_activated());
  EXPECT_TRUE(events[1].has_finished());
  EXPECT_EQ(events[1].seq(), events[0].seq() + 1);
  for (const auto& e : events) {
    EXPECT_EQ(e.robot_id(), "drone1");
    EXPECT_EQ(e.system(), "test");
    EXPECT_EQ(e.incarnation(), host_.events().incarnation());
    EXPECT_EQ(e.activation_id(), activation.activation_id());
    EXPECT_EQ(e.time().seconds(), 3600);  // the fake clock's start
  }
}

TEST(BehaviorConfigTest, ConfigOverridesOptionsAndRejectsBadValues) {
  FakeClock clock;
  BehaviorHost host(testing::hostOptions("r", "s"), clock);
  auto behavior = std::make_unique<ScriptedBehavior>();
  host.add(std::move(behavior));
  YAML::Node config = YAML::Load(
      "behaviors:\n  SCRIPTED:\n    frequency_hz: 20\n    maximum_execution_time_s: 3.5\n");
  ASSERT_TRUE(host.start(config).ok());
  EXPECT_EQ(host.find("SCRIPTED")->options().frequency_hz, 20.0);
  EXPECT_EQ(host.find("SCRIPTED")->options().maximum_execution_time, milliseconds(3500));
  host.stop();

  BehaviorHost bad_host(testing::hostOptions("r", "s"), clock);
  bad_host.add(std::make_unique<ScriptedBehavior>());
  auto status = bad_host.start(YAML::Load("behaviors:\n  SCRIPTED:\n    frequency_hz: -1\n"));
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(status.message(), HasSubstr("frequency_hz"));
}

// A behavior with a configuration message (decision 45): the test's
// SectionConfig, whose keys it keeps.
class ConfiguredBehavior final : public Behavior<v1::WaitParameters, test::SectionConfig> {
 public:
  ConfiguredBehavior() : Behavior("CONFIGURED") {}
  test::SectionConfig seen;

 protected:
  absl::Status onConfigure(const test::SectionConfig& config) override {
    seen = config;
    if (config.name() == "refuse") return absl::InvalidArgumentError("refused by the behavior");
    return absl::OkStatus();
  }
};

TEST(BehaviorConfigTest, ATypedBehaviorGetsItsKeysWithDefaults) {
  FakeClock clock;
  BehaviorHost host(testing::hostOptions("r", "s"), clock);
  auto owned = std::make_unique<ConfiguredBehavior>();
  ConfiguredBehavior* behavior = owned.get();
  host.add(std::move(owned));
  ASSERT_TRUE(host.start(YAML::Load("behaviors:\n"
                                    "  CONFIGURED:\n"
                                    "    frequency_hz: 40\n"
                                    "    tolerance_m: 2.5\n"
                                    "    mount_m: [0.1, 0.2, 0.3]\n"),
                         "sys.yaml")
                  .ok());
  EXPECT_EQ(host.find("CONFIGURED")->options().frequency_hz, 40.0);
  EXPECT_DOUBLE_EQ(behavior->seen.tolerance_m(), 2.5);
  EXPECT_DOUBLE_EQ(behavior->seen.shared().timeout_s(), 0.5);  // the proto's default
  EXPECT_EQ(behavior->seen.mount_m_size(), 3);
  host.stop();
}

TEST(BehaviorConfigTest, UnknownKeysAndBehaviorsStopTheStartWithTheirLine) {
  FakeClock clock;
  {
    BehaviorHost host(testing::hostOptions("r", "s"), clock);
    host.add(std::make_unique<ConfiguredBehavior>());
    const absl::Status s = host.start(
        YAML::Load("behaviors:\n  CONFIGURED:\n    frequency_hz: 40\n    tolerence_m: 1\n"),
        "sys.yaml");
    EXPECT_EQ(s.code(), absl::StatusCode::kInvalidArgument);
    EXPECT_THAT(s.message(),
                HasSubstr("sys.yaml:4:5: behaviors.CONFIGURED: unknown key 'tolerence_m'"));
  }
  {
    // A behavior without keys of its own (Empty) refuses any but the library's.
    BehaviorHost host(testing::hostOptions("r", "s"), clock);
    host.add(std::make_unique<ScriptedBehavior>());
    const absl::Status s =
        host.start(YAML::Load("behaviors:\n  SCRIPTED:\n    tolerance_m: 1\n"), "sys.yaml");
    EXPECT_THAT(s.message(), HasSubstr("sys.yaml:3:5: behaviors.SCRIPTED: unknown key"));
  }
  {
    // A section for a behavior the system does not host: a misspelled name.
    BehaviorHost host(testing::hostOptions("r", "s"), clock);
    host.add(std::make_unique<ScriptedBehavior>());
    const absl::Status s =
        host.start(YAML::Load("behaviors:\n  SCRIPTD:\n    frequency_hz: 5\n"), "sys.yaml");
    EXPECT_THAT(s.message(),
                HasSubstr("sys.yaml:2:3: behaviors: no behavior 'SCRIPTD' in this system "
                          "(it hosts SCRIPTED)"));
  }
  {
    // Out of range, on its value's line.
    BehaviorHost host(testing::hostOptions("r", "s"), clock);
    host.add(std::make_unique<ConfiguredBehavior>());
    const absl::Status s =
        host.start(YAML::Load("behaviors:\n  CONFIGURED:\n    timeout_s: 99\n"), "sys.yaml");
    EXPECT_THAT(s.message(), HasSubstr("sys.yaml:3:16: behaviors.CONFIGURED: key "
                                       "'shared.timeout_s' = 99 is out of range"));
  }
  {
    // The behavior's own refusal stops the start too.
    BehaviorHost host(testing::hostOptions("r", "s"), clock);
    host.add(std::make_unique<ConfiguredBehavior>());
    const absl::Status s =
        host.start(YAML::Load("behaviors:\n  CONFIGURED:\n    name: refuse\n"), "sys.yaml");
    EXPECT_THAT(s.message(), HasSubstr("refused by the behavior"));
  }
}

}  // namespace
}  // namespace behaviorlib
