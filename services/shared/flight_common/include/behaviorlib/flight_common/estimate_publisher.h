#pragma once

// The output of a self-localization behavior: its estimate on the robot's
// pose and twist estimate topics (flight_common/topics.h), numbered per
// publisher. Every estimator publishes through one of these:
// ESTIMATE_POSITION_WITH_SENSOR, ESTIMATE_POSITION_WITH_LINEAR_SPEED,
// SELF_LOCALIZE_WITH_EKF_SENSOR_FUSION and SELF_LOCALIZE_AND_MAP_WITH_LIDAR.
//
//   flight::EstimatePublisher out(channel);
//   out.reset();                                  // onActivate
//   out.publish(imu.header().stamp(), robotId(), {.position_m = p, ...});
//   if (!out.error().ok()) ...                    // checkProcesses
//
// Not thread-safe: a behavior publishes on its worker.

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cstdint>
#include <optional>
#include <string>

#include "absl/status/status.h"
#include "behaviorlib/channel/channel_client.h"
#include "behaviorlib/v1/types.pb.h"

namespace behaviorlib::flight {

/// One estimate of the vehicle's state.
struct Estimate {
  Eigen::Vector3d position_m = Eigen::Vector3d::Zero();             ///< world
  Eigen::Quaterniond orientation = Eigen::Quaterniond::Identity();  ///< world <- body
  Eigen::Vector3d velocity_m_s = Eigen::Vector3d::Zero();           ///< world
  Eigen::Vector3d body_rates_rad_s = Eigen::Vector3d::Zero();       ///< body
  /// The horizontal position's standard deviation, when the estimator
  /// knows it (the pose's optional field stays unset otherwise).
  std::optional<double> horizontal_stddev_m;
};

/// The messages of `estimate`: the pose in frame "world" and the twist
/// (linear velocity in the world frame, angular in the body frame), both
/// stamped `stamp`, for `robot_id`, numbered `seq`.
void estimateMessages(const google::protobuf::Timestamp& stamp, const std::string& robot_id,
                      uint64_t seq, const Estimate& estimate, v1::PoseStamped* pose,
                      v1::TwistStamped* twist);

class EstimatePublisher {
 public:
  /// `channel` may be null: publish() then keeps a FAILED_PRECONDITION.
  explicit EstimatePublisher(channel::ChannelClient* channel) : channel_(channel) {}

  /// Forgets the kept failure (a new activation). The numbering goes on.
  void reset() { error_ = absl::OkStatus(); }
  /// Publishes the pose, then the twist; the first failure is kept.
  void publish(const google::protobuf::Timestamp& stamp, const std::string& robot_id,
               const Estimate& estimate);
  /// The first failure to publish since reset(), or OK.
  const absl::Status& error() const { return error_; }

 private:
  channel::ChannelClient* channel_;
  uint64_t seq_ = 0;
  absl::Status error_;
};

}  // namespace behaviorlib::flight
