#include "behaviorlib/swarm_interaction/inform_robots_behavior.h"

#include "behaviorlib/flight_common/flight_support.h"
#include "behaviorlib/swarm_interaction/swarm_topics.h"

namespace behaviorlib::swarm {

absl::Status checkInformRobotsParameters(const v1::InformRobotsParameters& p) {
  if (p.text().empty() && p.payload_json().empty()) {
    return absl::InvalidArgumentError(
        "parameter 'text': set text or payload_json (a message needs content)");
  }
  if (!p.payload_json().empty() && !isJson(p.payload_json())) {
    return absl::InvalidArgumentError("parameter 'payload_json': not JSON text: " +
                                      p.payload_json());
  }
  for (int i = 0; i < p.robot_ids_size(); ++i) {
    if (!validRobotId(p.robot_ids(i))) {
      return absl::InvalidArgumentError("parameter 'robot_ids[" + std::to_string(i) + "]': '" +
                                        p.robot_ids(i) +
                                        "' is not a robot id (letters, digits, '_', '-', '.')");
    }
  }
  return absl::OkStatus();
}

InformRobotsBehavior::InformRobotsBehavior(channel::ChannelClient* channel)
    : Behavior(flight::flightBehaviorOptions(Duration::zero())), channel_(channel) {}

absl::Status InformRobotsBehavior::onActivate() {
  sent_ = false;
  error_ = absl::OkStatus();
  return checkInformRobotsParameters(parameters());
}

absl::Status InformRobotsBehavior::onModify(const v1::InformRobotsParameters& new_parameters) {
  if (sent_) return absl::FailedPreconditionError("the message has already been sent");
  return checkInformRobotsParameters(new_parameters);
}

void InformRobotsBehavior::onExecute() {
  if (sent_ || !error_.ok()) return;
  v1::SwarmMessage message;
  auto* header = message.mutable_header();
  *header->mutable_stamp() = toTimestamp(now());
  header->set_robot_id(robotId());
  header->set_seq(++seq_);
  *message.mutable_recipient_ids() = parameters().robot_ids();
  message.set_text(parameters().text());
  message.set_payload_json(parameters().payload_json());
  absl::Status s = channel_->publish(kMessagesTopic, message);
  if (s.ok()) {
    // The stream is asynchronous: closing it returns the broker's verdict.
    auto accepted = channel_->flush();
    if (!accepted.ok()) s = accepted.status();
  }
  if (s.ok()) {
    sent_ = true;
  } else {
    error_ = s;
  }
}

Situation InformRobotsBehavior::checkSituation() {
  if (!channel_) {
    return Situation::infeasible(
        v1::SITUATION_REASON_CONFIGURATION,
        "no data channel configured: start the behavior system with --channel HOST:PORT");
  }
  return Situation::ok();
}

Verdict InformRobotsBehavior::checkGoal() {
  if (!sent_) return Verdict::keepGoing();
  const int n = parameters().robot_ids_size();
  std::string to = "every robot";
  if (n > 0) {
    to.clear();
    for (int i = 0; i < n; ++i) to += (i ? ", " : "") + parameters().robot_ids(i);
  }
  return Verdict::finish("message sent on " + std::string(kMessagesTopic) + " to " + to);
}

Verdict InformRobotsBehavior::checkProcesses() {
  if (error_.ok()) return Verdict::keepGoing();
  return Verdict::finish("cannot publish on " + std::string(kMessagesTopic) + ": " +
                         std::string(error_.message()));
}

}  // namespace behaviorlib::swarm
