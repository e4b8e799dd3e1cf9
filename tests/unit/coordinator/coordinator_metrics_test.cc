// The coordinator's mission counters: what ended a mission (its `cause`
// label) and the outcome counted once per ended mission.

#include "coordinator/metrics/coordinator_metrics.h"

#include <gtest/gtest.h>
#include <prometheus/metric_family.h>

namespace behaviorlib::coordinator {
namespace {

v1::MissionStatus mission(
    v1::MissionState state,
    std::vector<std::pair<v1::MissionStepState, v1::TerminationCause>> steps) {
  v1::MissionStatus status;
  status.set_robot_id("drone1");
  status.set_state(state);
  for (const auto& [step_state, cause] : steps) {
    auto* record = status.add_steps();
    record->set_state(step_state);
    record->set_cause(cause);
  }
  return status;
}

TEST(MissionEndCause, IsTheCauseOfTheStepThatEndedTheMission) {
  constexpr auto kFinished = v1::MISSION_STEP_STATE_FINISHED;
  EXPECT_EQ(missionEndCause(mission(v1::MISSION_STATE_SUCCEEDED,
                                    {{kFinished, v1::TERMINATION_CAUSE_WRONG_PROGRESS},
                                     {kFinished, v1::TERMINATION_CAUSE_GOAL_ACHIEVED}})),
            "GOAL_ACHIEVED");
  EXPECT_EQ(missionEndCause(
                mission(v1::MISSION_STATE_FAILED, {{kFinished, v1::TERMINATION_CAUSE_GOAL_ACHIEVED},
                                                   {kFinished, v1::TERMINATION_CAUSE_TIME_OUT}})),
            "TIME_OUT");
  EXPECT_EQ(missionEndCause(mission(v1::MISSION_STATE_ABORTED,
                                    {{kFinished, v1::TERMINATION_CAUSE_INTERRUPTED}})),
            "INTERRUPTED");
  EXPECT_EQ(missionEndCause(
                mission(v1::MISSION_STATE_FAILED,
                        {{v1::MISSION_STEP_STATE_REFUSED, v1::TERMINATION_CAUSE_UNSPECIFIED}})),
            "REFUSED");
  // No step ended it: none ran, the last one succeeded (a recurrent behavior
  // failed, an abort came between steps), or one still runs.
  EXPECT_EQ(missionEndCause(mission(v1::MISSION_STATE_FAILED, {})), "NONE");
  EXPECT_EQ(missionEndCause(mission(v1::MISSION_STATE_ABORTED,
                                    {{kFinished, v1::TERMINATION_CAUSE_GOAL_ACHIEVED}})),
            "NONE");
  EXPECT_EQ(missionEndCause(
                mission(v1::MISSION_STATE_FAILED,
                        {{v1::MISSION_STEP_STATE_RUNNING, v1::TERMINATION_CAUSE_UNSPECIFIED}})),
            "NONE");
}

TEST(CoordinatorMetrics, CountsAnEndedMissionByOutcomeAndCause) {
  prometheus::Registry registry;
  CoordinatorMetrics metrics(registry);
  metrics.missionEnded(mission(v1::MISSION_STATE_ABORTED, {{v1::MISSION_STEP_STATE_FINISHED,
                                                            v1::TERMINATION_CAUSE_INTERRUPTED}}));
  metrics.missionEnded(
      mission(v1::MISSION_STATE_SUCCEEDED,
              {{v1::MISSION_STEP_STATE_FINISHED, v1::TERMINATION_CAUSE_GOAL_ACHIEVED}}));
  metrics.missionEnded(
      mission(v1::MISSION_STATE_SUCCEEDED,
              {{v1::MISSION_STEP_STATE_FINISHED, v1::TERMINATION_CAUSE_GOAL_ACHIEVED}}));
  std::map<std::string, double> counted;  // "outcome/cause"
  for (const auto& family : registry.Collect()) {
    if (family.name != "behaviorlib_coordinator_missions_finished_total") continue;
    for (const auto& metric : family.metric) {
      std::map<std::string, std::string> labels;
      for (const auto& label : metric.label) labels[label.name] = label.value;
      EXPECT_EQ(labels["robot"], "drone1");
      counted[labels["outcome"] + "/" + labels["cause"]] = metric.counter.value;
    }
  }
  const std::map<std::string, double> expected = {{"aborted/INTERRUPTED", 1},
                                                  {"succeeded/GOAL_ACHIEVED", 2}};
  EXPECT_EQ(counted, expected);
}

}  // namespace
}  // namespace behaviorlib::coordinator
