#pragma once

// The ground truth and the pose estimate of one robot, recorded off the
// data channel by stamp, for the tests of estimators:
//
//   PoseTracks tracks;
//   ASSERT_NO_FATAL_FAILURE(tracks.record(channel, "drone1"));
//   ... fly ...
//   tracks.stop();
//   compare(tracks.truth.points(), tracks.estimate.points());

#include <google/protobuf/util/time_util.h>
#include <gtest/gtest.h>

#include <array>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <utility>

#include "behaviorlib/channel/channel_client.h"
#include "behaviorlib/v1/types.pb.h"

namespace pose_tracks {

/// Poses on a topic, by stamp (ns of simulated time): x, y, z, yaw.
class Track {
 public:
  using Pose = std::array<double, 4>;

  void add(const behaviorlib::v1::PoseStamped& pose) {
    const auto& p = pose.pose().position_m();
    const auto& q = pose.pose().orientation();
    const double yaw = std::atan2(2.0 * (q.w() * q.z() + q.x() * q.y()),
                                  1.0 - 2.0 * (q.y() * q.y() + q.z() * q.z()));
    std::lock_guard lock(mutex_);
    points_[google::protobuf::util::TimeUtil::TimestampToNanoseconds(pose.header().stamp())] = {
        p.x(), p.y(), p.z(), yaw};
  }
  /// The newest stamp and pose, if any.
  std::optional<std::pair<int64_t, Pose>> newest() const {
    std::lock_guard lock(mutex_);
    if (points_.empty()) return std::nullopt;
    return *points_.rbegin();
  }
  std::map<int64_t, Pose> points() const {
    std::lock_guard lock(mutex_);
    return points_;
  }

 private:
  mutable std::mutex mutex_;
  std::map<int64_t, Pose> points_;
};

/// robots/{id}/ground_truth/pose and robots/{id}/self_localization/pose,
/// queued (none skipped) while recording.
struct PoseTracks {
  Track truth, estimate;

  void record(behaviorlib::channel::ChannelClient& channel, const std::string& robot_id) {
    const behaviorlib::channel::SubscribeOptions queued{
        .mode = behaviorlib::v1::DELIVERY_MODE_QUEUE, .queue_size = 5000};
    truth_sub_ = channel.subscribeTyped<behaviorlib::v1::PoseStamped>(
        "robots/" + robot_id + "/ground_truth/pose", queued,
        [this](const behaviorlib::v1::PoseStamped& p) { truth.add(p); });
    estimate_sub_ = channel.subscribeTyped<behaviorlib::v1::PoseStamped>(
        "robots/" + robot_id + "/self_localization/pose", queued,
        [this](const behaviorlib::v1::PoseStamped& p) { estimate.add(p); });
    ASSERT_TRUE(truth_sub_->waitConnected(std::chrono::seconds(5)));
    ASSERT_TRUE(estimate_sub_->waitConnected(std::chrono::seconds(5)));
  }
  /// Stops recording (before the tracks are read for good).
  void stop() {
    truth_sub_.reset();
    estimate_sub_.reset();
  }

 private:
  std::unique_ptr<behaviorlib::channel::Subscription> truth_sub_, estimate_sub_;
};

}  // namespace pose_tracks
