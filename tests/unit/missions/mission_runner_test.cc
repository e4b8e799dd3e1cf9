#include "coordinator/mission/mission_runner.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <unistd.h>

#include <array>
#include <deque>
#include <map>
#include <set>

#include "coordinator/durable/journal.h"

namespace behaviorlib::coordinator {
namespace {

using std::chrono::milliseconds;
using std::chrono::seconds;
using ::testing::ElementsAre;
using ::testing::HasSubstr;

// Behavior systems as the runner sees them: activations finish with
// scripted causes; request ids are idempotent, as in the real systems.
class ScriptedActions : public MissionActions {
 public:
  // Causes of the successive activations of a behavior (GOAL_ACHIEVED when
  // the script is empty).
  void script(const std::string& behavior, std::vector<v1::TerminationCause> causes) {
    std::lock_guard lock(mutex_);
    for (auto c : causes) script_[behavior].push_back(c);
  }
  // Activations of `behavior` stay active until finish() or deactivate().
  void hold(const std::string& behavior) {
    std::lock_guard lock(mutex_);
    held_.insert(behavior);
  }
  void finish(const std::string& behavior, v1::TerminationCause cause) {
    std::lock_guard lock(mutex_);
    held_.erase(behavior);
    for (auto& [id, b] : behavior_of_) {
      if (b == behavior && !outcome_.count(id)) outcome_[id] = {cause, "scripted"};
    }
  }
  void refuse(const std::string& behavior, absl::Status status) {
    std::lock_guard lock(mutex_);
    refuse_[behavior] = status;
  }
  std::vector<std::string> calls() const {
    std::lock_guard lock(mutex_);
    return calls_;
  }
  int count(const std::string& call) const {
    auto c = calls();
    return static_cast<int>(std::count(c.begin(), c.end(), call));
  }
  bool active(const std::string& behavior) const {
    std::lock_guard lock(mutex_);
    for (const auto& [id, b] : behavior_of_) {
      if (b == behavior && !outcome_.count(id)) return true;
    }
    return false;
  }
  google::protobuf::Struct lastParameters(const std::string& behavior) const {
    std::lock_guard lock(mutex_);
    return parameters_.at(behavior);
  }

  // A behavior of another robot than drone1 is "<behavior>@<robot>".
  static std::string on(const std::string& robot, const std::string& behavior) {
    return robot == "drone1" ? behavior : behavior + "@" + robot;
  }

  absl::StatusOr<std::string> activate(const std::string& robot, const std::string& of_robot,
                                       const google::protobuf::Struct& parameters,
                                       const std::string& request_id) override {
    const std::string behavior = on(robot, of_robot);
    std::lock_guard lock(mutex_);
    if (auto it = by_request_.find(request_id); it != by_request_.end()) {
      calls_.push_back("same activation " + behavior);
      return it->second;
    }
    if (auto it = refuse_.find(behavior); it != refuse_.end()) {
      calls_.push_back("refused " + behavior);
      return it->second;
    }
    calls_.push_back("activate " + behavior);
    std::string id = "a";
    id += std::to_string(++next_);
    by_request_[request_id] = id;
    behavior_of_[id] = behavior;
    parameters_[behavior] = parameters;
    if (!held_.count(behavior)) {
      auto& queue = script_[behavior];
      v1::TerminationCause cause = v1::TERMINATION_CAUSE_GOAL_ACHIEVED;
      if (!queue.empty()) {
        cause = queue.front();
        queue.pop_front();
      }
      outcome_[id] = {cause, "scripted"};
    }
    return id;
  }
  absl::Status deactivate(const std::string& robot, const std::string& of_robot) override {
    const std::string behavior = on(robot, of_robot);
    std::lock_guard lock(mutex_);
    calls_.push_back("deactivate " + behavior);
    for (auto& [id, b] : behavior_of_) {
      if (b == behavior && !outcome_.count(id))
        outcome_[id] = {v1::TERMINATION_CAUSE_INTERRUPTED, "deactivated"};
    }
    return absl::OkStatus();
  }
  absl::Status pause(const std::string& robot, const std::string& behavior) override {
    std::lock_guard lock(mutex_);
    calls_.push_back("pause " + on(robot, behavior));
    return absl::OkStatus();
  }
  absl::Status resume(const std::string& robot, const std::string& behavior) override {
    std::lock_guard lock(mutex_);
    calls_.push_back("resume " + on(robot, behavior));
    return absl::OkStatus();
  }
  std::optional<FinishedActivation> awaitFinished(const std::string&, const std::string& id,
                                                  milliseconds timeout) override {
    {
      std::lock_guard lock(mutex_);
      if (auto it = outcome_.find(id); it != outcome_.end()) return it->second;
    }
    std::this_thread::sleep_for(std::min(timeout, milliseconds(1)));
    return std::nullopt;
  }

 private:
  mutable std::mutex mutex_;
  std::vector<std::string> calls_;
  std::map<std::string, std::deque<v1::TerminationCause>> script_;
  std::set<std::string> held_;
  std::map<std::string, absl::Status> refuse_;
  std::map<std::string, std::string> by_request_, behavior_of_;
  std::map<std::string, FinishedActivation> outcome_;
  std::map<std::string, google::protobuf::Struct> parameters_;
  int next_ = 0;
};

MissionSpec mission(const std::string& yaml) {
  auto spec = parseMission(yaml, "test.yaml");
  EXPECT_TRUE(spec.ok()) << spec.status();
  return *spec;
}

struct MissionRun {
  ScriptedActions actions;
  BeliefStore beliefs;
  std::mutex mutex;
  std::vector<v1::MissionStatus> changes;
  std::unique_ptr<MissionRunner> runner;

  void start(const std::string& yaml, const std::string& id = "m1",
             MissionRunner::Options options = {}) {
    runner = std::make_unique<MissionRunner>(
        mission(yaml), id, "drone1", yaml, actions, beliefs,
        [this](const v1::MissionStatus& s) {
          std::lock_guard lock(mutex);
          changes.push_back(s);
        },
        options);
    runner->start();
  }
  v1::MissionStatus finish() {
    EXPECT_TRUE(runner->waitFinished(seconds(10)));
    return runner->status();
  }
  v1::MissionStatus last() {
    std::lock_guard lock(mutex);
    return changes.back();
  }
};

template <class F>
bool eventually(F f) {
  for (int i = 0; i < 5000; ++i) {
    if (f()) return true;
    std::this_thread::sleep_for(milliseconds(1));
  }
  return false;
}

constexpr const char* kTakeOffFollowLand = R"(name: demo
recurrent:
  - behavior: SELF_LOCALIZE
safety:
  - behavior: LAND
steps:
  - behavior: TAKE_OFF
  - behavior: FOLLOW_PATH
  - behavior: LAND
)";

TEST(MissionRunner, RunsStepsInOrderWithRecurrentBehaviorsAround) {
  MissionRun run;
  run.actions.hold("SELF_LOCALIZE");
  run.start(kTakeOffFollowLand);
  const v1::MissionStatus status = run.finish();
  EXPECT_EQ(status.state(), v1::MISSION_STATE_SUCCEEDED) << status.message();
  EXPECT_THAT(run.actions.calls(),
              ElementsAre("activate SELF_LOCALIZE", "activate TAKE_OFF", "activate FOLLOW_PATH",
                          "activate LAND", "deactivate SELF_LOCALIZE"));
  ASSERT_EQ(status.steps_size(), 3);
  EXPECT_EQ(status.steps(1).behavior(), "FOLLOW_PATH");
  EXPECT_EQ(status.steps(1).cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED);
  EXPECT_EQ(status.steps(1).request_id(), "m1/steps/1/attempt/1");
  EXPECT_TRUE(status.has_end_time());
}

constexpr const char* kBranches = R"(name: branches
safety:
  - behavior: LAND
steps:
  - behavior: STEP
    on:
      TIME_OUT: {retry: 2}
      WRONG_PROGRESS: {fallback: [{behavior: RECOVER}, {behavior: RECOVER_MORE}]}
      SITUATION_CHANGE: continue
      REFUSED: continue
      otherwise: abort
  - behavior: NEXT
)";

struct Branch {
  std::vector<v1::TerminationCause> causes;  // of STEP's activations
  v1::MissionState state;
  std::vector<std::string> calls;
};

class MissionBranches : public ::testing::TestWithParam<Branch> {};

TEST_P(MissionBranches, FollowTheTerminationCause) {
  MissionRun run;
  run.actions.script("STEP", GetParam().causes);
  run.start(kBranches);
  const v1::MissionStatus status = run.finish();
  EXPECT_EQ(status.state(), GetParam().state) << status.message();
  EXPECT_EQ(run.actions.calls(), GetParam().calls);
}

INSTANTIATE_TEST_SUITE_P(
    EachCause, MissionBranches,
    ::testing::Values(Branch{{v1::TERMINATION_CAUSE_GOAL_ACHIEVED},
                             v1::MISSION_STATE_SUCCEEDED,
                             {"activate STEP", "activate NEXT"}},
                      Branch{{v1::TERMINATION_CAUSE_TIME_OUT, v1::TERMINATION_CAUSE_TIME_OUT},
                             v1::MISSION_STATE_SUCCEEDED,
                             {"activate STEP", "activate STEP", "activate STEP", "activate NEXT"}},
                      Branch{{v1::TERMINATION_CAUSE_TIME_OUT, v1::TERMINATION_CAUSE_TIME_OUT,
                              v1::TERMINATION_CAUSE_TIME_OUT},
                             v1::MISSION_STATE_FAILED,
                             {"activate STEP", "activate STEP", "activate STEP", "activate LAND"}},
                      Branch{{v1::TERMINATION_CAUSE_WRONG_PROGRESS},
                             v1::MISSION_STATE_SUCCEEDED,
                             {"activate STEP", "activate RECOVER", "activate RECOVER_MORE",
                              "activate NEXT"}},
                      Branch{{v1::TERMINATION_CAUSE_SITUATION_CHANGE},
                             v1::MISSION_STATE_SUCCEEDED,
                             {"activate STEP", "activate NEXT"}},
                      Branch{{v1::TERMINATION_CAUSE_PROCESS_FAILURE},
                             v1::MISSION_STATE_FAILED,
                             {"activate STEP", "activate LAND"}},
                      Branch{{v1::TERMINATION_CAUSE_INTERRUPTED},
                             v1::MISSION_STATE_FAILED,
                             {"activate STEP", "activate LAND"}}));

TEST(MissionRunner, ARefusedActivationIsACauseToo) {
  MissionRun run;
  run.actions.refuse("STEP", absl::FailedPreconditionError("already flying"));
  run.start(kBranches);
  const v1::MissionStatus status = run.finish();
  EXPECT_EQ(status.state(), v1::MISSION_STATE_SUCCEEDED);
  EXPECT_EQ(status.steps(0).state(), v1::MISSION_STEP_STATE_REFUSED);
  EXPECT_EQ(status.steps(0).message(), "already flying");
}

TEST(MissionRunner, AFailureNamesTheStepAndCause) {
  MissionRun run;
  run.actions.script("STEP", {v1::TERMINATION_CAUSE_PROCESS_FAILURE});
  run.start(kBranches);
  const v1::MissionStatus status = run.finish();
  EXPECT_EQ(status.state(), v1::MISSION_STATE_FAILED);
  EXPECT_THAT(status.message(),
              HasSubstr("step steps/0 (STEP) finished PROCESS_FAILURE: scripted"));
  EXPECT_FALSE(status.in_safety_steps());
}

TEST(MissionRunner, BindsBeliefsIntoParametersAndSkipsOnConditions) {
  MissionRun run;
  google::protobuf::Value path;
  path.mutable_list_value()->add_values()->set_number_value(4.0);
  ASSERT_TRUE(run.beliefs.write("drone1/path", path, "GENERATE_PATH").ok());
  run.start(R"(name: bind
steps:
  - behavior: FOLLOW_PATH
    parameters: {path: "${belief.drone1/path}", speed_m_s: 1.0}
    remember: {followed: true}
  - behavior: CELEBRATE
    if: {belief: operator_answer, equals: "yes"}
  - remember: {report: "followed ${belief.followed}"}
)");
  const v1::MissionStatus status = run.finish();
  EXPECT_EQ(status.state(), v1::MISSION_STATE_SUCCEEDED);
  const auto params = run.actions.lastParameters("FOLLOW_PATH");
  EXPECT_EQ(params.fields().at("path").list_value().values(0).number_value(), 4.0);
  EXPECT_EQ(params.fields().at("speed_m_s").number_value(), 1.0);
  EXPECT_EQ(run.actions.count("activate CELEBRATE"), 0);
  EXPECT_EQ(status.steps(1).state(), v1::MISSION_STEP_STATE_SKIPPED);
  EXPECT_EQ(run.beliefs.get("report")->value().string_value(), "followed true");
}

TEST(MissionRunner, AnUnboundBeliefRefusesTheStep) {
  MissionRun run;
  run.start("steps:\n  - behavior: FOLLOW_PATH\n    parameters: {path: \"${belief.none}\"}\n");
  const v1::MissionStatus status = run.finish();
  EXPECT_EQ(status.state(), v1::MISSION_STATE_FAILED);
  EXPECT_THAT(status.message(), HasSubstr("belief 'none' is not in memory"));
  EXPECT_EQ(run.actions.count("activate FOLLOW_PATH"), 0);
}

TEST(MissionRunner, AbortDeactivatesTheCurrentBehaviorAndRunsTheSafetySteps) {
  MissionRun run;
  run.actions.hold("SELF_LOCALIZE");
  run.actions.hold("FOLLOW_PATH");
  run.start(kTakeOffFollowLand);
  ASSERT_TRUE(eventually([&] { return run.actions.active("FOLLOW_PATH"); }));
  ASSERT_TRUE(run.runner->abort("operator said so").ok());
  const v1::MissionStatus status = run.finish();
  EXPECT_EQ(status.state(), v1::MISSION_STATE_ABORTED);
  EXPECT_EQ(status.message(), "operator said so");
  EXPECT_EQ(status.steps(1).cause(), v1::TERMINATION_CAUSE_INTERRUPTED);
  EXPECT_THAT(run.actions.calls(),
              ElementsAre("activate SELF_LOCALIZE", "activate TAKE_OFF", "activate FOLLOW_PATH",
                          "deactivate FOLLOW_PATH", "activate LAND", "deactivate SELF_LOCALIZE"));
  EXPECT_EQ(run.runner->abort("again").code(), absl::StatusCode::kFailedPrecondition);
}

TEST(MissionRunner, AnAbortWithoutSafetyStepsSaysSoInTheFinalStatus) {
  // The coordinator's own safety action lands the vehicle: the mission's
  // safety steps are skipped, and its final message keeps saying so.
  MissionRun run;
  run.actions.hold("SELF_LOCALIZE");
  run.actions.hold("FOLLOW_PATH");
  run.start(kTakeOffFollowLand);
  ASSERT_TRUE(eventually([&] { return run.actions.active("FOLLOW_PATH"); }));
  ASSERT_TRUE(run.runner->abort("geofence breached", /*run_safety=*/false).ok());
  const v1::MissionStatus status = run.finish();
  EXPECT_EQ(status.state(), v1::MISSION_STATE_ABORTED);
  EXPECT_EQ(status.message(),
            "geofence breached; safety steps skipped (the vehicle is landed by the coordinator's "
            "safety action)");
  EXPECT_FALSE(status.in_safety_steps());
  EXPECT_THAT(run.actions.calls(),
              ElementsAre("activate SELF_LOCALIZE", "activate TAKE_OFF", "activate FOLLOW_PATH",
                          "deactivate FOLLOW_PATH", "deactivate SELF_LOCALIZE"));
}

TEST(MissionRunner, PauseAndResumeReachTheActiveBehavior) {
  MissionRun run;
  run.actions.hold("SELF_LOCALIZE");
  run.actions.hold("FOLLOW_PATH");
  run.start(kTakeOffFollowLand);
  ASSERT_TRUE(eventually([&] { return run.actions.active("FOLLOW_PATH"); }));
  ASSERT_TRUE(run.runner->pause().ok());
  ASSERT_TRUE(eventually([&] { return run.runner->status().state() == v1::MISSION_STATE_PAUSED; }));
  EXPECT_EQ(run.actions.count("pause FOLLOW_PATH"), 1);
  EXPECT_EQ(run.runner->pause().code(), absl::StatusCode::kFailedPrecondition);
  ASSERT_TRUE(run.runner->resume().ok());
  ASSERT_TRUE(eventually([&] { return run.actions.count("resume FOLLOW_PATH") == 1; }));
  run.actions.finish("FOLLOW_PATH", v1::TERMINATION_CAUSE_GOAL_ACHIEVED);
  EXPECT_EQ(run.finish().state(), v1::MISSION_STATE_SUCCEEDED);
  EXPECT_EQ(run.runner->resume().code(), absl::StatusCode::kFailedPrecondition);
}

TEST(MissionRunner, ARecurrentBehaviorThatEndsAbortsTheMission) {
  MissionRun run;
  run.actions.hold("SELF_LOCALIZE");
  run.actions.hold("FOLLOW_PATH");
  run.start(kTakeOffFollowLand);
  ASSERT_TRUE(eventually([&] { return run.actions.active("FOLLOW_PATH"); }));
  run.actions.finish("SELF_LOCALIZE", v1::TERMINATION_CAUSE_PROCESS_FAILURE);
  const v1::MissionStatus status = run.finish();
  EXPECT_EQ(status.state(), v1::MISSION_STATE_FAILED);
  EXPECT_THAT(status.message(),
              HasSubstr("recurrent behavior SELF_LOCALIZE finished PROCESS_FAILURE"));
  EXPECT_EQ(run.actions.count("deactivate FOLLOW_PATH"), 1);
  EXPECT_EQ(run.actions.count("activate LAND"), 1);
}

TEST(MissionRunner, AResumedMissionActivatesNothingTwice) {
  // The coordinator journals every change; it dies while FOLLOW_PATH runs.
  char name[] = "/tmp/mission_journal_XXXXXX";
  close(mkstemp(name));
  ScriptedActions actions;  // the behavior systems outlive the coordinator
  actions.hold("SELF_LOCALIZE");
  actions.hold("FOLLOW_PATH");
  {
    auto journal = Journal::open(name, [](const behaviorlib::durable::v1::JournalRecord&) {});
    ASSERT_TRUE(journal.ok());
    BeliefStore beliefs(journal->get());
    MissionRunner runner(mission(kTakeOffFollowLand), "m7", "drone1", kTakeOffFollowLand, actions,
                         beliefs, [&](const v1::MissionStatus& s) {
                           behaviorlib::durable::v1::JournalRecord r;
                           *r.mutable_mission() = s;
                           ASSERT_TRUE((*journal)->append(r).ok());
                         });
    runner.start();
    ASSERT_TRUE(eventually([&] { return actions.active("FOLLOW_PATH"); }));
  }  // the coordinator is gone; the mission was not aborted
  EXPECT_TRUE(actions.active("FOLLOW_PATH"));

  // A new coordinator replays the journal and resumes the mission.
  std::optional<v1::MissionStatus> recorded;
  BeliefStore beliefs;
  auto journal = Journal::open(name, [&](const behaviorlib::durable::v1::JournalRecord& r) {
    if (r.has_mission()) recorded = r.mission();
  });
  ASSERT_TRUE(journal.ok());
  ASSERT_TRUE(recorded.has_value());
  EXPECT_EQ(recorded->state(), v1::MISSION_STATE_RUNNING);
  auto spec = parseMission(recorded->source(), recorded->file());
  ASSERT_TRUE(spec.ok());
  MissionRunner resumed(*spec, *recorded, actions, beliefs, nullptr);
  resumed.start();
  ASSERT_TRUE(eventually([&] { return actions.count("same activation FOLLOW_PATH") == 1; }));
  actions.finish("FOLLOW_PATH", v1::TERMINATION_CAUSE_GOAL_ACHIEVED);
  ASSERT_TRUE(resumed.waitFinished(seconds(10)));
  EXPECT_EQ(resumed.status().state(), v1::MISSION_STATE_SUCCEEDED);
  EXPECT_EQ(actions.count("activate TAKE_OFF"), 1);
  EXPECT_EQ(actions.count("activate FOLLOW_PATH"), 1);
  EXPECT_EQ(actions.count("activate SELF_LOCALIZE"), 1);
  EXPECT_EQ(actions.count("activate LAND"), 1);
  EXPECT_EQ(resumed.status().steps_size(), 3);
  std::remove(name);
}

// Runs `yaml` until `until` holds, then drops the runner as a coordinator
// that dies would (the mission not aborted); its last status, as journaled.
std::optional<v1::MissionStatus> runUntilTheCoordinatorDies(const char* yaml,
                                                            ScriptedActions& actions,
                                                            BeliefStore& beliefs,
                                                            const std::function<bool()>& until) {
  std::vector<v1::MissionStatus> changes;
  std::mutex mutex;
  auto runner = std::make_unique<MissionRunner>(mission(yaml), "m8", "drone1", yaml, actions,
                                                beliefs, [&](const v1::MissionStatus& s) {
                                                  std::lock_guard lock(mutex);
                                                  changes.push_back(s);
                                                });
  runner->start();
  const bool reached = eventually(until);
  runner.reset();  // its thread joined: `changes` holds all it said
  if (!reached) return std::nullopt;
  return changes.back();
}

TEST(MissionRunner, AMissionResumedInsideAFallbackFinishesTheFallback) {
  ScriptedActions actions;
  actions.script("STEP", {v1::TERMINATION_CAUSE_WRONG_PROGRESS});
  actions.hold("RECOVER");
  BeliefStore beliefs;
  const auto last = runUntilTheCoordinatorDies(kBranches, actions, beliefs,
                                               [&] { return actions.active("RECOVER"); });
  ASSERT_TRUE(last.has_value());
  MissionRunner resumed(mission(kBranches), *last, actions, beliefs, nullptr);
  resumed.start();
  ASSERT_TRUE(eventually([&] { return actions.count("same activation RECOVER") == 1; }));
  actions.finish("RECOVER", v1::TERMINATION_CAUSE_GOAL_ACHIEVED);
  ASSERT_TRUE(resumed.waitFinished(seconds(10)));
  EXPECT_EQ(resumed.status().state(), v1::MISSION_STATE_SUCCEEDED);
  EXPECT_THAT(actions.calls(),
              ElementsAre("activate STEP", "activate RECOVER", "same activation RECOVER",
                          "activate RECOVER_MORE", "activate NEXT"));
}

// A sub-mission's call ends like a behavior: GOAL_ACHIEVED when its steps
// went on, or the cause of the step that failed it, which the call's `on:`
// branches on. A retried call runs its steps again under new request ids.
constexpr const char* kCalls = R"(name: calls
safety:
  - behavior: LAND
submissions:
  go:
    parameters: {speed: {type: number, default: 1}}
    steps:
      - behavior: PLAN
      - behavior: FLY
        parameters: {speed: "${param.speed}"}
steps:
  - name: first
    call: go
    with: {speed: 2}
    on:
      WRONG_PROGRESS: {retry: 1, then: {fallback: [{behavior: RECOVER}]}}
  - call: go
  - behavior: LAND
)";

TEST(MissionRunner, ACallRunsTheSubMissionAndBranchesOnTheCauseOfItsFailedStep) {
  MissionRun run;
  // FLY fails the first call twice (the call is retried once), then the
  // fallback; the second call succeeds.
  run.actions.script("FLY",
                     {v1::TERMINATION_CAUSE_WRONG_PROGRESS, v1::TERMINATION_CAUSE_WRONG_PROGRESS});
  run.start(kCalls);
  const v1::MissionStatus status = run.finish();
  EXPECT_EQ(status.state(), v1::MISSION_STATE_SUCCEEDED) << status.message();
  EXPECT_THAT(run.actions.calls(),
              ElementsAre("activate PLAN", "activate FLY", "activate PLAN", "activate FLY",
                          "activate RECOVER", "activate PLAN", "activate FLY", "activate LAND"));
  std::vector<std::string> nodes;
  for (const auto& step : status.steps()) {
    nodes.push_back(step.node() + " " +
                    (step.call().empty() ? step.behavior() : "call " + step.call()) + " " +
                    v1::TerminationCause_Name(step.cause()));
  }
  EXPECT_THAT(nodes,
              ElementsAre("steps/0 call go TERMINATION_CAUSE_WRONG_PROGRESS",
                          "steps/0/attempt/1/call/steps/0 PLAN TERMINATION_CAUSE_GOAL_ACHIEVED",
                          "steps/0/attempt/1/call/steps/1 FLY TERMINATION_CAUSE_WRONG_PROGRESS",
                          "steps/0 call go TERMINATION_CAUSE_WRONG_PROGRESS",
                          "steps/0/attempt/2/call/steps/0 PLAN TERMINATION_CAUSE_GOAL_ACHIEVED",
                          "steps/0/attempt/2/call/steps/1 FLY TERMINATION_CAUSE_WRONG_PROGRESS",
                          "steps/0/fallback/0 RECOVER TERMINATION_CAUSE_GOAL_ACHIEVED",
                          "steps/1 call go TERMINATION_CAUSE_GOAL_ACHIEVED",
                          "steps/1/attempt/1/call/steps/0 PLAN TERMINATION_CAUSE_GOAL_ACHIEVED",
                          "steps/1/attempt/1/call/steps/1 FLY TERMINATION_CAUSE_GOAL_ACHIEVED",
                          "steps/2 LAND TERMINATION_CAUSE_GOAL_ACHIEVED"));
  EXPECT_EQ(status.steps(2).request_id(), "m1/steps/0/attempt/1/call/steps/1/attempt/1");
  EXPECT_TRUE(status.steps(2).path().empty()) << "a step inside a call has only its node";
  EXPECT_THAT(status.steps(6).path(), ElementsAre(0, 0)) << "a fallback keeps its v1 path";
  EXPECT_EQ(run.actions.lastParameters("FLY").fields().at("speed").number_value(), 1)
      << "the second call's default";
}

TEST(MissionRunner, ACallThatFailsWithoutABranchAbortsTheMissionNamingIt) {
  MissionRun run;
  run.actions.script("FLY", {v1::TERMINATION_CAUSE_TIME_OUT});
  run.start(kCalls);
  const v1::MissionStatus status = run.finish();
  EXPECT_EQ(status.state(), v1::MISSION_STATE_FAILED);
  EXPECT_THAT(status.message(), HasSubstr("step 'first' (call go) finished TIME_OUT"));
  EXPECT_THAT(status.message(), HasSubstr("(FLY) finished TIME_OUT"));
  EXPECT_EQ(run.actions.count("activate LAND"), 1) << "the safety step";
}

TEST(MissionRunner, AMissionResumedInsideACallActivatesNothingTwice) {
  ScriptedActions actions;
  actions.hold("FLY");
  BeliefStore beliefs;
  // The coordinator is gone while the first call flies.
  const auto last =
      runUntilTheCoordinatorDies(kCalls, actions, beliefs, [&] { return actions.active("FLY"); });
  ASSERT_TRUE(last.has_value());
  MissionRunner resumed(mission(kCalls), *last, actions, beliefs, nullptr);
  resumed.start();
  ASSERT_TRUE(eventually([&] { return actions.count("same activation FLY") == 1; }));
  actions.finish("FLY", v1::TERMINATION_CAUSE_GOAL_ACHIEVED);
  ASSERT_TRUE(resumed.waitFinished(seconds(10)));
  EXPECT_EQ(resumed.status().state(), v1::MISSION_STATE_SUCCEEDED) << resumed.status().message();
  EXPECT_THAT(actions.calls(), ElementsAre("activate PLAN", "activate FLY", "same activation FLY",
                                           "activate PLAN", "activate FLY", "activate LAND"));
}

// Loops: for_each over a literal list or a belief's list (the item as
// ${each.<as>}), repeat N times, repeat until a belief condition (at most
// max_times, then WRONG_PROGRESS). Each iteration's steps activate anew.
constexpr const char* kLoops = R"(name: loops
steps:
  - name: visit
    for_each: {in: [{x: 1}, {x: 2}], as: point}
    steps:
      - behavior: FLY
        parameters: {goal: "${each.point}", label: "to ${each.point_name}"}
  - name: found
    for_each: {in: {belief: drone1/codes}, as: code, max_items: 5}
    steps:
      - behavior: READ
        parameters: {code: "${each.code}"}
  - name: twice
    repeat: {times: 2}
    steps:
      - behavior: SCAN
  - name: until_done
    repeat: {until: {belief: drone1/done, exists: true}, max_times: 4}
    steps:
      - behavior: SEARCH
      - remember: {drone1/searched: true}
)";

TEST(MissionRunner, LoopsRunTheirStepsOnceAnItemOrAnIteration) {
  // ${each.point_name} is not a loop's item: refused when parsed.
  auto bad = parseMission(kLoops, "loops.yaml");
  ASSERT_FALSE(bad.ok());
  EXPECT_THAT(
      std::string(bad.status().message()),
      HasSubstr("loops.yaml:7: steps step 'visit' step: ${each.point_name} is not the item of a "
                "for_each around it (its items: point)"));
  std::string text = kLoops;
  text.replace(text.find(", label: \"to ${each.point_name}\""),
               std::string(", label: \"to ${each.point_name}\"").size(), "");
  MissionRun run;
  ASSERT_TRUE(run.beliefs
                  .write(
                      "drone1/codes",
                      [] {
                        google::protobuf::Value v;
                        v.mutable_list_value()->add_values()->set_string_value("A7");
                        v.mutable_list_value()->add_values()->set_string_value("B2");
                        v.mutable_list_value()->add_values()->set_string_value("C9");
                        return v;
                      }(),
                      "test")
                  .ok());
  run.start(text);
  const v1::MissionStatus status = run.finish();
  EXPECT_EQ(status.state(), v1::MISSION_STATE_FAILED) << "until_done never holds";
  EXPECT_THAT(status.message(),
              HasSubstr("step 'until_done' (repeat until drone1/done (at most 4 times)) finished "
                        "WRONG_PROGRESS: repeat: belief 'drone1/done' did not come to hold in 4 "
                        "iterations"));
  EXPECT_EQ(run.actions.count("activate FLY"), 2);
  EXPECT_EQ(run.actions.count("activate READ"), 3);
  EXPECT_EQ(run.actions.count("activate SCAN"), 2);
  EXPECT_EQ(run.actions.count("activate SEARCH"), 4);
  EXPECT_EQ(run.actions.lastParameters("READ").fields().at("code").string_value(), "C9");
  EXPECT_EQ(run.actions.lastParameters("FLY")
                .fields()
                .at("goal")
                .struct_value()
                .fields()
                .at("x")
                .number_value(),
            2)
      << "a whole item is the item itself";
  std::vector<std::string> nodes;
  for (const auto& step : status.steps()) {
    if (step.behavior() == "SCAN" || !step.loop().empty())
      nodes.push_back(step.node() + " " + step.loop());
  }
  EXPECT_THAT(nodes, ::testing::IsSupersetOf({"steps/0 for_each point in 2 items",
                                              "steps/1 for_each code in belief drone1/codes",
                                              "steps/2 repeat 2 times",
                                              "steps/2/attempt/1/iteration/0/steps/0 ",
                                              "steps/2/attempt/1/iteration/1/steps/0 "}));

  // The condition holds after the second iteration: the loop ends there.
  MissionRun until;
  until.actions.script("SEARCH", {});
  const std::string only_until =
      "name: u\nsteps:\n  - repeat: {until: {belief: drone1/found, "
      "exists: true}, max_times: 5}\n    steps:\n"
      "      - behavior: SEARCH\n"
      "      - if: {belief: drone1/searched_once, exists: true}\n"
      "        remember: {drone1/found: true}\n"
      "      - remember: {drone1/searched_once: true}\n";
  until.start(only_until);
  EXPECT_EQ(until.finish().state(), v1::MISSION_STATE_SUCCEEDED);
  EXPECT_EQ(until.actions.count("activate SEARCH"), 2);

  // A belief that is not a list: the loop is refused (REFUSED, aborting).
  MissionRun refused;
  ASSERT_TRUE(refused.beliefs
                  .write(
                      "drone1/codes",
                      [] {
                        google::protobuf::Value v;
                        v.set_string_value("not a list");
                        return v;
                      }(),
                      "test")
                  .ok());
  refused.start(
      "name: r\nsteps:\n  - for_each: {in: {belief: drone1/codes}, as: c}\n"
      "    steps: [{behavior: READ}]\n");
  const v1::MissionStatus r = refused.finish();
  EXPECT_EQ(r.state(), v1::MISSION_STATE_FAILED);
  EXPECT_THAT(r.message(), HasSubstr("was refused: for_each: belief 'drone1/codes' is not a list"));
}

TEST(MissionRunner, AMissionResumedInsideALoopGoesOnFromItsIteration) {
  ScriptedActions actions;
  actions.hold("SCAN");
  BeliefStore beliefs;
  const char* yaml =
      "name: l\nsteps:\n  - repeat: {times: 3}\n    steps:\n"
      "      - behavior: MOVE\n      - behavior: SCAN\n";
  // The coordinator dies in the second iteration's SCAN.
  int scans = 0;
  const auto last = runUntilTheCoordinatorDies(yaml, actions, beliefs, [&] {
    if (actions.active("SCAN") && actions.count("activate SCAN") == 2) return true;
    if (actions.active("SCAN") && actions.count("activate SCAN") > scans) {
      scans = actions.count("activate SCAN");
      actions.finish("SCAN", v1::TERMINATION_CAUSE_GOAL_ACHIEVED);
      actions.hold("SCAN");
    }
    return false;
  });
  ASSERT_TRUE(last.has_value());
  MissionRunner resumed(mission(yaml), *last, actions, beliefs, nullptr);
  resumed.start();
  ASSERT_TRUE(eventually([&] { return actions.count("same activation SCAN") == 1; }));
  actions.finish("SCAN", v1::TERMINATION_CAUSE_GOAL_ACHIEVED);
  ASSERT_TRUE(eventually([&] { return actions.count("activate SCAN") == 3; }));
  actions.finish("SCAN", v1::TERMINATION_CAUSE_GOAL_ACHIEVED);
  ASSERT_TRUE(resumed.waitFinished(seconds(10)));
  EXPECT_EQ(resumed.status().state(), v1::MISSION_STATE_SUCCEEDED) << resumed.status().message();
  EXPECT_EQ(actions.count("activate MOVE"), 3) << "each iteration's MOVE once";
  EXPECT_EQ(actions.count("activate SCAN"), 3);
}

// Parallel branches run at once, each on its robot (a fleet mission); `all`
// waits for every branch, and the first that fails decides (the others are
// interrupted); `any` ends with the first that achieves. Their steps are at
// ".../attempt/<a>/branch/<b>/steps/<j>".
constexpr const char* kFleet = R"(name: fleet
robot: drone1
safety:
  - behavior: LAND
  - {robot: drone2, behavior: LAND}
steps:
  - name: take_off
    parallel:
      branches:
        - {name: one, steps: [{behavior: TAKE_OFF}, {behavior: FLY}]}
        - {name: two, robot: drone2, steps: [{behavior: TAKE_OFF}, {behavior: FLY}]}
    on:
      WRONG_PROGRESS: continue
  - name: land
    parallel:
      end: any
      branches:
        - behavior: LAND
        - {robot: drone2, behavior: LAND}
)";

v1::MissionStepRecord recordOf(const v1::MissionStatus& status, const std::string& node) {
  for (const auto& r : status.steps()) {
    if (r.node() == node) return r;
  }
  ADD_FAILURE() << "no record at " << node;
  return {};
}

// Starts kFleet with both vehicles' FLY held; true once both fly.
bool flyBoth(MissionRun& run) {
  run.actions.hold("FLY");
  run.actions.hold("FLY@drone2");
  run.start(kFleet);
  return eventually([&] { return run.actions.active("FLY") && run.actions.active("FLY@drone2"); });
}

TEST(MissionRunner, ParallelBranchesRunAtOnceEachOnItsRobot) {
  MissionRun run;
  run.actions.hold("FLY");
  run.actions.hold("FLY@drone2");
  run.actions.hold("LAND");
  run.actions.hold("LAND@drone2");
  run.start(kFleet);
  // Both branches fly at once.
  ASSERT_TRUE(
      eventually([&] { return run.actions.active("FLY") && run.actions.active("FLY@drone2"); }));
  EXPECT_THAT(run.runner->status().robot_ids(), ElementsAre("drone1", "drone2"));
  run.actions.finish("FLY", v1::TERMINATION_CAUSE_GOAL_ACHIEVED);
  // `all`: the step waits for the other branch.
  std::this_thread::sleep_for(milliseconds(200));
  EXPECT_EQ(run.actions.count("activate LAND"), 0);
  run.actions.finish("FLY@drone2", v1::TERMINATION_CAUSE_GOAL_ACHIEVED);
  // `any`: drone1's LAND achieves first; drone2's is interrupted.
  ASSERT_TRUE(
      eventually([&] { return run.actions.active("LAND") && run.actions.active("LAND@drone2"); }));
  run.actions.finish("LAND", v1::TERMINATION_CAUSE_GOAL_ACHIEVED);
  const v1::MissionStatus status = run.finish();
  EXPECT_EQ(status.state(), v1::MISSION_STATE_SUCCEEDED) << status.message();
  EXPECT_EQ(run.actions.count("deactivate LAND@drone2"), 1);
  const auto take_off = recordOf(status, "steps/0");
  EXPECT_EQ(take_off.parallel(), "all of 2 branches");
  EXPECT_EQ(take_off.cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED);
  const auto fly_two = recordOf(status, "steps/0/attempt/1/branch/1/steps/1");
  EXPECT_EQ(fly_two.behavior(), "FLY");
  EXPECT_EQ(fly_two.robot_id(), "drone2");
  EXPECT_EQ(fly_two.request_id(), "m1/steps/0/attempt/1/branch/1/steps/1/attempt/1");
  EXPECT_EQ(recordOf(status, "steps/1").message(), "branch 0 achieved its steps");
  const auto land_two = recordOf(status, "steps/1/attempt/1/branch/1/steps/0");
  EXPECT_EQ(land_two.cause(), v1::TERMINATION_CAUSE_INTERRUPTED);
  EXPECT_THAT(land_two.message(), HasSubstr("another branch decided the parallel step"));
}

TEST(MissionRunner, TheFirstBranchThatFailsEndsAnAllParallelStepWithItsCause) {
  MissionRun run;
  ASSERT_TRUE(flyBoth(run));
  run.actions.finish("FLY@drone2", v1::TERMINATION_CAUSE_WRONG_PROGRESS);
  const v1::MissionStatus status = run.finish();
  // WRONG_PROGRESS: continue, and the mission lands.
  EXPECT_EQ(status.state(), v1::MISSION_STATE_SUCCEEDED) << status.message();
  EXPECT_EQ(run.actions.count("deactivate FLY"), 1) << "drone1's branch is interrupted";
  const auto take_off = recordOf(status, "steps/0");
  EXPECT_EQ(take_off.cause(), v1::TERMINATION_CAUSE_WRONG_PROGRESS);
  EXPECT_THAT(take_off.message(), HasSubstr("branch 1 'two': step"));
  EXPECT_EQ(recordOf(status, "steps/0/attempt/1/branch/0/steps/1").cause(),
            v1::TERMINATION_CAUSE_INTERRUPTED);
}

TEST(MissionRunner, AnAbortedFleetMissionRunsEachRobotsSafetySteps) {
  MissionRun run;
  ASSERT_TRUE(flyBoth(run));
  // The coordinator's safety action lands drone2 itself: only drone1's
  // safety steps run.
  ASSERT_TRUE(run.runner->abort("geofence breached by drone2", false, "drone2").ok());
  const v1::MissionStatus status = run.finish();
  EXPECT_EQ(status.state(), v1::MISSION_STATE_ABORTED);
  EXPECT_EQ(run.actions.count("deactivate FLY"), 1);
  EXPECT_EQ(run.actions.count("deactivate FLY@drone2"), 1);
  EXPECT_EQ(run.actions.count("activate LAND"), 1);
  EXPECT_EQ(run.actions.count("activate LAND@drone2"), 0);
  EXPECT_THAT(status.message(), HasSubstr("drone2's safety steps skipped"));

  MissionRun both;
  ASSERT_TRUE(flyBoth(both));
  ASSERT_TRUE(both.runner->abort("by request").ok());
  EXPECT_EQ(both.finish().state(), v1::MISSION_STATE_ABORTED);
  EXPECT_EQ(both.actions.count("activate LAND"), 1);
  EXPECT_EQ(both.actions.count("activate LAND@drone2"), 1);
}

// Pause and Resume reach every running branch: each robot's behavior.
TEST(MissionRunner, PauseAndResumeReachEveryBranch) {
  MissionRun run;
  ASSERT_TRUE(flyBoth(run));
  ASSERT_TRUE(run.runner->pause().ok());
  ASSERT_TRUE(eventually([&] {
    return run.actions.count("pause FLY") == 1 && run.actions.count("pause FLY@drone2") == 1;
  }));
  EXPECT_EQ(run.runner->status().state(), v1::MISSION_STATE_PAUSED);
  ASSERT_TRUE(run.runner->resume().ok());
  ASSERT_TRUE(eventually([&] {
    return run.actions.count("resume FLY") == 1 && run.actions.count("resume FLY@drone2") == 1;
  }));
  EXPECT_EQ(run.runner->status().state(), v1::MISSION_STATE_RUNNING);
  run.actions.finish("FLY", v1::TERMINATION_CAUSE_GOAL_ACHIEVED);
  run.actions.finish("FLY@drone2", v1::TERMINATION_CAUSE_GOAL_ACHIEVED);
  EXPECT_EQ(run.finish().state(), v1::MISSION_STATE_SUCCEEDED);
}

// wait_for: a synchronisation point on another branch's step (by name) or a
// belief, bounded by a time limit on the injected clock.
constexpr const char* kWaits = R"(name: waits
steps:
  - parallel:
      branches:
        - steps:
            - behavior: TAKE_OFF
            - wait_for: {step: two_up, timeout_s: 30}
            - behavior: FLY
        - robot: drone2
          steps:
            - {name: two_up, behavior: TAKE_OFF}
  - name: sync
    wait_for: {belief: drone2/ready, exists: true, timeout_s: 5}
    on:
      TIME_OUT: continue
  - behavior: LAND
)";

TEST(MissionRunner, AWaitHoldsItsBranchUntilTheOtherRobotsStepAchievedOrItsTimeLimit) {
  FakeClock clock;
  MissionRun run;
  run.actions.hold("TAKE_OFF@drone2");
  run.start(kWaits, "m1", MissionRunner::Options{.clock = &clock});
  ASSERT_TRUE(eventually([&] { return run.actions.count("activate TAKE_OFF") == 1; }));
  std::this_thread::sleep_for(milliseconds(200));
  EXPECT_EQ(run.actions.count("activate FLY"), 0) << "drone1 waits for drone2's take-off";
  run.actions.finish("TAKE_OFF@drone2", v1::TERMINATION_CAUSE_GOAL_ACHIEVED);
  ASSERT_TRUE(eventually([&] { return run.actions.count("activate FLY") == 1; }));
  // The belief never comes: TIME_OUT after 5 s of the clock's time, not before.
  ASSERT_TRUE(eventually([&] {
    const auto s = run.runner->status();
    return s.steps_size() > 0 &&
           s.steps(s.steps_size() - 1).wait_for() == "belief 'drone2/ready' exists";
  }));
  clock.advance(std::chrono::seconds(4));
  std::this_thread::sleep_for(milliseconds(200));
  EXPECT_EQ(run.actions.count("activate LAND"), 0);
  clock.advance(std::chrono::seconds(2));
  const v1::MissionStatus status = run.finish();
  EXPECT_EQ(status.state(), v1::MISSION_STATE_SUCCEEDED) << status.message();
  const auto sync = recordOf(status, "steps/1");
  EXPECT_EQ(sync.cause(), v1::TERMINATION_CAUSE_TIME_OUT);
  EXPECT_EQ(sync.message(), "waited 5 s for belief 'drone2/ready' exists");
  EXPECT_EQ(recordOf(status, "steps/0/attempt/1/branch/0/steps/1").wait_for(),
            "step 'two_up' achieved");
}

TEST(MissionRunner, AMissionResumedInsideAParallelStepActivatesNothingTwice) {
  ScriptedActions actions;
  actions.hold("FLY");
  actions.hold("FLY@drone2");
  BeliefStore beliefs;
  // The coordinator is gone while both branches fly.
  const auto last = runUntilTheCoordinatorDies(kFleet, actions, beliefs, [&] {
    return actions.active("FLY") && actions.active("FLY@drone2");
  });
  ASSERT_TRUE(last.has_value());
  MissionRunner resumed(mission(kFleet), *last, actions, beliefs, nullptr);
  resumed.start();
  ASSERT_TRUE(eventually([&] {
    return actions.count("same activation FLY") == 1 &&
           actions.count("same activation FLY@drone2") == 1;
  }));
  actions.finish("FLY", v1::TERMINATION_CAUSE_GOAL_ACHIEVED);
  actions.finish("FLY@drone2", v1::TERMINATION_CAUSE_GOAL_ACHIEVED);
  ASSERT_TRUE(resumed.waitFinished(seconds(10)));
  EXPECT_EQ(resumed.status().state(), v1::MISSION_STATE_SUCCEEDED) << resumed.status().message();
  for (const char* b : {"TAKE_OFF", "TAKE_OFF@drone2", "FLY", "FLY@drone2"}) {
    EXPECT_EQ(actions.count(std::string("activate ") + b), 1) << b;
  }
}

// `when:` conditions on the vehicle, read from its topics while the step
// runs (a scripted reader stands for the data channel; time is a FakeClock).
class ScriptedVehicle : public VehicleReader {
 public:
  void set(double battery, std::array<double, 3> position, int64_t stamp_s) {
    std::lock_guard lock(mutex_);
    battery_ = battery;
    position_ = position;
    stamp_s_ = stamp_s;
  }
  absl::StatusOr<v1::FlightStatus> flightStatus(const std::string&) override {
    std::lock_guard lock(mutex_);
    v1::FlightStatus status;
    status.mutable_header()->mutable_stamp()->set_seconds(stamp_s_);
    status.set_battery_ratio(battery_);
    return status;
  }
  absl::StatusOr<v1::PoseStamped> poseEstimate(const std::string&) override {
    std::lock_guard lock(mutex_);
    v1::PoseStamped pose;
    pose.mutable_header()->mutable_stamp()->set_seconds(stamp_s_);
    pose.mutable_pose()->mutable_position_m()->set_x(position_[0]);
    pose.mutable_pose()->mutable_position_m()->set_y(position_[1]);
    pose.mutable_pose()->mutable_position_m()->set_z(position_[2]);
    return pose;
  }

 private:
  std::mutex mutex_;
  double battery_ = 1.0;
  std::array<double, 3> position_{};
  int64_t stamp_s_ = 1;
};

constexpr const char* kWhen = R"(name: when
safety:
  - behavior: LAND
steps:
  - name: fly
    behavior: FLY
    when:
      - battery_below: 0.3
      - {near: {point_m: [5, 0, 1], radius_m: 0.5}, ends: GOAL_ACHIEVED}
    on:
      SITUATION_CHANGE: abort
  - behavior: NEXT
)";

TEST(MissionRunner, AConditionOnTheVehicleEndsItsStepWhileItRuns) {
  // Near the point: the step ends GOAL_ACHIEVED, its behavior deactivated.
  {
    FakeClock clock;
    ScriptedVehicle vehicle;
    MissionRun run;
    run.actions.hold("FLY");
    run.start(kWhen, "m1", MissionRunner::Options{.clock = &clock, .vehicles = &vehicle});
    ASSERT_TRUE(eventually([&] { return run.actions.active("FLY"); }));
    std::this_thread::sleep_for(milliseconds(150));
    EXPECT_TRUE(run.actions.active("FLY")) << "far from the point, battery full";
    vehicle.set(0.9, {4.8, 0.1, 1.0}, 2);
    const v1::MissionStatus status = run.finish();
    EXPECT_EQ(status.state(), v1::MISSION_STATE_SUCCEEDED) << status.message();
    EXPECT_EQ(run.actions.count("deactivate FLY"), 1);
    EXPECT_EQ(status.steps(0).cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED);
    EXPECT_EQ(status.steps(0).message(),
              "condition on the vehicle: 0.22 m from (5, 0, 1), within 0.5 m");
  }
  // The battery low: SITUATION_CHANGE, which this step aborts on.
  {
    FakeClock clock;
    ScriptedVehicle vehicle;
    MissionRun run;
    run.actions.hold("FLY");
    run.start(kWhen, "m2", MissionRunner::Options{.clock = &clock, .vehicles = &vehicle});
    ASSERT_TRUE(eventually([&] { return run.actions.active("FLY"); }));
    vehicle.set(0.25, {0, 0, 1}, 2);
    const v1::MissionStatus status = run.finish();
    EXPECT_EQ(status.state(), v1::MISSION_STATE_FAILED);
    EXPECT_EQ(status.steps(0).cause(), v1::TERMINATION_CAUSE_SITUATION_CHANGE);
    EXPECT_EQ(status.steps(0).message(), "condition on the vehicle: battery 0.25 below 0.3");
    EXPECT_EQ(run.actions.count("activate LAND"), 1) << "the safety steps ran";
  }
  // The topics stop: after max_age_s (1 s) of the clock's time the step
  // ends PROCESS_FAILURE, not before.
  {
    FakeClock clock;
    ScriptedVehicle vehicle;
    MissionRun run;
    run.actions.hold("FLY");
    run.start(kWhen, "m3", MissionRunner::Options{.clock = &clock, .vehicles = &vehicle});
    ASSERT_TRUE(eventually([&] { return run.actions.active("FLY"); }));
    std::this_thread::sleep_for(milliseconds(150));
    clock.advance(std::chrono::milliseconds(900));
    std::this_thread::sleep_for(milliseconds(150));
    EXPECT_TRUE(run.actions.active("FLY"));
    clock.advance(std::chrono::milliseconds(200));
    const v1::MissionStatus status = run.finish();
    EXPECT_EQ(status.state(), v1::MISSION_STATE_FAILED);
    EXPECT_EQ(status.steps(0).cause(), v1::TERMINATION_CAUSE_PROCESS_FAILURE);
    EXPECT_THAT(status.steps(0).message(),
                HasSubstr("robots/drone1/flight_state did not advance for 1.1 s (limit 1 s)"));
  }
}

TEST(MissionNode, PositionsReadBackFromTheirText) {
  for (const std::string text : {"steps/0", "steps/3/fallback/1", "steps/2/attempt/1/call/steps/0",
                                 "steps/0/attempt/2/branch/1/steps/3",
                                 "steps/2/attempt/3/call/steps/1/fallback/0/attempt/1/call/steps/4",
                                 "steps/1/attempt/2/iteration/7/steps/0/attempt/1/call/steps/2"}) {
    auto position = parseNode(text);
    ASSERT_TRUE(position.has_value()) << text;
    EXPECT_EQ(nodeText(*position), text);
  }
  for (const std::string bad : {"", "steps", "fallback/1", "steps/x", "steps/1/call/steps/0",
                                "steps/-1", "steps/1/attempt/1/call/steps"}) {
    EXPECT_FALSE(parseNode(bad).has_value()) << bad;
  }
}

}  // namespace
}  // namespace behaviorlib::coordinator
