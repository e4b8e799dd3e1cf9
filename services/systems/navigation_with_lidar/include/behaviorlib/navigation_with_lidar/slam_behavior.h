#pragma once

// SELF_LOCALIZE_AND_MAP_WITH_LIDAR (recurrent): localization by matching the
// 2-D lidar's scans against a map it builds as it goes (navigation/lidar_slam.h),
// fused with the IMU and the optical-flow body speed in the INS error-state
// filter (sensor_fusion/ekf.h); no GPS, no ground truth. It publishes on the
// topics every self-localization behavior publishes, so the motion
// controllers and the system's own OctoMap (built from this estimate) work
// unchanged.
//
//   robots/{id}/imu           Imu, queued: every sample predicts; its roll and
//                             pitch level the scans; its heading (an AHRS)
//                             corrects the filter 10 times a second (use_imu_yaw)
//   robots/{id}/linear_speed  TwistStamped, body frame -> velocity update
//   robots/{id}/baro          Altitude -> altitude update
//   robots/{id}/lidar/scan    LaserScan, queued: matched against the map at the
//                             estimate for its stamp; the correction (the match
//                             minus that estimate) is applied to the current
//                             state as a horizontal position (with the match's
//                             covariance) and a heading; then the scan is
//                             inserted at the corrected pose
//   -> robots/{id}/self_localization/pose and /twist, every second IMU
//      sample (100 Hz with the simulator's IMU)
//
// The map's frame is the start pose: initial_position_m (x, y) and
// initial_yaw_rad (else the IMU's heading); z comes from the barometer.
//
//   checkSituation  before: a data channel, and fresh IMU, body speed and
//                   lidar samples on it ("no lidar" otherwise)
//   checkGoal       none (recurrent)
//   checkProgress   the matching degenerate or failing (too few points, a
//                   poor score, a direction the scan cannot see: a long
//                   featureless corridor, an open field) for longer than
//                   max_degenerate_s; more than max_rejected_ratio of the
//                   last match_window matches rejected by the filter's gate;
//                   the horizontal standard deviation beyond
//                   max_horizontal_stddev_m -> WRONG_PROGRESS
//   checkProcesses  the lidar silent for lidar_timeout_s, the IMU for
//                   imu_timeout_s (behavior clock), no start within
//                   start_timeout_s, a non-finite state, or the estimate
//                   cannot be published -> PROCESS_FAILURE
//
// Config (its section of --config; the keys, their ranges and defaults are
// declared in proto/behaviorlib/config/v1/navigation_with_lidar.proto,
// SelfLocalizeAndMapWithLidarConfig): imu_timeout_s [0.25], lidar_timeout_s
// [1], start_timeout_s [2], max_degenerate_s [5], max_rejected_ratio [0.5],
// match_window [20], max_horizontal_stddev_m [1], baro_stddev_m [0.5],
// linear_speed_stddev_m_s [0.1], imu_yaw_stddev_rad [0.01],
// gyro_noise_rad_s [0.005], accel_noise_m_s2 [0.05] (EkfNoise's defaults),
// resolution_m [0.05], likelihood_sigma_m [0.04], max_extent_m [100],
// max_free_range_m [12]. The lidar's mounting is the system's (mapping:
// lidar_mount_m).

#include <cstdint>
#include <deque>
#include <memory>
#include <optional>
#include <string>

#include "behaviorlib/behavior_execution_manager.h"
#include "behaviorlib/channel/channel_client.h"
#include "behaviorlib/config/v1/navigation_with_lidar.pb.h"
#include "behaviorlib/flight_common/estimate_publisher.h"
#include "behaviorlib/navigation/lidar_slam.h"
#include "behaviorlib/sensor_fusion/ekf.h"
#include "behaviorlib/sensor_fusion/ins_feed.h"
#include "behaviorlib/v1/behaviors/navigation_with_lidar.pb.h"
#include "behaviorlib/v1/types.pb.h"

namespace behaviorlib::nav {

class SlamBehavior final : public Behavior<v1::SelfLocalizeAndMapWithLidarParameters,
                                           config::v1::SelfLocalizeAndMapWithLidarConfig> {
 public:
  /// `channel` may be null: the behavior then reports itself infeasible.
  SlamBehavior(channel::ChannelClient* channel, const Eigen::Vector3d& lidar_mount_m);
  ~SlamBehavior() override;

 protected:
  absl::Status onConfigure(const config::v1::SelfLocalizeAndMapWithLidarConfig& config) override;
  absl::Status onActivate() override;
  void onDeactivate() override;
  void onPause() override;
  void onResume() override;
  absl::Status onModify(const v1::SelfLocalizeAndMapWithLidarParameters& new_parameters) override;

  Situation checkSituation() override;
  Verdict checkProgress() override;
  Verdict checkProcesses() override;

 private:
  struct Stamped {
    TimePoint stamp;
    Pose2 pose;
  };
  void onImu(const v1::Imu& imu);
  void onBaro(const v1::Altitude& altitude);
  void onLinearSpeed(const v1::TwistStamped& twist);
  void onScan(const v1::LaserScan& scan);
  void start(const Eigen::Quaterniond& imu_orientation);
  Pose2 currentPose() const;
  std::optional<Pose2> poseAt(TimePoint stamp) const;
  void publishEstimate(const v1::Header& imu_header);
  void stopSubscriptions();
  fusion::InsEkf& ekf() { return ins_.ekf(); }
  const fusion::InsEkf& ekf() const { return ins_.ekf(); }

  channel::ChannelClient* channel_;
  const Eigen::Vector3d lidar_mount_m_;
  // Config.
  Duration imu_timeout_ = std::chrono::milliseconds(250);
  Duration lidar_timeout_ = std::chrono::seconds(1);
  Duration start_timeout_ = std::chrono::seconds(2);
  Duration max_degenerate_ = std::chrono::seconds(5);
  double max_rejected_ratio_ = 0.5;
  int match_window_ = 20;
  double max_horizontal_stddev_m_ = 1.0;
  double baro_stddev_m_ = 0.5;
  double linear_speed_stddev_m_s_ = 0.1;
  double imu_yaw_stddev_rad_ = 0.01;
  fusion::EkfNoise noise_;
  LidarSlamConfig slam_config_;

  // State: samples arrive on the worker (onWorker), so no lock.
  fusion::InsFeed ins_;
  flight::EstimatePublisher estimate_;
  std::unique_ptr<LidarSlam> slam_;
  bool running_ = false, publishing_ = false;
  std::optional<TimePoint> last_imu_, last_scan_;
  std::optional<double> last_baro_m_;
  std::deque<Stamped> history_;      // the estimate at recent IMU stamps
  std::deque<bool> match_accepted_;  // the last match_window matches
  std::optional<TimePoint> degenerate_since_;
  std::string degenerate_reason_;

  TimePoint activated_at_{};
  bool active_ = false;
  std::unique_ptr<channel::Subscription> imu_sub_, baro_sub_, speed_sub_, scan_sub_;
};

}  // namespace behaviorlib::nav
