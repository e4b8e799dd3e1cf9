#pragma once

// ESTIMATE_POSITION_WITH_SENSOR (recurrent): self-localization from the
// simulator's (or a driver's) sensors on the data channel, fused by a small
// Kalman filter per world axis (SensorPositionFilter, position_estimators.h):
//
//   robots/{id}/imu   Imu, queued (every sample predicts: its attitude rotates
//                     the specific force into the world frame)
//   robots/{id}/gps   PositionFix -> position update (gated)
//   robots/{id}/baro  Altitude -> height update with the barometer's offset
//                     (gated; with use_barometer)
//   -> robots/{id}/self_localization/pose  (position, the IMU's orientation)
//      robots/{id}/self_localization/twist (world velocity, body rates)
//      every second IMU sample (100 Hz with the simulator's 200 Hz IMU),
//      stamped with that sample's stamp. The filter starts at the first fix.
//
//   checkSituation  before: a data channel, and fresh IMU and position-fix
//                   samples on it (2 x their timeouts); no barometer lowers
//                   the performance estimate to 0.5
//   checkGoal       none (recurrent)
//   checkProgress   more than max_rejected_samples fixes (or altitudes) in a
//                   row further than max_innovation_m from the prediction:
//                   WRONG_PROGRESS (the fix jumps further than the vehicle
//                   can move)
//   checkProcesses  a stream (IMU, fix, barometer if used) without a sample
//                   for longer than its timeout, or repeating the same value
//                   for longer than frozen_timeout_s (a stuck sensor: real
//                   samples always carry noise); a non-finite state; the
//                   estimate cannot be published: PROCESS_FAILURE
//
// Config (defaults): imu_timeout_s [0.5], gps_timeout_s [1.0] (10 fix
// periods), baro_timeout_s [1.0], frozen_timeout_s [0.5] (0: off),
// accel_noise_m_s2 [0.05], accel_bias_walk_m_s2 [0.002], baro_drift_m
// [0.02], baro_offset_stddev_m [0.3] (the SensorFilterNoise fields). Times
// are on the behavior clock, compared with the samples' stamps.

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

class EstimatePositionWithSensorBehavior final
    : public Behavior<v1::EstimatePositionWithSensorParameters,
                      config::v1::EstimatePositionWithSensorConfig> {
 public:
  /// `channel` may be null (the process runs without --channel): the
  /// behavior then reports itself infeasible.
  explicit EstimatePositionWithSensorBehavior(channel::ChannelClient* channel);
  ~EstimatePositionWithSensorBehavior() override;

 protected:
  absl::Status onConfigure(const config::v1::EstimatePositionWithSensorConfig& config) override;
  absl::Status onActivate() override;
  void onDeactivate() override;
  void onPause() override;
  void onResume() override;
  absl::Status onModify(const v1::EstimatePositionWithSensorParameters& new_parameters) override;

  Situation checkSituation() override;
  Verdict checkProgress() override;
  Verdict checkProcesses() override;

 private:
  void onImu(const v1::Imu& imu);
  void onFix(const v1::PositionFix& fix);
  void onAltitude(const v1::Altitude& altitude);
  /// Counts a gated measurement; records the jump once the run of rejected
  /// ones passes the limit.
  void countRejection(bool accepted, double innovation_m, const std::string& what, uint32_t* run);
  void stopSubscriptions();

  channel::ChannelClient* channel_;
  // Config.
  Duration imu_timeout_ = std::chrono::milliseconds(500);
  Duration gps_timeout_ = std::chrono::seconds(1);
  Duration baro_timeout_ = std::chrono::seconds(1);
  Duration frozen_timeout_ = std::chrono::milliseconds(500);
  SensorFilterNoise noise_;

  // Filter state: samples arrive on the worker (onWorker), so no lock.
  SensorPositionFilter filter_;
  bool running_ = false, publishing_ = false;
  bool use_barometer_ = true;
  double max_innovation_m_ = 5.0;
  uint32_t max_rejected_ = 3;
  uint32_t rejected_fixes_ = 0, rejected_altitudes_ = 0;
  std::optional<double> last_imu_s_;
  Eigen::Vector3d last_gyro_ = Eigen::Vector3d::Zero();
  uint64_t imu_count_ = 0;
  std::optional<SensorStream> imu_, gps_, baro_;
  std::string jump_;
  flight::EstimatePublisher estimate_;

  bool active_ = false;
  TimePoint activated_at_{};
  std::unique_ptr<channel::Subscription> imu_sub_, gps_sub_, baro_sub_;
};

}  // namespace behaviorlib::basic
