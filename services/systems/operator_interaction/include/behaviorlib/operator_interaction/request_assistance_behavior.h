#pragma once

// REQUEST_OPERATOR_ASSISTANCE (goal-based): asks the operator a question
// through belief memory and waits for the answer.
//
//   operator/requests/{request_id}  {robot_id, question, answer_key, timeout_s,
//                                    time, state: open|answered|timed_out|withdrawn}
//   operator/answers/{request_id}   written by the operator (any JSON value)
//   answer_key                      the answer, copied there
//
// An AnswerWatch thread does the calls; the monitoring only looks at it.
//
//   onActivate      INVALID_ARGUMENT for an empty question, or a request_id
//                   or answer_key that is not a belief key
//   checkSituation  a coordinator
//   checkGoal       the answer copied to answer_key -> GOAL_ACHIEVED
//   time-out        timeout_s of active time (the maximum execution time)
//                   -> TIME_OUT
//   checkProcesses  the coordinator failing for read_failure_timeout_s
//                   -> PROCESS_FAILURE
//   onDeactivate    marks the request answered, timed_out or withdrawn
//
// Config (defaults): read_failure_timeout_s [5], poll_period_s [0.1] (wall
// time between reads of the answer).

#include <memory>
#include <optional>
#include <string>

#include "behaviorlib/behavior_execution_manager.h"
#include "behaviorlib/config/v1/operator_interaction.pb.h"
#include "behaviorlib/operator_interaction/answer_watch.h"
#include "behaviorlib/server/belief_client.h"
#include "behaviorlib/v1/behaviors/operator_interaction.pb.h"

namespace behaviorlib::operator_interaction {

class RequestOperatorAssistanceBehavior final
    : public Behavior<v1::RequestOperatorAssistanceParameters,
                      config::v1::RequestOperatorAssistanceConfig> {
 public:
  /// `beliefs` may be null: the behavior is then infeasible.
  explicit RequestOperatorAssistanceBehavior(const server::BeliefClient* beliefs);
  ~RequestOperatorAssistanceBehavior() override;

 protected:
  absl::Status onConfigure(const config::v1::RequestOperatorAssistanceConfig& config) override;
  absl::Status onActivate() override;
  void onDeactivate() override;
  absl::Status onModify(const v1::RequestOperatorAssistanceParameters& new_parameters) override;

  Situation checkSituation() override;
  Verdict checkGoal() override;
  Verdict checkProcesses() override;

 private:
  google::protobuf::Value requestValue(const std::string& state) const;

  const server::BeliefClient* beliefs_;
  Duration read_failure_timeout_ = std::chrono::seconds(5);
  double poll_period_s_ = 0.1;

  std::unique_ptr<AnswerWatch> watch_;
  std::string request_id_, answer_key_;
  TimePoint asked_at_{};
  std::optional<TimePoint> failing_since_;
};

}  // namespace behaviorlib::operator_interaction
