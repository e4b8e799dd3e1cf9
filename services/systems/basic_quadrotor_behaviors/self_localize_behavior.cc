#include "behaviorlib/basic_quadrotor_behaviors/self_localize_behavior.h"

#include <cmath>

#include "behaviorlib/flight_common/flight_monitoring.h"
#include "behaviorlib/flight_common/flight_support.h"
#include "behaviorlib/flight_common/topics.h"
#include "behaviorlib/flight_common/vehicle.h"

namespace behaviorlib::basic {
SelfLocalizeWithGroundTruthBehavior::SelfLocalizeWithGroundTruthBehavior(
    channel::ChannelClient* channel)
    : Behavior(flight::flightBehaviorOptions(Duration::zero())), channel_(channel) {}

SelfLocalizeWithGroundTruthBehavior::~SelfLocalizeWithGroundTruthBehavior() { stopSubscriptions(); }

absl::Status SelfLocalizeWithGroundTruthBehavior::onConfigure(
    const config::v1::SelfLocalizeWithGroundTruthConfig& config) {
  timeout_ = seconds(config.ground_truth_timeout_s());
  max_jump_m_ = config.max_jump_m();
  return absl::OkStatus();
}

void SelfLocalizeWithGroundTruthBehavior::onPose(const v1::PoseStamped& pose) {
  if (last_pose_ && jump_.empty()) {
    const auto& a = last_pose_->pose().position_m();
    const auto& b = pose.pose().position_m();
    const double jump =
        std::sqrt((a.x() - b.x()) * (a.x() - b.x()) + (a.y() - b.y()) * (a.y() - b.y()) +
                  (a.z() - b.z()) * (a.z() - b.z()));
    if (!(jump <= max_jump_m_)) {
      jump_ = "the ground truth jumped " + flight::fixed2(jump) + " m in " +
              flight::secondsText(flight::stampTime(pose.header()) -
                                  flight::stampTime(last_pose_->header())) +
              " (limit " + flight::fixed2(max_jump_m_) + " m between samples)";
    }
  }
  last_pose_ = pose;
  if (!publishing_) return;
  v1::PoseStamped estimate = pose;
  estimate.mutable_header()->set_seq(++seq_);
  estimate.mutable_header()->set_frame_id("world");
  estimate.mutable_header()->set_robot_id(robotId());
  estimate.set_horizontal_stddev_m(0.0);  // the ground truth is exact
  if (absl::Status s = channel_->publish(flight::poseEstimateTopic(robotId()), estimate); !s.ok()) {
    if (publish_error_.ok()) publish_error_ = s;
  }
}

void SelfLocalizeWithGroundTruthBehavior::onTwist(const v1::TwistStamped& twist) {
  if (!publishing_) return;
  v1::TwistStamped estimate = twist;
  estimate.mutable_header()->set_seq(++twist_seq_);
  estimate.mutable_header()->set_robot_id(robotId());
  if (absl::Status s = channel_->publish(flight::twistEstimateTopic(robotId()), estimate);
      !s.ok()) {
    if (publish_error_.ok()) publish_error_ = s;
  }
}

absl::Status SelfLocalizeWithGroundTruthBehavior::onActivate() {
  last_pose_.reset();
  jump_.clear();
  publish_error_ = absl::OkStatus();
  publishing_ = true;
  const channel::SubscribeOptions options{.mode = v1::DELIVERY_MODE_LATEST,
                                          .send_latest_first = true};
  pose_subscription_ = channel_->subscribeTyped<v1::PoseStamped>(
      flight::groundTruthPoseTopic(robotId()), options,
      onWorker<v1::PoseStamped>([this](const v1::PoseStamped& pose) { onPose(pose); },
                                Delivery::kLatest));
  twist_subscription_ = channel_->subscribeTyped<v1::TwistStamped>(
      flight::groundTruthTwistTopic(robotId()), options,
      onWorker<v1::TwistStamped>([this](const v1::TwistStamped& twist) { onTwist(twist); },
                                 Delivery::kLatest));
  activated_at_ = now();
  active_ = true;
  return absl::OkStatus();
}

void SelfLocalizeWithGroundTruthBehavior::stopSubscriptions() {
  publishing_ = false;
  pose_subscription_.reset();
  twist_subscription_.reset();
}

void SelfLocalizeWithGroundTruthBehavior::onDeactivate() {
  active_ = false;
  stopSubscriptions();
}

void SelfLocalizeWithGroundTruthBehavior::onPause() { publishing_ = false; }

void SelfLocalizeWithGroundTruthBehavior::onResume() { publishing_ = true; }

Situation SelfLocalizeWithGroundTruthBehavior::checkSituation() {
  if (!channel_) {
    return Situation::infeasible(
        v1::SITUATION_REASON_CONFIGURATION,
        "no data channel configured: start the behavior system with --channel HOST:PORT");
  }
  if (active_) return Situation::ok();
  const std::string topic = flight::groundTruthPoseTopic(robotId());
  auto sample = channel_->getLatest(topic, flight::kChannelReadTimeout);
  if (!sample.ok()) {
    return Situation::infeasible(sample.status().code() == absl::StatusCode::kNotFound
                                     ? v1::SITUATION_REASON_INPUT_MISSING
                                     : v1::SITUATION_REASON_PLATFORM_UNAVAILABLE,
                                 sample.status().code() == absl::StatusCode::kNotFound
                                     ? "no ground truth on " + topic +
                                           ": is the simulator running with --channel and a "
                                           "vehicle " +
                                           robotId() + "?"
                                     : "cannot read " + topic + " from the channel at " +
                                           channel_->address() + ": " +
                                           std::string(sample.status().message()));
  }
  v1::PoseStamped pose;
  if (!sample->sample().UnpackTo(&pose)) {
    return Situation::infeasible(v1::SITUATION_REASON_INPUT_INVALID,
                                 topic + " does not carry behaviorlib.v1.PoseStamped");
  }
  if (auto stale = flight::staleness([&] { return "the ground truth on " + topic; }, pose.header(),
                                     now(), timeout_)) {
    return Situation::infeasible(v1::SITUATION_REASON_INPUT_STALE,
                                 *stale + "; is the simulator running?");
  }
  return Situation::ok();
}

Verdict SelfLocalizeWithGroundTruthBehavior::checkProgress() {
  if (!jump_.empty()) return Verdict::finish(jump_);
  return Verdict::keepGoing();
}

Verdict SelfLocalizeWithGroundTruthBehavior::checkProcesses() {
  if (!publish_error_.ok()) {
    return Verdict::finish("cannot publish the estimate: " + std::string(publish_error_.message()));
  }
  const TimePoint t = now();
  if (!last_pose_) {
    // The subscription delivers the latest sample first: allow it the
    // timeout to arrive.
    if (t - activated_at_ > timeout_) {
      return Verdict::finish("no ground truth received on " +
                             flight::groundTruthPoseTopic(robotId()) + " within " +
                             flight::secondsText(timeout_));
    }
    return Verdict::keepGoing();
  }
  if (auto stale = flight::staleness(
          [&] { return "the ground truth on " + flight::groundTruthPoseTopic(robotId()); },
          last_pose_->header(), t, timeout_)) {
    return Verdict::finish(*stale);
  }
  return Verdict::keepGoing();
}

}  // namespace behaviorlib::basic
