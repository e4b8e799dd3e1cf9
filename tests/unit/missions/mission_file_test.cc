#include "coordinator/mission/mission_file.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <map>
#include <string>

#include "behaviorlib/error_details.h"

namespace behaviorlib::coordinator {
namespace {

using ::testing::HasSubstr;

constexpr const char* kMission = R"(name: demo
robot: drone1
recurrent:
  - behavior: SELF_LOCALIZE_WITH_GROUND_TRUTH
safety:
  - behavior: LAND
steps:
  - name: take_off
    behavior: TAKE_OFF
    parameters: {altitude_m: 1.5}
    on:
      TIME_OUT: {retry: 2, then: continue}
      WRONG_PROGRESS:
        fallback:
          - behavior: LAND
      otherwise: abort
  - name: follow
    if: {belief: drone1/path, exists: true}
    behavior: FOLLOW_PATH
    parameters:
      path: "${belief.drone1/path}"
    remember: {followed: true}
  - remember: {done: "yes"}
)";

TEST(MissionFile, ParsesStepsActionsConditionsAndBindings) {
  auto mission = parseMission(kMission, "demo.yaml");
  ASSERT_TRUE(mission.ok()) << mission.status();
  EXPECT_EQ(mission->name, "demo");
  EXPECT_EQ(mission->robot_id, "drone1");
  ASSERT_EQ(mission->steps.size(), 3u);
  ASSERT_EQ(mission->recurrent.size(), 1u);
  ASSERT_EQ(mission->safety.size(), 1u);
  const MissionStep& take_off = mission->steps[0];
  EXPECT_EQ(take_off.line, 8);
  EXPECT_EQ(take_off.parameters.fields().at("altitude_m").number_value(), 1.5);
  EXPECT_EQ(take_off.on.at("TIME_OUT").kind, MissionAction::Kind::kRetry);
  EXPECT_EQ(take_off.on.at("TIME_OUT").retries, 2);
  EXPECT_EQ(take_off.on.at("TIME_OUT").then->kind, MissionAction::Kind::kContinue);
  EXPECT_EQ(take_off.on.at("WRONG_PROGRESS").fallback.at(0).behavior, "LAND");
  const MissionStep& follow = mission->steps[1];
  ASSERT_TRUE(follow.condition.has_value());
  EXPECT_EQ(follow.condition->key, "drone1/path");
  EXPECT_EQ(follow.parameter_lines.at("path"), 21);
  EXPECT_TRUE(mission->steps[2].behavior.empty());
}

struct BadMission {
  std::string text;
  int line;
  std::string problem;
  std::string field;  // the BadRequest field violation's path
};

class MissionFileErrors : public ::testing::TestWithParam<BadMission> {};

TEST_P(MissionFileErrors, NameFileLineAndProblem) {
  auto mission = parseMission(GetParam().text, "m.yaml");
  ASSERT_FALSE(mission.ok());
  EXPECT_EQ(mission.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(mission.status().message()),
              HasSubstr("m.yaml:" + std::to_string(GetParam().line) + ": "));
  EXPECT_THAT(std::string(mission.status().message()), HasSubstr(GetParam().problem));
  // Machine-readable: the reason, and the field with the file and line.
  EXPECT_EQ(errors::reasonOf(mission.status()), "MISSION_INVALID");
  auto bad = errors::badRequest(mission.status());
  ASSERT_TRUE(bad.has_value());
  ASSERT_EQ(bad->field_violations_size(), 1);
  EXPECT_EQ(bad->field_violations(0).field(), GetParam().field);
  EXPECT_EQ(bad->field_violations(0).description(), mission.status().message());
}

INSTANTIATE_TEST_SUITE_P(
    Problems, MissionFileErrors,
    ::testing::Values(
        BadMission{"name: x\n", 1, "missing 'steps'", ""},
        BadMission{"steps: []\n", 1, "'steps' is empty", "steps"},
        BadMission{"steps:\n  - behavior: A\n    param: {}\n", 3, "unknown key 'param'",
                   "steps[0].param"},
        BadMission{"steps:\n  - behavior: A\n    on:\n      TIMEOUT: abort\n", 4,
                   "unknown key 'TIMEOUT'", "steps[0].on.TIMEOUT"},
        BadMission{"steps:\n  - behavior: A\n    on:\n      TIME_OUT: again\n", 4,
                   "unknown action 'again'", "steps[0].on.TIME_OUT"},
        BadMission{"steps:\n  - behavior: A\n    on:\n      TIME_OUT: {retry: 0}\n", 4, "1..100",
                   "steps[0].on.TIME_OUT.retry"},
        BadMission{"steps:\n  - behavior: A\n    parameters: {p: \"${belief.x\"}\n", 3,
                   "unterminated binding", "steps[0].parameters.p"},
        BadMission{"steps:\n  - name: x\n", 2, "needs a 'behavior'", "steps[0]"},
        BadMission{"steps:\n  - behavior: A\n    if: {belief: k}\n", 3,
                   "exactly one of 'exists' and 'equals'", "steps[0].if"},
        BadMission{"steps:\n  - remember: {\"bad key\": 1}\n", 2, "has the character ' '",
                   "steps[0].remember.bad key"},
        BadMission{
            "safety:\n  - behavior: LAND\n    on: {TIME_OUT: abort}\nsteps:\n  - behavior: A\n", 2,
            "'on' and 'if' are for steps only", "safety[0].on"},
        BadMission{"steps:\n  - behavior: A\n    on:\n      TIME_OUT: {fallback: []}\n", 4,
                   "fallback: empty", "steps[0].on.TIME_OUT.fallback"},
        BadMission{"steps: [\n", 2, "not valid YAML", ""}));

v1::BehaviorDescription description(const std::string& name) {
  v1::BehaviorDescription d;
  d.set_name(name);
  auto* p = d.add_parameters();
  p->set_name("altitude_m");
  p->set_type("number");
  auto* path = d.add_parameters();
  path->set_name("path");
  path->set_type("object");
  path->set_repeated(true);
  return d;
}

TEST(MissionFile, CheckedAgainstTheRegisteredBehaviorsBeforeAnythingFlies) {
  auto mission = parseMission(kMission, "demo.yaml");
  ASSERT_TRUE(mission.ok());
  std::map<std::string, v1::BehaviorDescription> registered;
  for (const char* name : {"SELF_LOCALIZE_WITH_GROUND_TRUTH", "LAND", "TAKE_OFF", "FOLLOW_PATH"}) {
    registered[name] = description(name);
  }
  auto lookup = [&](const std::string& b) -> const v1::BehaviorDescription* {
    auto it = registered.find(b);
    return it == registered.end() ? nullptr : &it->second;
  };
  EXPECT_TRUE(checkMission(*mission, lookup).ok());  // the binding is checked later

  registered.erase("LAND");  // used by the safety step and a fallback
  absl::Status missing = checkMission(*mission, lookup);
  EXPECT_EQ(missing.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(
      std::string(missing.message()),
      HasSubstr(
          "demo.yaml:15: behavior LAND is not hosted by any registered system of robot 'drone1'"));
  registered["LAND"] = description("LAND");

  registered["TAKE_OFF"].mutable_parameters()->DeleteSubrange(0, 1);
  absl::Status unknown = checkMission(*mission, lookup);
  EXPECT_THAT(
      std::string(unknown.message()),
      HasSubstr("demo.yaml:10: TAKE_OFF has no parameter 'altitude_m' (its parameters: path)"));

  EXPECT_EQ(errors::reasonOf(unknown), "MISSION_INVALID");
  ASSERT_TRUE(errors::badRequest(unknown).has_value());
  EXPECT_EQ(errors::badRequest(unknown)->field_violations(0).field(),
            "steps[0].parameters.altitude_m");

  registered["TAKE_OFF"] = description("TAKE_OFF");
  registered["TAKE_OFF"].mutable_parameters(0)->set_type("string");
  EXPECT_THAT(std::string(checkMission(*mission, lookup).message()),
              HasSubstr("TAKE_OFF parameter 'altitude_m' must be a string"));

  // A fallback step's path goes through its cause.
  registered.erase("LAND");
  registered["TAKE_OFF"] = description("TAKE_OFF");
  absl::Status in_fallback = checkMission(*mission, lookup);
  ASSERT_TRUE(errors::badRequest(in_fallback).has_value());
  EXPECT_EQ(errors::badRequest(in_fallback)->field_violations(0).field(),
            "steps[0].on.WRONG_PROGRESS.fallback[0].behavior");
}

// Every problem at once, each with its line: a mission with four mistakes
// on four lines is refused naming all four, before anything flies.
TEST(MissionFile, TheCheckFindsEveryProblemAtOnceWithItsLine) {
  auto mission = parseMission(R"(name: four_mistakes
robot: drone1
steps:
  - name: wait
    behavior: WAIT
    parameters: {duration_s: 2}
  - name: take_off
    behavior: TAKE_OFF
    parameters:
      altitude_m: 500
  - name: fly
    behavior: FOLLW_PATH
  - name: land
    behavior: LAND
    parameters: {speed: 1}
  - name: climb
    behavior: TAKE_OFF
    parameters: {altitude_m: [1, 2]}
)",
                              "four.yaml");
  ASSERT_TRUE(mission.ok()) << mission.status();
  std::map<std::string, v1::BehaviorDescription> registered;
  for (const char* name : {"WAIT", "TAKE_OFF", "LAND"})
    registered[name] = v1::BehaviorDescription();
  auto* duration = registered["WAIT"].add_parameters();
  duration->set_name("duration_s");
  duration->set_type("number");
  duration->set_required(true);
  auto* altitude = registered["TAKE_OFF"].add_parameters();
  altitude->set_name("altitude_m");
  altitude->set_type("number");
  altitude->mutable_range()->set_min(0.2);
  altitude->mutable_range()->set_max(30);
  auto lookup = [&](const std::string& b) -> const v1::BehaviorDescription* {
    auto it = registered.find(b);
    return it == registered.end() ? nullptr : &it->second;
  };
  const absl::Status checked = checkMission(*mission, lookup);
  EXPECT_EQ(checked.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(errors::reasonOf(checked), "MISSION_INVALID");
  const std::string message(checked.message());
  EXPECT_THAT(message, HasSubstr("4 problems in the mission"));
  EXPECT_THAT(message,
              HasSubstr("four.yaml:10: TAKE_OFF parameter 'altitude_m' = 500 is out of range "
                        "[0.2, 30]"));
  EXPECT_THAT(message, HasSubstr("four.yaml:11: behavior FOLLW_PATH is not hosted by any "
                                 "registered system of robot 'drone1'"));
  EXPECT_THAT(message, HasSubstr("four.yaml:15: LAND has no parameter 'speed'"));
  EXPECT_THAT(message, HasSubstr("four.yaml:18: TAKE_OFF parameter 'altitude_m' must be a number"));
  auto violations = errors::badRequest(checked);
  ASSERT_TRUE(violations.has_value());
  ASSERT_EQ(violations->field_violations_size(), 4);
  EXPECT_EQ(violations->field_violations(0).field(), "steps[1].parameters.altitude_m");
  EXPECT_EQ(violations->field_violations(1).field(), "steps[2].behavior");
  EXPECT_EQ(violations->field_violations(2).field(), "steps[3].parameters.speed");
  EXPECT_EQ(violations->field_violations(3).field(), "steps[4].parameters.altitude_m");

  // A required parameter left out; a value in range and a list within it pass.
  auto bad_wait = parseMission(
      "steps:\n  - behavior: WAIT\n  - behavior: TAKE_OFF\n"
      "    parameters: {altitude_m: 30}\n",
      "w.yaml");
  ASSERT_TRUE(bad_wait.ok()) << bad_wait.status();
  const absl::Status missing = checkMission(*bad_wait, lookup);
  EXPECT_EQ(std::string(missing.message()), "w.yaml:2: WAIT needs parameter 'duration_s'");
  altitude->set_repeated(true);
  auto in_range = parseMission(
      "steps:\n  - behavior: TAKE_OFF\n    parameters: {altitude_m: "
      "[0.2, 30]}\n",
      "r.yaml");
  ASSERT_TRUE(in_range.ok());
  EXPECT_TRUE(checkMission(*in_range, lookup).ok());
  auto list_out = parseMission(
      "steps:\n  - behavior: TAKE_OFF\n    parameters: {altitude_m: "
      "[1, 0.1]}\n",
      "r.yaml");
  ASSERT_TRUE(list_out.ok());
  EXPECT_THAT(std::string(checkMission(*list_out, lookup).message()),
              HasSubstr("parameter 'altitude_m[1]' = 0.1 is out of range [0.2, 30]"));
}

// At most 50 problems are listed; the rest are counted.
TEST(MissionFile, TheCheckListsAtMostFiftyProblems) {
  std::string text = "steps:\n";
  for (int i = 0; i < 60; ++i) text += "  - behavior: NOT_HOSTED_" + std::to_string(i) + "\n";
  auto mission = parseMission(text, "many.yaml");
  ASSERT_TRUE(mission.ok()) << mission.status();
  const absl::Status checked = checkMission(
      *mission, [](const std::string&) -> const v1::BehaviorDescription* { return nullptr; });
  EXPECT_THAT(std::string(checked.message()), HasSubstr("60 problems in the mission"));
  EXPECT_THAT(std::string(checked.message()), HasSubstr("... and 10 more"));
  ASSERT_TRUE(errors::badRequest(checked).has_value());
  EXPECT_EQ(errors::badRequest(checked)->field_violations_size(), 50);
}

}  // namespace
}  // namespace behaviorlib::coordinator
