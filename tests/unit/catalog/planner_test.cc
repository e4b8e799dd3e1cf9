#include "coordinator/catalog/planner.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <map>

namespace behaviorlib::coordinator {
namespace {

using ::testing::ElementsAre;
using ::testing::HasSubstr;

const Catalog& shipped() {
  static const Catalog catalog = Catalog::load(BEHAVIORLIB_SHIPPED_CATALOG).value();
  return catalog;
}

PlanRequest request(const std::string& target, std::set<std::string> active) {
  PlanRequest r;
  r.robot_id = "drone1";
  r.target = target;
  r.active = std::move(active);
  for (const auto& [name, entry] : shipped().behaviors()) r.available.insert(name);
  return r;
}

// "deactivate X", "check_situation Y", "activate Y".
std::vector<std::string> describe(const Plan& plan) {
  std::vector<std::string> out;
  for (const auto& step : plan.steps)
    out.push_back(std::string(stepKindName(step.kind)) + " " + step.behavior);
  return out;
}

TEST(Planner, ActivatesMissingRequirementsFirstWithTheirDefaults) {
  auto plan = makePlan(shipped(), request("FOLLOW_PATH", {}));
  ASSERT_TRUE(plan.ok()) << plan.status();
  EXPECT_THAT(describe(*plan), ElementsAre("check_situation SELF_LOCALIZE_WITH_GROUND_TRUTH",
                                           "activate SELF_LOCALIZE_WITH_GROUND_TRUTH",
                                           "check_situation QUADROTOR_PID_MOTION_CONTROL",
                                           "activate QUADROTOR_PID_MOTION_CONTROL",
                                           "check_situation FOLLOW_PATH", "activate FOLLOW_PATH"));
  EXPECT_EQ(plan->steps[1].reason, "provides self_localization required by FOLLOW_PATH");
  EXPECT_EQ(plan->steps.back().reason, "the target");
}

TEST(Planner, AnActiveProviderSatisfiesARequirement) {
  auto plan = makePlan(shipped(), request("FOLLOW_PATH", {"SELF_LOCALIZE_WITH_EKF_SENSOR_FUSION",
                                                          "QUADROTOR_MPC_MOTION_CONTROL"}));
  ASSERT_TRUE(plan.ok()) << plan.status();
  EXPECT_THAT(describe(*plan), ElementsAre("check_situation FOLLOW_PATH", "activate FOLLOW_PATH"));
}

TEST(Planner, DeactivatesWhatHoldsTheSameResource) {
  auto plan = makePlan(shipped(), request("FOLLOW_PATH", {"SELF_LOCALIZE_WITH_GROUND_TRUTH",
                                                          "QUADROTOR_PID_MOTION_CONTROL",
                                                          "ROTATE_WITH_PID_CONTROL"}));
  ASSERT_TRUE(plan.ok()) << plan.status();
  EXPECT_THAT(describe(*plan), ElementsAre("deactivate ROTATE_WITH_PID_CONTROL",
                                           "check_situation FOLLOW_PATH", "activate FOLLOW_PATH"));
  EXPECT_EQ(plan->steps[0].reason, "holds motion_reference, which FOLLOW_PATH needs");
}

TEST(Planner, SwitchingMotionControllersKeepsTheirUsers) {
  auto plan = makePlan(shipped(), request("QUADROTOR_MPC_MOTION_CONTROL",
                                          {"SELF_LOCALIZE_WITH_GROUND_TRUTH",
                                           "QUADROTOR_PID_MOTION_CONTROL", "FOLLOW_PATH"}));
  ASSERT_TRUE(plan.ok()) << plan.status();
  EXPECT_THAT(describe(*plan), ElementsAre("deactivate QUADROTOR_PID_MOTION_CONTROL",
                                           "check_situation QUADROTOR_MPC_MOTION_CONTROL",
                                           "activate QUADROTOR_MPC_MOTION_CONTROL"));
}

TEST(Planner, ARequirementsConflictsAreDeactivatedToo) {
  // ROTATE_WITH_MPC_CONTROL needs the MPC controller, which takes the
  // platform from the PID controller, which FOLLOW_PATH uses (it goes first).
  auto plan = makePlan(shipped(), request("ROTATE_WITH_MPC_CONTROL",
                                          {"SELF_LOCALIZE_WITH_GROUND_TRUTH",
                                           "QUADROTOR_PID_MOTION_CONTROL", "FOLLOW_PATH"}));
  ASSERT_TRUE(plan.ok()) << plan.status();
  EXPECT_THAT(
      describe(*plan),
      ElementsAre("deactivate FOLLOW_PATH", "deactivate QUADROTOR_PID_MOTION_CONTROL",
                  "check_situation QUADROTOR_MPC_MOTION_CONTROL",
                  "activate QUADROTOR_MPC_MOTION_CONTROL",
                  "check_situation ROTATE_WITH_MPC_CONTROL", "activate ROTATE_WITH_MPC_CONTROL"));
}

TEST(Planner, BehaviorsThatWouldLoseARequirementAreDeactivatedFirst) {
  // LAND takes the platform from the motion controller; FOLLOW_PATH would
  // lose motion_control (and LAND holds the motion reference too).
  auto plan = makePlan(
      shipped(), request("LAND", {"SELF_LOCALIZE_WITH_GROUND_TRUTH", "QUADROTOR_PID_MOTION_CONTROL",
                                  "KEEP_HOVERING_WITH_PID_CONTROL", "WAIT"}));
  ASSERT_TRUE(plan.ok()) << plan.status();
  EXPECT_THAT(describe(*plan), ElementsAre("deactivate KEEP_HOVERING_WITH_PID_CONTROL",
                                           "deactivate QUADROTOR_PID_MOTION_CONTROL",
                                           "check_situation LAND", "activate LAND"));
}

TEST(Planner, ReplacingTheEstimatorKeepsItsUsers) {
  auto plan = makePlan(shipped(), request("SELF_LOCALIZE_WITH_EKF_SENSOR_FUSION",
                                          {"SELF_LOCALIZE_WITH_GROUND_TRUTH", "FOLLOW_PATH",
                                           "QUADROTOR_PID_MOTION_CONTROL"}));
  ASSERT_TRUE(plan.ok()) << plan.status();
  EXPECT_THAT(describe(*plan), ElementsAre("deactivate SELF_LOCALIZE_WITH_GROUND_TRUTH",
                                           "check_situation SELF_LOCALIZE_WITH_EKF_SENSOR_FUSION",
                                           "activate SELF_LOCALIZE_WITH_EKF_SENSOR_FUSION"));
}

// Decision 45: the catalog's defaults are for a requirement the plan
// activates on its own; the target gets the caller's parameters alone (its
// unset fields take the proto's defaults in the behavior system).
TEST(Planner, CatalogDefaultsGoToRequirementsNotTheTarget) {
  auto catalog = Catalog::parse(
      "capabilities:\n  loc: {default: LOC}\n"
      "behaviors:\n"
      "  LOC:\n    provides: [loc]\n    defaults: {rate_hz: 5.0}\n"
      "  MOVE:\n    requires: [loc]\n    defaults: {speed_m_s: 1.0, height_m: 2.0}\n",
      "c.yaml");
  ASSERT_TRUE(catalog.ok()) << catalog.status();
  PlanRequest r;
  r.robot_id = "drone1";
  r.target = "MOVE";
  r.available = {"MOVE", "LOC"};
  (*r.parameters.mutable_fields())["speed_m_s"].set_number_value(3.0);
  auto plan = makePlan(*catalog, r);
  ASSERT_TRUE(plan.ok()) << plan.status();
  std::map<std::string, google::protobuf::Struct> activated;
  for (const auto& step : plan->steps) {
    if (step.kind == StepKind::kActivate) activated[step.behavior] = step.parameters;
  }
  ASSERT_EQ(activated.size(), 2u);
  const auto& target = activated.at("MOVE").fields();
  EXPECT_DOUBLE_EQ(target.at("speed_m_s").number_value(), 3.0);
  EXPECT_FALSE(target.contains("height_m"));  // not the catalog's: the proto's, in the system
  EXPECT_DOUBLE_EQ(activated.at("LOC").fields().at("rate_hz").number_value(), 5.0);
}

TEST(Planner, RefusesWithReasons) {
  auto active = makePlan(shipped(), request("WAIT", {"WAIT"}));
  EXPECT_EQ(active.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(std::string(active.status().message()), HasSubstr("WAIT is already active"));

  PlanRequest missing = request("FOLLOW_PATH", {});
  missing.available.erase("QUADROTOR_PID_MOTION_CONTROL");
  auto no_provider = makePlan(shipped(), missing);
  EXPECT_EQ(no_provider.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(std::string(no_provider.status().message()),
              HasSubstr("FOLLOW_PATH requires motion_control; its default provider "
                        "QUADROTOR_PID_MOTION_CONTROL is not hosted"));

  PlanRequest unknown = request("FLY_TO_MARS", {});
  EXPECT_EQ(makePlan(shipped(), unknown).status().code(), absl::StatusCode::kNotFound);
}

// Records every call; fails where told.
class FakeActions : public PlanActions {
 public:
  std::vector<std::string> calls;
  std::map<std::string, absl::Status> activate_fails, situation_fails, deactivate_fails;
  int situation_failures_left = 0;  // for the behavior in situation_fails, then OK

  absl::Status checkSituation(const std::string& b) override {
    calls.push_back("check_situation " + b);
    auto it = situation_fails.find(b);
    if (it == situation_fails.end()) return absl::OkStatus();
    if (situation_failures_left > 0 && --situation_failures_left == 0) situation_fails.erase(it);
    return absl::FailedPreconditionError("no fresh pose estimate");
  }
  absl::StatusOr<std::string> activate(const std::string& b,
                                       const google::protobuf::Struct&) override {
    calls.push_back("activate " + b);
    if (auto it = activate_fails.find(b); it != activate_fails.end()) return it->second;
    return "id-" + b;
  }
  absl::Status deactivate(const std::string& b) override {
    calls.push_back("deactivate " + b);
    if (auto it = deactivate_fails.find(b); it != deactivate_fails.end()) return it->second;
    return absl::OkStatus();
  }
};

ApplyOptions instant() {
  ApplyOptions options;
  options.sleep = [](std::chrono::milliseconds) {};
  return options;
}

TEST(ApplyPlan, RunsTheStepsInOrder) {
  auto plan = makePlan(shipped(), request("FOLLOW_PATH", {"ROTATE_WITH_PID_CONTROL"}));
  ASSERT_TRUE(plan.ok()) << plan.status();
  FakeActions actions;
  auto result = applyPlan(*plan, actions, instant());
  ASSERT_TRUE(result.ok()) << result.status();
  EXPECT_EQ(result->activation_id, "id-FOLLOW_PATH");
  EXPECT_EQ(result->activated.size(), 3u);
  EXPECT_THAT(result->deactivated, ElementsAre("ROTATE_WITH_PID_CONTROL"));
  EXPECT_EQ(actions.calls, describe(*plan));
}

TEST(ApplyPlan, AFailingStepStopsWhatThePlanStartedAndNamesTheStep) {
  auto plan = makePlan(shipped(), request("FOLLOW_PATH", {}));
  ASSERT_TRUE(plan.ok());
  FakeActions actions;
  actions.activate_fails["FOLLOW_PATH"] = absl::InvalidArgumentError("path is empty");
  auto result = applyPlan(*plan, actions, instant());
  ASSERT_FALSE(result.ok());
  EXPECT_EQ(result.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(
      std::string(result.status().message()),
      HasSubstr("step 6 of 6 (activate FOLLOW_PATH) on robot 'drone1' failed: path is empty"));
  EXPECT_THAT(actions.calls,
              ElementsAre("check_situation SELF_LOCALIZE_WITH_GROUND_TRUTH",
                          "activate SELF_LOCALIZE_WITH_GROUND_TRUTH",
                          "check_situation QUADROTOR_PID_MOTION_CONTROL",
                          "activate QUADROTOR_PID_MOTION_CONTROL", "check_situation FOLLOW_PATH",
                          "activate FOLLOW_PATH", "deactivate QUADROTOR_PID_MOTION_CONTROL",
                          "deactivate SELF_LOCALIZE_WITH_GROUND_TRUTH"));
}

TEST(ApplyPlan, AConflictThatAlreadyFinishedIsNotAFailureButAnUnreachableSystemIs) {
  auto plan = makePlan(shipped(), request("FOLLOW_PATH", {"ROTATE_WITH_PID_CONTROL"}));
  ASSERT_TRUE(plan.ok());
  FakeActions actions;
  actions.deactivate_fails["ROTATE_WITH_PID_CONTROL"] =
      absl::FailedPreconditionError("cannot deactivate ROTATE_WITH_PID_CONTROL: it is not active");
  auto result = applyPlan(*plan, actions, instant());
  ASSERT_TRUE(result.ok()) << result.status();
  EXPECT_TRUE(result->deactivated.empty());
  EXPECT_EQ(result->activation_id, "id-FOLLOW_PATH");

  FakeActions down;
  down.deactivate_fails["ROTATE_WITH_PID_CONTROL"] = absl::UnavailableError("system is down");
  auto failed = applyPlan(*plan, down, instant());
  EXPECT_EQ(failed.status().code(), absl::StatusCode::kUnavailable);
  EXPECT_THAT(std::string(failed.status().message()),
              HasSubstr("(deactivate ROTATE_WITH_PID_CONTROL)"));
}

TEST(ApplyPlan, ASituationThatDependsOnAJustStartedRequirementIsRetried) {
  auto plan = makePlan(shipped(), request("FOLLOW_PATH", {"QUADROTOR_PID_MOTION_CONTROL"}));
  ASSERT_TRUE(plan.ok());
  FakeActions actions;
  actions.situation_fails["FOLLOW_PATH"] = absl::OkStatus();
  actions.situation_failures_left = 3;
  auto result = applyPlan(*plan, actions, instant());
  ASSERT_TRUE(result.ok()) << result.status();
  // Three refusals, then it holds.
  EXPECT_EQ(std::count(actions.calls.begin(), actions.calls.end(), "check_situation FOLLOW_PATH"),
            4);
}

TEST(ApplyPlan, ASituationThatNeverHoldsIsRetriedOnlyForTheStateLagWhenNothingWasStarted) {
  auto plan = makePlan(shipped(), request("WAIT", {}));
  ASSERT_TRUE(plan.ok());
  FakeActions actions;
  actions.situation_fails["WAIT"] = absl::OkStatus();
  ApplyOptions options = instant();
  options.lag_timeout = std::chrono::milliseconds(200);
  options.settle_poll = std::chrono::milliseconds(50);
  auto result = applyPlan(*plan, actions, options);
  EXPECT_EQ(result.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(std::string(result.status().message()),
              HasSubstr("step 1 of 2 (check_situation WAIT)"));
  // The first check and four retries over the 200 ms lag window; nothing
  // activated.
  EXPECT_EQ(actions.calls, std::vector<std::string>(5, "check_situation WAIT"));
}

TEST(ApplyPlan, ARefusalFromStaleStateClearsWithinTheLagWindow) {
  auto plan = makePlan(shipped(), request("WAIT", {}));
  ASSERT_TRUE(plan.ok());
  FakeActions actions;
  actions.situation_fails["WAIT"] = absl::OkStatus();
  actions.situation_failures_left = 2;
  auto result = applyPlan(*plan, actions, instant());
  ASSERT_TRUE(result.ok()) << result.status();
  EXPECT_EQ(result->activation_id, "id-WAIT");
}

}  // namespace
}  // namespace behaviorlib::coordinator
