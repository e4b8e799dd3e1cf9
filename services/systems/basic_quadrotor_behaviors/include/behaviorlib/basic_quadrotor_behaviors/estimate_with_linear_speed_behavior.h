#pragma once

// ESTIMATE_POSITION_WITH_LINEAR_SPEED (recurrent): dead reckoning
// (LinearSpeedDeadReckoning, position_estimators.h) from the data channel:
//
//   robots/{id}/linear_speed  TwistStamped (body frame), queued: every sample
//                             is integrated
//   robots/{id}/imu           Imu, latest: its orientation (attitude and yaw)
//                             rotates the speed into the world frame
//   -> robots/{id}/self_localization/pose  (position, the IMU's orientation)
//      robots/{id}/self_localization/twist (world velocity, body rates)
//      one estimate per speed sample (30 Hz with the simulator), stamped with
//      its stamp.
//
// The start: the initial_{x,y,z}_m parameters (all three), or else the latest
// pose estimate on robots/{id}/self_localization/pose (no older than
// max_initial_estimate_age_s), advanced to the activation time along the
// latest velocity estimate.
//
//   checkSituation  before: a data channel, fresh linear-speed and IMU
//                   samples (2 x their timeouts); while active: the
//                   performance estimate falls from 1 to 0 as the drift
//                   bound approaches max_drift_m
//   checkGoal       none (recurrent)
//   checkProgress   the drift bound (drift_ratio x distance travelled +
//                   drift_rate_m_s x time) beyond max_drift_m, or a speed
//                   sample faster than max_speed_m_s (a faulty sensor):
//                   WRONG_PROGRESS
//   checkProcesses  the linear speed or the IMU without a sample for longer
//                   than its timeout, or repeating the same value for longer
//                   than frozen_timeout_s; a non-finite position; the
//                   estimate cannot be published: PROCESS_FAILURE
//   time-out        max_duration_s of active time: TIME_OUT
//
// Config (defaults): linear_speed_timeout_s [0.5] (15 sample periods),
// imu_timeout_s [0.5], frozen_timeout_s [0.5] (0: off),
// max_initial_estimate_age_s [2], drift_ratio [0.03], drift_rate_m_s
// [0.005]. Times are on the behavior clock, compared with the samples'
// stamps.

#include <memory>
#include <optional>
#include <string>

#include "behaviorlib/basic_quadrotor_behaviors/position_estimators.h"
#include "behaviorlib/basic_quadrotor_behaviors/sensor_stream.h"
#include "behaviorlib/behavior_execution_manager.h"
#include "behaviorlib/channel/channel_client.h"
#include "behaviorlib/config/v1/basic_quadrotor_behaviors.pb.h"
#include "behaviorlib/flight_common/estimate_publisher.h"
#include "behaviorlib/v1/behaviors/basic_quadrotor_behaviors.pb.h"
#include "behaviorlib/v1/types.pb.h"

namespace behaviorlib::basic {

class EstimatePositionWithLinearSpeedBehavior final
    : public Behavior<v1::EstimatePositionWithLinearSpeedParameters,
                      config::v1::EstimatePositionWithLinearSpeedConfig> {
 public:
  /// `channel` may be null (the process runs without --channel): the
  /// behavior then reports itself infeasible.
  explicit EstimatePositionWithLinearSpeedBehavior(channel::ChannelClient* channel);
  ~EstimatePositionWithLinearSpeedBehavior() override;

 protected:
  absl::Status onConfigure(
      const config::v1::EstimatePositionWithLinearSpeedConfig& config) override;
  absl::Status onActivate() override;
  void onDeactivate() override;
  void onPause() override;
  void onResume() override;
  absl::Status onModify(
      const v1::EstimatePositionWithLinearSpeedParameters& new_parameters) override;

  Situation checkSituation() override;
  Verdict checkProgress() override;
  Verdict checkProcesses() override;

 private:
  /// The initial position from the parameters or the latest estimate.
  absl::StatusOr<Eigen::Vector3d> initialPosition(TimePoint at);
  void onSpeed(const v1::TwistStamped& speed);
  void onImu(const v1::Imu& imu);
  /// The drift bound, metres.
  double driftBound() const;
  void stopSubscriptions();

  channel::ChannelClient* channel_;
  // Config.
  Duration speed_timeout_ = std::chrono::milliseconds(500);
  Duration imu_timeout_ = std::chrono::milliseconds(500);
  Duration frozen_timeout_ = std::chrono::milliseconds(500);
  Duration max_initial_estimate_age_ = std::chrono::seconds(2);
  double drift_ratio_ = 0.03;
  double drift_rate_m_s_ = 0.005;

  // Dead reckoning: samples arrive on the worker (onWorker), so no lock.
  std::optional<LinearSpeedDeadReckoning> reckoning_;
  double start_s_ = 0.0;
  bool running_ = false, publishing_ = false;
  double max_speed_m_s_ = 15.0;
  std::optional<Eigen::Quaterniond> orientation_;
  Eigen::Vector3d gyro_ = Eigen::Vector3d::Zero();
  std::optional<SensorStream> speed_, imu_;
  std::string implausible_;
  flight::EstimatePublisher estimate_;

  bool active_ = false;
  TimePoint activated_at_{};
  std::unique_ptr<channel::Subscription> speed_sub_, imu_sub_;
};

}  // namespace behaviorlib::basic
