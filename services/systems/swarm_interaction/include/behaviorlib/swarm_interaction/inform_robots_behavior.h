#pragma once

// INFORM_ROBOTS (goal-based): publishes one SwarmMessage from this robot on
// robots/swarm/messages, for the given robots or all of them.
//
//   onActivate      INVALID_ARGUMENT with neither text nor payload_json, a
//                   payload_json that is not JSON, or a bad robot id
//   onExecute       publishes the message once, then flushes the channel's
//                   publish stream (the broker has accepted it)
//   checkSituation  a data channel
//   checkGoal       published -> GOAL_ACHIEVED
//   checkProcesses  the channel refused the message -> PROCESS_FAILURE

#include <google/protobuf/empty.pb.h>

#include <string>

#include "absl/status/status.h"
#include "behaviorlib/behavior_execution_manager.h"
#include "behaviorlib/channel/channel_client.h"
#include "behaviorlib/v1/behaviors/swarm_interaction.pb.h"

namespace behaviorlib::swarm {

class InformRobotsBehavior final
    : public Behavior<v1::InformRobotsParameters, google::protobuf::Empty> {
 public:
  /// `channel` may be null: the behavior then reports itself infeasible.
  explicit InformRobotsBehavior(channel::ChannelClient* channel);

 protected:
  absl::Status onActivate() override;
  void onExecute() override;
  absl::Status onModify(const v1::InformRobotsParameters& new_parameters) override;

  Situation checkSituation() override;
  Verdict checkGoal() override;
  Verdict checkProcesses() override;

 private:
  channel::ChannelClient* channel_;
  uint64_t seq_ = 0;
  bool sent_ = false;
  absl::Status error_;
};

/// The parameters' problem (INVALID_ARGUMENT naming the field), or OK.
absl::Status checkInformRobotsParameters(const v1::InformRobotsParameters& p);

}  // namespace behaviorlib::swarm
