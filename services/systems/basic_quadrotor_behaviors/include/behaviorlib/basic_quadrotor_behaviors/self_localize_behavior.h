#pragma once

// SELF_LOCALIZE_WITH_GROUND_TRUTH (recurrent): republishes the simulator's
// ground truth as the robot's estimate, one estimate per ground-truth sample
// (100 Hz from the simulator), on the behavior's worker:
//   robots/{id}/ground_truth/pose  -> robots/{id}/self_localization/pose
//   robots/{id}/ground_truth/twist -> robots/{id}/self_localization/twist
// Stamps are kept (simulated time of the ground truth); frame "world".
//
//   checkSituation  before: a data channel and fresh ground truth on it
//   checkGoal       none (recurrent)
//   checkProgress   the ground truth jumps further between two samples than
//                   max_jump_m: WRONG_PROGRESS (a teleport or a reset
//                   invalidates everything built on the old estimate)
//   checkProcesses  ground truth older than ground_truth_timeout_s on the
//                   behavior clock, or the estimate cannot be published:
//                   PROCESS_FAILURE
//
// Config: ground_truth_timeout_s [0.5], max_jump_m [1].

#include <memory>
#include <optional>
#include <string>

#include "behaviorlib/behavior_execution_manager.h"
#include "behaviorlib/channel/channel_client.h"
#include "behaviorlib/config/v1/basic_quadrotor_behaviors.pb.h"
#include "behaviorlib/v1/behaviors/basic_quadrotor_behaviors.pb.h"
#include "behaviorlib/v1/types.pb.h"

namespace behaviorlib::basic {

class SelfLocalizeWithGroundTruthBehavior final
    : public Behavior<v1::SelfLocalizeWithGroundTruthParameters,
                      config::v1::SelfLocalizeWithGroundTruthConfig> {
 public:
  /// `channel` may be null (the process runs without --channel): the
  /// behavior then reports itself infeasible.
  explicit SelfLocalizeWithGroundTruthBehavior(channel::ChannelClient* channel);
  ~SelfLocalizeWithGroundTruthBehavior() override;

 protected:
  absl::Status onConfigure(const config::v1::SelfLocalizeWithGroundTruthConfig& config) override;
  absl::Status onActivate() override;
  void onDeactivate() override;
  void onPause() override;
  void onResume() override;

  Situation checkSituation() override;
  Verdict checkProgress() override;
  Verdict checkProcesses() override;

 private:
  void onPose(const v1::PoseStamped& pose);
  void onTwist(const v1::TwistStamped& twist);
  void stopSubscriptions();

  channel::ChannelClient* channel_;
  Duration timeout_ = std::chrono::milliseconds(500);
  double max_jump_m_ = 1.0;

  // Samples arrive on the worker (onWorker), so no lock.
  bool publishing_ = false;
  std::optional<v1::PoseStamped> last_pose_;
  std::string jump_;
  absl::Status publish_error_;
  uint64_t seq_ = 0;
  uint64_t twist_seq_ = 0;

  bool active_ = false;
  TimePoint activated_at_{};
  std::unique_ptr<channel::Subscription> pose_subscription_;
  std::unique_ptr<channel::Subscription> twist_subscription_;
};

}  // namespace behaviorlib::basic
