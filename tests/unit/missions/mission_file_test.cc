#include "coordinator/mission/mission_file.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <map>
#include <sstream>
#include <string>

#include "behaviorlib/error_details.h"

namespace behaviorlib::coordinator {
namespace {

using ::testing::ElementsAre;
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
            "'on', 'if' and 'when' are for steps only", "safety[0].on"},
        BadMission{"steps:\n  - behavior: A\n    on:\n      TIME_OUT: {fallback: []}\n", 4,
                   "fallback: empty", "steps[0].on.TIME_OUT.fallback"},
        BadMission{"steps: [\n", 2, "not valid YAML", ""},
        // Parallel branches and waits.
        BadMission{"steps:\n  - parallel: {branches: [{behavior: A}]}\n", 2,
                   "a list of 2 to 16 branches", "steps[0].parallel.branches"},
        BadMission{"steps:\n  - parallel:\n      end: most\n      branches: [{behavior: A}, "
                   "{behavior: B}]\n",
                   3, "'most' (all or any)", "steps[0].parallel.end"},
        BadMission{"steps:\n  - behavior: A\n    parallel: {branches: [{behavior: A}, {behavior: "
                   "B}]}\n",
                   2, "'parallel' goes with no 'behavior'", "steps[0].behavior"},
        BadMission{"steps:\n  - parallel:\n      branches:\n        - {robot: \"\", behavior: A}\n"
                   "        - {behavior: B}\n",
                   4, "a robot id of 1 to 128 characters", "steps[0].parallel.branches[0].robot"},
        BadMission{"steps:\n  - wait_for: {step: up}\n", 2, "needs 'timeout_s'",
                   "steps[0].wait_for"},
        BadMission{"steps:\n  - wait_for: {step: up, timeout_s: 0}\n", 2, "needs 'timeout_s'",
                   "steps[0].wait_for.timeout_s"},
        BadMission{"steps:\n  - name: down\n    behavior: A\n  - wait_for: {step: up, timeout_s: "
                   "5}\n",
                   4, "wait_for step 'up': no step of the mission has that name (named: down)",
                   "steps[1].wait_for.step"},
        BadMission{"steps:\n  - wait_for: {belief: k, timeout_s: 5}\n", 2,
                   "exactly one of 'exists' and 'equals'", "steps[0].wait_for"},
        // Conditions on the vehicle.
        BadMission{"steps:\n  - behavior: A\n    when: [{battery_below: 1.5}]\n", 3,
                   "battery_below: a number in [0, 1]", "steps[0].when[0].battery_below"},
        BadMission{"steps:\n  - behavior: A\n    when: [{near: {point_m: [1, 2]}, radius_m: 1}]\n",
                   3, "unknown key 'radius_m'", "steps[0].when[0].radius_m"},
        BadMission{"steps:\n  - behavior: A\n    when: [{battery_below: 0.2, ends: ABORT}]\n", 3,
                   "ends: 'ABORT' (GOAL_ACHIEVED, SITUATION_CHANGE", "steps[0].when[0].ends"},
        BadMission{"steps:\n  - wait_for: {belief: k, exists: true, timeout_s: 5}\n    when: "
                   "[{battery_below: 0.2}]\n",
                   3, "'when' goes with a 'behavior'", "steps[0].when"},
        BadMission{"safety:\n  - wait_for: {belief: k, exists: true, timeout_s: 5}\n"
                   "steps:\n  - behavior: A\n",
                   2, "'parallel' and 'wait_for' are for steps only", "safety[0]"}));

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

// A sub-mission is defined once with typed parameters and called as a step:
// each call's steps are its own, with the call's values in place of
// ${param.x} (a whole value, or a part of a text), and the defaults where
// the call gives none.
constexpr const char* kRooms = R"(name: rooms
robot: drone1
submissions:
  plan_and_fly:
    parameters:
      goal_m: {type: list, description: where to go}
      speed_m_s: {type: number, default: 1.0, min: 0.1, max: 3}
      room: {type: string, default: "?"}
    steps:
      - name: plan
        behavior: GENERATE_PATH
        parameters: {goal_m: "${param.goal_m}", belief_key: "drone1/path_${param.room}"}
      - name: fly
        behavior: FOLLOW_PATH
        parameters: {path_m: "${belief.drone1/path_${param.room}}", speed_m_s: "${param.speed_m_s}"}
steps:
  - name: room_b
    call: plan_and_fly
    with: {goal_m: [1, 2, 3], room: b}
    on:
      WRONG_PROGRESS: {retry: 1}
  - call: plan_and_fly
    with: {goal_m: [4, 5, 6], speed_m_s: 2.5, room: c}
)";

TEST(MissionFile, ASubMissionIsCalledWithItsParameters) {
  auto mission = parseMission(kRooms, "rooms.yaml");
  ASSERT_TRUE(mission.ok()) << mission.status();
  EXPECT_EQ(mission->submissions, std::vector<std::string>{"plan_and_fly"});
  ASSERT_EQ(mission->steps.size(), 2u);
  const MissionStep& b = mission->steps[0];
  EXPECT_EQ(b.call, "plan_and_fly");
  EXPECT_TRUE(b.behavior.empty());
  EXPECT_EQ(b.on.at("WRONG_PROGRESS").retries, 1);
  ASSERT_EQ(b.body.size(), 2u);
  EXPECT_EQ(b.body[0].behavior, "GENERATE_PATH");
  EXPECT_EQ(b.body[0].line, 10) << "the sub-mission's own line";
  EXPECT_EQ(b.body[0].parameters.fields().at("goal_m").list_value().values_size(), 3);
  EXPECT_EQ(b.body[0].parameters.fields().at("belief_key").string_value(), "drone1/path_b");
  EXPECT_EQ(b.body[1].parameters.fields().at("path_m").string_value(), "${belief.drone1/path_b}");
  EXPECT_EQ(b.body[1].parameters.fields().at("speed_m_s").number_value(), 1.0) << "the default";
  const MissionStep& c = mission->steps[1];
  EXPECT_EQ(c.body[1].parameters.fields().at("speed_m_s").number_value(), 2.5);
  EXPECT_EQ(c.body[0].parameters.fields().at("belief_key").string_value(), "drone1/path_c");
  // The check goes into the calls: a behavior nobody hosts is named once,
  // at its line in the sub-mission.
  v1::BehaviorDescription follow;
  follow.set_name("FOLLOW_PATH");
  for (const char* name : {"path_m", "speed_m_s"}) follow.add_parameters()->set_name(name);
  follow.mutable_parameters(1)->set_type("number");
  follow.mutable_parameters(0)->set_type("object");
  follow.mutable_parameters(0)->set_repeated(true);
  const MissionProblems problems = checkMissionProblems(
      *mission,
      [&](const std::string& /*robot*/, const std::string& name) -> const v1::BehaviorDescription* {
        return name == "FOLLOW_PATH" ? &follow : nullptr;
      });
  ASSERT_EQ(problems.list.size(), 1u) << problems.status();
  EXPECT_EQ(problems.list[0].description,
            "rooms.yaml:10: behavior GENERATE_PATH is not hosted by any registered system of "
            "robot 'drone1'");
}

TEST(MissionFile, ACallIsCheckedAgainstTheSubMissionsParameters) {
  const std::string head =
      std::string(kRooms).substr(0, std::string(kRooms).find("steps:\n  - name"));
  struct Case {
    std::string steps;
    std::string message;
  };
  for (const Case& c : std::vector<Case>{
           {"steps: [{call: nope}]\n", "no sub-mission 'nope' (defined: plan_and_fly)"},
           {"steps: [{call: plan_and_fly}]\n", "needs parameter 'goal_m': where to go"},
           {"steps: [{call: plan_and_fly, with: {goal_m: [1], height: 2}}]\n",
            "has no parameter 'height' (its parameters: goal_m, speed_m_s, room)"},
           {"steps: [{call: plan_and_fly, with: {goal_m: 5}}]\n", "with goal_m: expected a list"},
           {"steps: [{call: plan_and_fly, with: {goal_m: [1], speed_m_s: 9}}]\n",
            "with speed_m_s: 9 is out of range [0.1, 3]"},
           {"steps: [{call: plan_and_fly, behavior: WAIT}]\n", "give 'behavior' or 'call'"},
           {"steps: [{behavior: WAIT, with: {a: 1}}]\n", "'with' goes with 'call'"},
           {"steps: [{behavior: WAIT, parameters: {d: \"${param.x}\"}}]\n",
            "${param.x} is only for a sub-mission's steps"},
       }) {
    auto mission = parseMission(head + c.steps, "rooms.yaml");
    ASSERT_FALSE(mission.ok()) << c.steps;
    EXPECT_THAT(std::string(mission.status().message()), HasSubstr(c.message)) << c.steps;
    EXPECT_THAT(std::string(mission.status().message()), HasSubstr("rooms.yaml:"));
  }
  // A sub-mission that calls itself, through another.
  auto loop = parseMission(R"(robot: drone1
submissions:
  a: {steps: [{call: b}]}
  b: {steps: [{behavior: WAIT}, {call: a}]}
steps: [{call: a}]
)",
                           "loop.yaml");
  ASSERT_FALSE(loop.ok());
  EXPECT_THAT(
      std::string(loop.status().message()),
      HasSubstr("loop.yaml:4: submission 'b' step: sub-mission 'a' calls itself (a -> b -> a)"));
  // A parameter the steps use but the sub-mission does not declare.
  auto undeclared = parseMission(R"(robot: drone1
submissions:
  s:
    parameters: {a: {type: number}}
    steps: [{behavior: WAIT, parameters: {duration_s: "${param.b}"}}]
steps: [{call: s, with: {a: 1}}]
)",
                                 "u.yaml");
  ASSERT_FALSE(undeclared.ok());
  EXPECT_THAT(std::string(undeclared.status().message()),
              HasSubstr("u.yaml:5: submission 's': ${param.b} is not one of its parameters"));
}

TEST(MissionFile, SubMissionsAreImportedFromTheMissionDirectory) {
  const std::map<std::string, std::string> files = {
      {"common/fly.yaml",
       "description: shared\nsubmissions:\n  fly:\n"
       "    parameters: {to: {type: number}}\n"
       "    steps:\n      - behavior: TAKE_OFF\n"
       "        parameters: {altitude_m: \"${param.to}\"}\n"},
      {"bad.yaml", "submissions:\n  broken: {steps: []}\n"}};
  const ImportReader reader = [&](const std::string& path) -> absl::StatusOr<std::string> {
    auto it = files.find(path);
    if (it == files.end()) return absl::NotFoundError("no such file");
    return it->second;
  };
  auto mission = parseMission(
      "robot: drone1\nimport: [common/fly.yaml]\nsteps: [{call: fly, with: {to: 2}}]\n", "m.yaml",
      reader);
  ASSERT_TRUE(mission.ok()) << mission.status();
  EXPECT_EQ(mission->imports.at("common/fly.yaml"), files.at("common/fly.yaml"));
  const MissionStep& take_off = mission->steps[0].body.at(0);
  EXPECT_EQ(take_off.file, "common/fly.yaml");
  EXPECT_EQ(take_off.line, 6);
  EXPECT_EQ(take_off.parameters.fields().at("altitude_m").number_value(), 2);
  // A problem in an imported file names that file; a missing one, the import.
  auto bad = parseMission("robot: drone1\nimport: [bad.yaml]\nsteps: [{behavior: WAIT}]\n",
                          "m.yaml", reader);
  ASSERT_FALSE(bad.ok());
  EXPECT_THAT(std::string(bad.status().message()), HasSubstr("bad.yaml:2: "));
  auto missing = parseMission("robot: drone1\nimport: nowhere.yaml\nsteps: [{behavior: WAIT}]\n",
                              "m.yaml", reader);
  EXPECT_THAT(std::string(missing.status().message()),
              HasSubstr("m.yaml:2: import 'nowhere.yaml': no such file"));
  auto no_dir =
      parseMission("robot: drone1\nimport: [common/fly.yaml]\nsteps: [{call: fly}]\n", "m.yaml");
  EXPECT_THAT(std::string(no_dir.status().message()), HasSubstr("cannot import files"));
}

// Every loop has a bound: a repeat-until without max_times, a loop without
// steps, or more items than max_items is refused with its line.
TEST(MissionFile, ALoopWithoutABoundIsRefused) {
  struct Case {
    std::string step;
    std::string message;
  };
  for (const Case& c : std::vector<Case>{
           {"  - repeat: {until: {belief: d/x, exists: true}}\n    steps: [{behavior: A}]\n",
            "t.yaml:3: steps step repeat: 'until' needs 'max_times' (every loop has a bound"},
           {"  - repeat: {}\n    steps: [{behavior: A}]\n", "needs 'times', or 'until' with"},
           {"  - repeat: {times: 0}\n    steps: [{behavior: A}]\n",
            "repeat times: a whole number, 1..1000"},
           {"  - repeat: {times: 2}\n", "a loop needs 'steps'"},
           {"  - for_each: {in: [1, 2, 3], as: i, max_items: 2}\n    steps: [{behavior: A}]\n",
            "3 items, more than max_items 2"},
           {"  - for_each: {in: 5, as: i}\n    steps: [{behavior: A}]\n",
            "expected a list, or {belief: key}"},
           {"  - behavior: A\n    steps: [{behavior: B}]\n",
            "'steps' goes with 'for_each' or 'repeat'"},
       }) {
    auto mission = parseMission("robot: drone1\nsteps:\n" + c.step, "t.yaml");
    ASSERT_FALSE(mission.ok()) << c.step;
    EXPECT_THAT(std::string(mission.status().message()), HasSubstr(c.message)) << c.step;
  }
}

TEST(MissionFile, CheckedAgainstTheRegisteredBehaviorsBeforeAnythingFlies) {
  auto mission = parseMission(kMission, "demo.yaml");
  ASSERT_TRUE(mission.ok());
  std::map<std::string, v1::BehaviorDescription> registered;
  for (const char* name : {"SELF_LOCALIZE_WITH_GROUND_TRUTH", "LAND", "TAKE_OFF", "FOLLOW_PATH"}) {
    registered[name] = description(name);
  }
  auto lookup = [&](const std::string& /*robot*/,
                    const std::string& b) -> const v1::BehaviorDescription* {
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
  auto lookup = [&](const std::string& /*robot*/,
                    const std::string& b) -> const v1::BehaviorDescription* {
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
      *mission, [](const std::string&, const std::string&) -> const v1::BehaviorDescription* {
        return nullptr;
      });
  EXPECT_THAT(std::string(checked.message()), HasSubstr("60 problems in the mission"));
  EXPECT_THAT(std::string(checked.message()), HasSubstr("... and 10 more"));
  ASSERT_TRUE(errors::badRequest(checked).has_value());
  EXPECT_EQ(errors::badRequest(checked)->field_violations_size(), 50);
}

// A fleet mission: steps and branches name their robots (inherited by
// what they contain); the check looks each behavior up on its step's robot.
TEST(MissionFile, AFleetMissionsStepsAreCheckedOnTheirRobots) {
  auto mission = parseMission(R"(name: fleet
robot: drone1
safety:
  - {robot: drone2, behavior: LAND}
steps:
  - parallel:
      branches:
        - {behavior: TAKE_OFF}
        - robot: drone2
          steps:
            - behavior: TAKE_OFF
            - behavior: SCAN
              on: {TIME_OUT: {fallback: [{behavior: HOVER}]}}
  - {robot: drone3, wait_for: {belief: drone2/done, exists: true, timeout_s: 60}}
)",
                              "fleet.yaml");
  ASSERT_TRUE(mission.ok()) << mission.status();
  EXPECT_THAT(mission->robots, ElementsAre("drone2", "drone3"));
  EXPECT_THAT(missionRobots(*mission, "drone1"), ElementsAre("drone1", "drone2", "drone3"));
  EXPECT_THAT(missionRobots(*mission, "drone2"), ElementsAre("drone2", "drone3"));
  const auto& branches = mission->steps[0].parallel->branches;
  ASSERT_EQ(branches.size(), 2u);
  EXPECT_EQ(branches[0].steps[0].robot, "");
  EXPECT_EQ(branches[1].steps[1].robot, "drone2");
  EXPECT_EQ(branches[1].steps[1].on.at("TIME_OUT").fallback[0].robot, "drone2");
  EXPECT_DOUBLE_EQ(mission->steps[1].wait->timeout_s, 60);
  // drone2 hosts no SCAN and no HOVER; drone1 hosts everything.
  std::vector<std::string> asked;
  const MissionProblems problems = checkMissionProblems(
      *mission,
      [&](const std::string& robot, const std::string& behavior) -> const v1::BehaviorDescription* {
        static const v1::BehaviorDescription d;
        asked.push_back((robot.empty() ? "drone1" : robot) + ":" + behavior);
        return robot == "drone2" && (behavior == "SCAN" || behavior == "HOVER") ? nullptr : &d;
      });
  ASSERT_EQ(problems.list.size(), 2u) << problems.status();
  EXPECT_EQ(
      problems.list[0].description,
      "fleet.yaml:12: behavior SCAN is not hosted by any registered system of robot 'drone2'");
  EXPECT_EQ(problems.list[1].description,
            "fleet.yaml:13: behavior HOVER is not hosted by any registered system of robot "
            "'drone2'");
  EXPECT_THAT(asked, ::testing::Contains("drone2:LAND"));
}

// Every shipped mission parses (its sub-missions imported from the mission
// directory), the fleet ones name the robots they command, and none
// localizes on the ground truth.
TEST(MissionFile, EveryShippedMissionParses) {
  const std::filesystem::path dir = BEHAVIORLIB_SHIPPED_MISSIONS_DIR;
  const ImportReader read = [&](const std::string& path) -> absl::StatusOr<std::string> {
    std::ifstream in(dir / path);
    if (!in) return absl::NotFoundError(path);
    std::stringstream text;
    text << in.rdbuf();
    return text.str();
  };
  int parsed = 0;
  for (const auto& entry : std::filesystem::directory_iterator(dir)) {
    if (entry.path().extension() != ".yaml") continue;
    SCOPED_TRACE(entry.path().filename().string());
    absl::StatusOr<std::string> text = read(entry.path().filename().string());
    ASSERT_TRUE(text.ok());
    auto mission = parseMission(*text, entry.path().filename().string(), read);
    ASSERT_TRUE(mission.ok()) << mission.status();
    EXPECT_FALSE(mission->robot_id.empty());
    if (entry.path().filename() == "swarm_two_vehicles.yaml") {
      EXPECT_THAT(missionRobots(*mission, mission->robot_id), ElementsAre("drone1", "drone2"));
    }
    // A vehicle has no ground truth: every shipped mission localizes on an
    // estimator it has (the EKF, the lidar SLAM); the ground truth is the
    // tests' (decision 49).
    EXPECT_EQ(text->find("SELF_LOCALIZE_WITH_GROUND_TRUTH"), std::string::npos);
    ++parsed;
  }
  EXPECT_GE(parsed, 7);
}

}  // namespace
}  // namespace behaviorlib::coordinator
