#pragma once

// SELF_LOCALIZE_WITH_EKF_SENSOR_FUSION (recurrent): the INS error-state EKF
// (services/sensor_fusion) fed from the data channel and publishing the
// robot's pose estimate.
//
//   robots/{id}/imu           Imu, queued (every sample predicts)
//   robots/{id}/gps           PositionFix -> position update
//   robots/{id}/baro          Altitude -> altitude update      (use_barometer)
//   robots/{id}/linear_speed  TwistStamped, body frame -> velocity update
//                                                              (use_linear_speed)
//   the IMU's orientation     -> yaw update, 10 Hz             (use_imu_yaw)
//   -> robots/{id}/self_localization/pose and /twist, every second IMU
//      sample (100 Hz with the simulator's IMU)
//
// Samples are applied in the order they arrive (the broker keeps each
// topic's order; different topics may interleave by a few milliseconds,
// well inside the filter's noise). The filter starts at the first GPS fix
// after an IMU sample, with the IMU's orientation.
//
//   checkSituation  before: a data channel, and fresh IMU and GPS samples on it
//   checkGoal       none (recurrent)
//   checkProgress   divergence: horizontal standard deviation beyond
//                   max_horizontal_stddev_m, or more than max_rejected_ratio of
//                   the last gps_window fixes rejected by the innovation gate
//                   -> WRONG_PROGRESS
//   checkProcesses  IMU silent for imu_timeout_s, GPS for gps_timeout_s (on
//                   the behavior clock), no start within start_timeout_s, a
//                   non-finite state, or the estimate cannot be published
//                   -> PROCESS_FAILURE
//
// Config (its section of --config; the keys, their ranges and defaults are
// declared in proto/behaviorlib/config/v1/multi_sensor_fusion.proto,
// SelfLocalizeWithEkfSensorFusionConfig): imu_timeout_s [0.25],
// gps_timeout_s [1.5], start_timeout_s [2], max_horizontal_stddev_m [3],
// max_rejected_ratio [0.5], gps_window [20], baro_stddev_m [0.5],
// linear_speed_stddev_m_s [0.1], yaw_stddev_rad [0.05], gyro_noise_rad_s
// [0.005], accel_noise_m_s2 [0.05] (noise densities of the IMU, per
// sqrt(Hz): EkfNoise's defaults), baro_drift_m_sqrt_s [0.02] (the
// barometer's offset, estimated against GPS altitude; 0 fixes it at 0).

#include <deque>
#include <memory>
#include <optional>
#include <string>

#include "behaviorlib/behavior_execution_manager.h"
#include "behaviorlib/channel/channel_client.h"
#include "behaviorlib/config/v1/multi_sensor_fusion.pb.h"
#include "behaviorlib/flight_common/estimate_publisher.h"
#include "behaviorlib/sensor_fusion/ekf.h"
#include "behaviorlib/sensor_fusion/ins_feed.h"
#include "behaviorlib/v1/behaviors/multi_sensor_fusion.pb.h"
#include "behaviorlib/v1/types.pb.h"

namespace behaviorlib::fusion {

class EkfSelfLocalizationBehavior final
    : public Behavior<v1::SelfLocalizeWithEkfSensorFusionParameters,
                      config::v1::SelfLocalizeWithEkfSensorFusionConfig> {
 public:
  /// `channel` may be null: the behavior then reports itself infeasible.
  explicit EkfSelfLocalizationBehavior(channel::ChannelClient* channel);
  ~EkfSelfLocalizationBehavior() override;

 protected:
  absl::Status onConfigure(
      const config::v1::SelfLocalizeWithEkfSensorFusionConfig& config) override;
  absl::Status onActivate() override;
  void onDeactivate() override;
  void onPause() override;
  void onResume() override;
  absl::Status onModify(
      const v1::SelfLocalizeWithEkfSensorFusionParameters& new_parameters) override;

  Situation checkSituation() override;
  Verdict checkProgress() override;
  Verdict checkProcesses() override;

 private:
  void onImu(const v1::Imu& imu);
  void onGps(const v1::PositionFix& fix);
  void onBaro(const v1::Altitude& altitude);
  void onLinearSpeed(const v1::TwistStamped& twist);
  void stopSubscriptions();

  channel::ChannelClient* channel_;
  // Config.
  Duration imu_timeout_ = std::chrono::milliseconds(250);
  Duration gps_timeout_ = std::chrono::milliseconds(1500);
  Duration start_timeout_ = std::chrono::seconds(2);
  double max_horizontal_stddev_m_ = 3.0;
  double max_rejected_ratio_ = 0.5;
  int gps_window_ = 20;
  double baro_stddev_m_ = 0.5;
  double linear_speed_stddev_m_s_ = 0.1;
  double yaw_stddev_rad_ = 0.05;
  EkfNoise noise_;

  // Filter state: samples arrive on the worker (onWorker), so no lock.
  InsFeed ins_;
  flight::EstimatePublisher estimate_;
  bool running_ = false, publishing_ = false;
  bool use_linear_speed_ = true, use_barometer_ = true;
  std::optional<TimePoint> last_imu_, last_gps_;
  std::deque<bool> gps_accepted_;  // the last gps_window fixes

  TimePoint activated_at_{};
  bool active_ = false;
  std::unique_ptr<channel::Subscription> imu_sub_, gps_sub_, baro_sub_, speed_sub_;
};

}  // namespace behaviorlib::fusion
