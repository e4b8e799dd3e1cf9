#include "behaviorlib/swarm_interaction/inform_position_behavior.h"

#include "behaviorlib/flight_common/flight_monitoring.h"
#include "behaviorlib/flight_common/flight_support.h"
#include "behaviorlib/flight_common/topics.h"
#include "behaviorlib/flight_common/vehicle.h"
#include "behaviorlib/swarm_interaction/swarm_topics.h"

namespace behaviorlib::swarm {
namespace {

BehaviorOptions positionOptions() {
  BehaviorOptions o = flight::flightBehaviorOptions(Duration::zero());
  o.frequency_hz = 50.0;  // the highest rate_hz
  return o;
}

Duration periodOf(double rate_hz) { return seconds(1.0 / rate_hz); }

absl::Status checkRecipients(const google::protobuf::RepeatedPtrField<std::string>& ids) {
  for (int i = 0; i < ids.size(); ++i) {
    if (!validRobotId(ids.Get(i))) {
      return absl::InvalidArgumentError("parameter 'robot_ids[" + std::to_string(i) + "]': '" +
                                        ids.Get(i) +
                                        "' is not a robot id (letters, digits, '_', '-', '.')");
    }
  }
  return absl::OkStatus();
}

}  // namespace

InformPositionToRobotsBehavior::InformPositionToRobotsBehavior(channel::ChannelClient* channel)
    : Behavior(positionOptions()), channel_(channel) {}

InformPositionToRobotsBehavior::~InformPositionToRobotsBehavior() { pose_sub_.reset(); }

absl::Status InformPositionToRobotsBehavior::onConfigure(
    const config::v1::InformPositionToRobotsConfig& config) {
  pose_timeout_ = seconds(config.pose_timeout_s());
  return absl::OkStatus();
}

absl::Status InformPositionToRobotsBehavior::onActivate() {
  if (auto s = checkRecipients(parameters().robot_ids()); !s.ok()) return s;
  latest_.reset();
  error_ = absl::OkStatus();
  next_publish_.reset();
  pose_sub_ = channel_->subscribeTyped<v1::PoseStamped>(
      flight::poseEstimateTopic(robotId()),
      {.mode = v1::DELIVERY_MODE_LATEST, .send_latest_first = true},
      onWorker<v1::PoseStamped>([this](const v1::PoseStamped& pose) { latest_ = pose; },
                                Delivery::kLatest));
  activated_at_ = now();
  active_ = true;
  return absl::OkStatus();
}

void InformPositionToRobotsBehavior::onDeactivate() {
  active_ = false;
  pose_sub_.reset();
}

absl::Status InformPositionToRobotsBehavior::onModify(
    const v1::InformPositionToRobotsParameters& p) {
  if (auto s = checkRecipients(p.robot_ids()); !s.ok()) return s;
  next_publish_.reset();  // the new rate applies from now
  return absl::OkStatus();
}

void InformPositionToRobotsBehavior::onExecute() {
  const TimePoint t = now();
  if (next_publish_ && t < *next_publish_) return;
  const std::optional<v1::PoseStamped>& pose = latest_;
  if (!pose) return;
  const double max_stddev_m = parameters().max_horizontal_stddev_m();
  if (max_stddev_m > 0.0 && pose->has_horizontal_stddev_m() &&
      pose->horizontal_stddev_m() > max_stddev_m) {
    // Not worth sharing yet: the next estimate is judged a period later.
    next_publish_ = t + periodOf(parameters().rate_hz());
    return;
  }
  v1::SwarmPosition position;
  *position.mutable_header() = pose->header();
  position.mutable_header()->set_frame_id("world");
  position.mutable_header()->set_robot_id(robotId());
  position.mutable_header()->set_seq(++seq_);
  *position.mutable_recipient_ids() = parameters().robot_ids();
  *position.mutable_pose() = pose->pose();
  if (pose->has_horizontal_stddev_m())
    position.set_horizontal_stddev_m(pose->horizontal_stddev_m());
  if (absl::Status s = channel_->publish(kPositionsTopic, position); !s.ok()) error_ = s;
  const Duration period = periodOf(parameters().rate_hz());
  // Keeps the rate without drifting; after a stall it restarts from now.
  next_publish_ =
      next_publish_ && t - *next_publish_ < period ? *next_publish_ + period : t + period;
}

Situation InformPositionToRobotsBehavior::checkSituation() {
  if (!channel_) {
    return Situation::infeasible(
        v1::SITUATION_REASON_CONFIGURATION,
        "no data channel configured: start the behavior system with --channel HOST:PORT");
  }
  if (active_) return Situation::ok();
  const std::string topic = flight::poseEstimateTopic(robotId());
  auto sample = channel_->getLatest(topic, flight::kChannelReadTimeout);
  if (!sample.ok()) {
    return Situation::infeasible(
        sample.status().code() == absl::StatusCode::kNotFound
            ? v1::SITUATION_REASON_INPUT_MISSING
            : v1::SITUATION_REASON_PLATFORM_UNAVAILABLE,
        sample.status().code() == absl::StatusCode::kNotFound
            ? "no pose estimate on " + topic + ": activate a self-localization behavior first"
            : "cannot read " + topic + " from the channel at " + channel_->address() + ": " +
                  std::string(sample.status().message()));
  }
  v1::PoseStamped pose;
  if (!sample->sample().UnpackTo(&pose)) {
    return Situation::infeasible(v1::SITUATION_REASON_INPUT_INVALID,
                                 topic + " does not carry behaviorlib.v1.PoseStamped");
  }
  if (auto stale = flight::staleness([&] { return "the pose estimate on " + topic; }, pose.header(),
                                     now(), 2 * pose_timeout_)) {
    return Situation::infeasible(v1::SITUATION_REASON_INPUT_STALE,
                                 *stale + "; is a self-localization behavior active?");
  }
  return Situation::ok();
}

Verdict InformPositionToRobotsBehavior::checkProcesses() {
  if (!error_.ok()) {
    return Verdict::finish("cannot publish on " + std::string(kPositionsTopic) + ": " +
                           std::string(error_.message()));
  }
  const TimePoint t = now();
  const std::string topic = flight::poseEstimateTopic(robotId());
  if (!latest_) {
    if (t - activated_at_ > pose_timeout_) {
      return Verdict::finish("no pose estimate received on " + topic + " within " +
                             flight::secondsText(pose_timeout_));
    }
    return Verdict::keepGoing();
  }
  if (auto stale = flight::staleness([&] { return "the pose estimate on " + topic; },
                                     latest_->header(), t, pose_timeout_)) {
    return Verdict::finish(*stale);
  }
  return Verdict::keepGoing();
}

}  // namespace behaviorlib::swarm
