#pragma once

// INFORM_POSITION_TO_ROBOTS (recurrent): shares this robot's pose estimate
// with the swarm.
//
//   robots/{id}/self_localization/pose  PoseStamped, latest
//   -> robots/swarm/positions           SwarmPosition at rate_hz (behavior clock)
//
// An estimate stating a horizontal standard deviation above
// max_horizontal_stddev_m (when set) is not shared; the one shared carries
// what its estimator states.
//
//   onActivate      INVALID_ARGUMENT for a bad robot id in robot_ids
//   checkSituation  before: a data channel and a fresh pose estimate
//   checkProcesses  no estimate within pose_timeout_s of the activation, an
//                   estimate older than pose_timeout_s, or a refused
//                   publication -> PROCESS_FAILURE
//
// Config (defaults): pose_timeout_s [1].

#include <memory>
#include <optional>

#include "behaviorlib/behavior_execution_manager.h"
#include "behaviorlib/channel/channel_client.h"
#include "behaviorlib/config/v1/swarm_interaction.pb.h"
#include "behaviorlib/v1/behaviors/swarm_interaction.pb.h"
#include "behaviorlib/v1/types.pb.h"

namespace behaviorlib::swarm {

class InformPositionToRobotsBehavior final
    : public Behavior<v1::InformPositionToRobotsParameters,
                      config::v1::InformPositionToRobotsConfig> {
 public:
  /// `channel` may be null: the behavior then reports itself infeasible.
  explicit InformPositionToRobotsBehavior(channel::ChannelClient* channel);
  ~InformPositionToRobotsBehavior() override;

 protected:
  absl::Status onConfigure(const config::v1::InformPositionToRobotsConfig& config) override;
  absl::Status onActivate() override;
  void onExecute() override;
  void onDeactivate() override;
  absl::Status onModify(const v1::InformPositionToRobotsParameters& new_parameters) override;

  Situation checkSituation() override;
  Verdict checkProcesses() override;

 private:
  channel::ChannelClient* channel_;
  Duration pose_timeout_ = std::chrono::seconds(1);

  std::optional<v1::PoseStamped> latest_;  // delivered on the worker (onWorker)

  std::unique_ptr<channel::Subscription> pose_sub_;
  TimePoint activated_at_{};
  std::optional<TimePoint> next_publish_;
  uint64_t seq_ = 0;
  absl::Status error_;
  bool active_ = false;
};

}  // namespace behaviorlib::swarm
