// behaviorctl's output forms (clients/behaviorctl/behaviorctl_output.h): an
// aligned table with "-" for an empty cell, kubectl's ages on a given clock,
// the -o values, YAML from a reply, and an error's reason and fields.

#include "clients/behaviorctl/behaviorctl_output.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <chrono>

#include "behaviorlib/error_details.h"
#include "behaviorlib/errors/status_details.h"

namespace behaviorlib::behaviorctl {
namespace {

using ::testing::HasSubstr;

std::chrono::system_clock::time_point at(int64_t seconds) {
  return std::chrono::system_clock::time_point(std::chrono::seconds(seconds));
}

google::protobuf::Timestamp stamp(int64_t seconds) {
  google::protobuf::Timestamp t;
  t.set_seconds(seconds);
  return t;
}

TEST(TableTest, ColumnsAlignUnderTheirHeadersAndAnEmptyCellIsADash) {
  const Table table{{"ROBOT", "STATE", "ACTIVATION"},
                    {{"drone1", "ACTIVE", "WAIT-1"}, {"a-longer-robot", "", ""}}};
  EXPECT_EQ(table.render(),
            "ROBOT           STATE   ACTIVATION\n"
            "drone1          ACTIVE  WAIT-1\n"
            "a-longer-robot  -       -\n");
}

TEST(AgeTest, SecondsThenMinutesHoursAndDaysAsKubectlPrintsThem) {
  EXPECT_EQ(age(stamp(1000), at(1045)), "45s");
  EXPECT_EQ(age(stamp(1000), at(1000 + 119)), "119s");
  EXPECT_EQ(age(stamp(1000), at(1000 + 12 * 60)), "12m");
  EXPECT_EQ(age(stamp(1000), at(1000 + 5 * 3600)), "5h");
  EXPECT_EQ(age(stamp(1000), at(1000 + 3 * 86400)), "3d");
  EXPECT_EQ(age(stamp(2000), at(1000)), "0s");  // a clock behind the server's
  EXPECT_EQ(age(google::protobuf::Timestamp(), at(1000)), "");
}

TEST(OutputFormatTest, TheFourFormsAndTheDefault) {
  EXPECT_EQ(*parseOutputFormat("", OutputFormat::kTable), OutputFormat::kTable);
  EXPECT_EQ(*parseOutputFormat("", OutputFormat::kJson), OutputFormat::kJson);
  EXPECT_EQ(*parseOutputFormat("wide", OutputFormat::kJson), OutputFormat::kWide);
  EXPECT_EQ(*parseOutputFormat("yaml", OutputFormat::kTable), OutputFormat::kYaml);
  const auto bad = parseOutputFormat("xml", OutputFormat::kTable);
  ASSERT_FALSE(bad.ok());
  EXPECT_THAT(std::string(bad.status().message()), HasSubstr("table, wide, json, yaml"));
}

TEST(TablesTest, SystemsShowTheirStateShortAndWideAddsWhy) {
  v1::ListSystemsResponse response;
  auto* system = response.add_systems();
  system->set_robot_id("drone1");
  system->set_system("basic_quadrotor_behaviors");
  system->set_state(v1::SYSTEM_STATE_DOWN);
  system->set_address("127.0.0.1:5");
  system->add_behaviors("WAIT");
  *system->mutable_state_time() = stamp(100);
  system->set_state_message("health check failed");
  const Table narrow = systemsTable(response, false, at(190));
  ASSERT_EQ(narrow.rows.size(), 1u);
  EXPECT_EQ(narrow.rows[0], (std::vector<std::string>{"drone1", "basic_quadrotor_behaviors", "DOWN",
                                                      "127.0.0.1:5", "1", "90s"}));
  const Table wide = systemsTable(response, true, at(190));
  EXPECT_EQ(wide.header.back(), "MESSAGE");
  EXPECT_EQ(wide.rows[0].back(), "health check failed");
}

TEST(TablesTest, ABehaviorOfASystemThatIsDownSaysSoAndWideShowsItsSchema) {
  v1::ListFleetBehaviorsResponse response;
  auto* behavior = response.add_behaviors();
  behavior->set_robot_id("drone1");
  behavior->set_system("basic_quadrotor_behaviors");
  behavior->set_system_state(v1::SYSTEM_STATE_DOWN);
  behavior->mutable_description()->set_name("TAKE_OFF");
  auto* parameter = behavior->mutable_description()->add_parameters();
  parameter->set_name("altitude_m");
  parameter->mutable_range()->set_min(0.2);
  parameter->mutable_range()->set_max(30);
  parameter->set_default_json("1.0");
  const Table narrow = fleetBehaviorsTable(response, false);
  EXPECT_EQ(narrow.rows[0][3], "system DOWN");
  const Table wide = fleetBehaviorsTable(response, true);
  EXPECT_EQ(wide.rows[0].back(), "altitude_m [0.2, 30] = 1.0");
}

TEST(TablesTest, AMissionShowsTheStepItIsAt) {
  v1::ListMissionsResponse response;
  auto* mission = response.add_missions();
  mission->set_mission_id("m-1");
  mission->set_state(v1::MISSION_STATE_RUNNING);
  mission->add_steps()->set_name("take_off");
  auto* step = mission->add_steps();
  step->set_behavior("FOLLOW_PATH");
  step->set_state(v1::MISSION_STEP_STATE_RUNNING);
  mission->set_in_safety_steps(true);
  const Table table = missionsTable(response, false, at(0));
  EXPECT_EQ(table.rows[0][3], "RUNNING (safety steps)");
  EXPECT_EQ(table.rows[0][4], "FOLLOW_PATH RUNNING");
}

TEST(MissionCheckTest, ProblemsComeFirstThenEachStepsPlanAndWideAddsTheReasons) {
  v1::CheckMissionResponse response;
  response.set_name("demo");
  response.set_robot_id("drone1");
  response.add_problems()->set_description("m.yaml:7: TAKE_OFF parameter 'altitude_m' = 500");
  response.set_problems_left_out(2);
  auto* plan = response.add_plans();
  plan->set_node("steps/0");
  plan->set_name("take_off");
  plan->set_behavior("TAKE_OFF");
  plan->set_line(6);
  auto* step = plan->add_plan();
  step->set_kind(v1::ActivationPlanStep::KIND_DEACTIVATE);
  step->set_behavior("HOVER");
  step->set_reason("holds platform_commands");
  step = plan->add_plan();
  step->set_kind(v1::ActivationPlanStep::KIND_ACTIVATE);
  step->set_behavior("TAKE_OFF");
  step->set_reason("the target");
  auto* bound = response.add_plans();
  bound->set_node("steps/1");
  bound->set_behavior("FOLLOW_PATH");
  bound->set_no_plan("bound to beliefs");
  const std::string text = missionCheckText(response, false);
  EXPECT_EQ(text,
            "m.yaml:7: TAKE_OFF parameter 'altitude_m' = 500\n"
            "... and 2 more\n"
            "mission 'demo' for robot 'drone1': 3 problems\n"
            "\n"
            "NODE     STEP         LINE  PLAN\n"
            "steps/0  take_off     6     deactivate HOVER, activate TAKE_OFF\n"
            "steps/1  FOLLOW_PATH  0     no plan: bound to beliefs\n");
  const std::string wide = missionCheckText(response, true);
  EXPECT_NE(wide.find("steps/0: deactivate HOVER: holds platform_commands\n"), std::string::npos)
      << wide;
  response.clear_problems();
  response.set_problems_left_out(0);
  EXPECT_EQ(missionCheckText(response, false)
                .rfind("mission 'demo' for robot 'drone1': no "
                       "problem found\n",
                       0),
            0u);
}

TEST(TablesTest, ABeliefValueIsCutInTheNarrowTableOnly) {
  v1::ListBeliefsResponse response;
  auto* belief = response.add_beliefs();
  belief->set_key("k");
  belief->mutable_value()->set_string_value(std::string(60, 'x'));
  EXPECT_EQ(beliefsTable(response, false, at(0)).rows[0][1].size(), 40u);
  EXPECT_EQ(beliefsTable(response, true, at(0)).rows[0][1].size(), 62u);  // quoted
}

TEST(YamlTest, AReplyPrintsAsYamlWithItsProtoFieldNames) {
  v1::ListSystemsResponse response;
  response.add_systems()->set_robot_id("drone1");
  response.mutable_systems(0)->set_last_event_seq(7);
  const std::string yaml = toYaml(response);
  EXPECT_THAT(yaml, HasSubstr("systems:"));
  EXPECT_THAT(yaml, HasSubstr("robot_id: drone1"));
  EXPECT_THAT(yaml, HasSubstr("last_event_seq: 7"));
}

TEST(ErrorTest, AnErrorSaysItsCodeReasonAndEachField) {
  absl::Status status = absl::InvalidArgumentError("parameter 'altitude_m' = 500 is out of range");
  status = errors::withReason(status, v1::PARAMETER_OUT_OF_RANGE);
  status = errors::withFieldViolation(status, "parameters.altitude_m", "out of range [0.2, 30]");
  EXPECT_EQ(describeError(errors::toGrpc(status)),
            "behaviorctl: INVALID_ARGUMENT: parameter 'altitude_m' = 500 is out of range\n"
            "  reason: PARAMETER_OUT_OF_RANGE\n"
            "  field parameters.altitude_m: out of range [0.2, 30]\n");
  EXPECT_EQ(describeError(grpc::Status(grpc::StatusCode::UNAVAILABLE, "connection refused")),
            "behaviorctl: UNAVAILABLE: connection refused\n");
}

}  // namespace
}  // namespace behaviorlib::behaviorctl
