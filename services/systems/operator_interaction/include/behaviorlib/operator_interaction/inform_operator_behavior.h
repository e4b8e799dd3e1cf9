#pragma once

// INFORM_OPERATOR (goal-based): leaves a message for the operator in belief
// memory and, with a data channel, publishes it.
//
//   operator/message_counts/{id}   the last n (read, then written)
//   operator/messages/{id}/{n}     {robot_id, text, time}
//   robots/{id}/operator/messages  Text (with a data channel)
//
//   checkSituation  a coordinator
//   onExecute       the writes and the publication, once
//   checkGoal       written -> GOAL_ACHIEVED
//   checkProcesses  belief memory or the channel failed -> PROCESS_FAILURE

#include <google/protobuf/empty.pb.h>

#include <string>

#include "absl/status/status.h"
#include "behaviorlib/behavior_execution_manager.h"
#include "behaviorlib/channel/channel_client.h"
#include "behaviorlib/server/belief_client.h"
#include "behaviorlib/v1/behaviors/operator_interaction.pb.h"

namespace behaviorlib::operator_interaction {

class InformOperatorBehavior final
    : public Behavior<v1::InformOperatorParameters, google::protobuf::Empty> {
 public:
  /// `beliefs` may be null (the behavior is then infeasible), `channel` too
  /// (nothing is published then).
  InformOperatorBehavior(const server::BeliefClient* beliefs, channel::ChannelClient* channel);

 protected:
  absl::Status onActivate() override;
  void onExecute() override;
  absl::Status onModify(const v1::InformOperatorParameters& new_parameters) override;

  Situation checkSituation() override;
  Verdict checkGoal() override;
  Verdict checkProcesses() override;

 private:
  absl::Status inform();

  const server::BeliefClient* beliefs_;
  channel::ChannelClient* channel_;
  bool done_ = false;
  std::string key_;
  absl::Status error_;
  uint64_t seq_ = 0;
};

}  // namespace behaviorlib::operator_interaction
