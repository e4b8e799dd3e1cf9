#include "behaviorlib/operator_interaction/inform_operator_behavior.h"

#include <google/protobuf/util/time_util.h>

#include "behaviorlib/operator_interaction/operator_beliefs.h"
#include "behaviorlib/v1/types.pb.h"

namespace behaviorlib::operator_interaction {
namespace {

BehaviorOptions informOptions() {
  BehaviorOptions o;
  o.frequency_hz = 20.0;
  // onExecute makes three calls to the coordinator of at most 0.5 s each.
  o.watchdog_timeout = std::chrono::milliseconds(3000);
  return o;
}

}  // namespace

InformOperatorBehavior::InformOperatorBehavior(const server::BeliefClient* beliefs,
                                               channel::ChannelClient* channel)
    : Behavior(informOptions()), beliefs_(beliefs), channel_(channel) {}

absl::Status InformOperatorBehavior::onActivate() {
  done_ = false;
  key_.clear();
  error_ = absl::OkStatus();
  if (parameters().text().empty()) {
    return absl::InvalidArgumentError("parameter 'text': empty; say something to the operator");
  }
  return absl::OkStatus();
}

absl::Status InformOperatorBehavior::onModify(const v1::InformOperatorParameters& new_parameters) {
  if (done_) return absl::FailedPreconditionError("the message has already been written");
  if (new_parameters.text().empty()) {
    return absl::InvalidArgumentError("parameter 'text': empty; say something to the operator");
  }
  return absl::OkStatus();
}

absl::Status InformOperatorBehavior::inform() {
  const std::string writer = robotId() + "/INFORM_OPERATOR";
  const std::string count_key = "operator/message_counts/" + robotId();
  auto previous = beliefs_->read(count_key);
  if (!previous.ok() && previous.status().code() != absl::StatusCode::kNotFound) {
    return previous.status();
  }
  const uint64_t n =
      (previous.ok() ? static_cast<uint64_t>(previous->value().number_value()) : 0) + 1;
  const TimePoint t = now();
  google::protobuf::Value message;
  auto& fields = *message.mutable_struct_value()->mutable_fields();
  fields["robot_id"] = stringValue(robotId());
  fields["text"] = stringValue(parameters().text());
  fields["time"] = stringValue(timeText(t));
  key_ = "operator/messages/" + robotId() + "/" + std::to_string(n);
  if (auto s = beliefs_->write(key_, message, writer); !s.ok()) return s.status();
  if (auto s = beliefs_->write(count_key, numberValue(static_cast<double>(n)), writer); !s.ok()) {
    return s.status();
  }
  if (channel_) {
    v1::Text text;
    *text.mutable_header()->mutable_stamp() =
        google::protobuf::util::TimeUtil::NanosecondsToTimestamp(t.time_since_epoch().count());
    text.mutable_header()->set_robot_id(robotId());
    text.mutable_header()->set_seq(++seq_);
    text.set_text(parameters().text());
    if (auto s = channel_->publish("robots/" + robotId() + "/operator/messages", text); !s.ok()) {
      return s;
    }
  }
  return absl::OkStatus();
}

void InformOperatorBehavior::onExecute() {
  if (done_ || !error_.ok()) return;
  error_ = inform();
  done_ = error_.ok();
}

Situation InformOperatorBehavior::checkSituation() {
  if (!beliefs_) {
    return Situation::infeasible(
        v1::SITUATION_REASON_PEER_UNAVAILABLE,
        "no coordinator to hold the operator's messages: start the behavior system with "
        "--coordinator HOST:PORT");
  }
  return Situation::ok();
}

Verdict InformOperatorBehavior::checkGoal() {
  return done_ ? Verdict::finish("the operator's message is at " + key_) : Verdict::keepGoing();
}

Verdict InformOperatorBehavior::checkProcesses() {
  if (error_.ok()) return Verdict::keepGoing();
  return Verdict::finish("cannot inform the operator: " + std::string(error_.message()));
}

}  // namespace behaviorlib::operator_interaction
