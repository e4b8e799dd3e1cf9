#include "behaviorlib/operator_interaction/request_assistance_behavior.h"

#include <google/protobuf/util/json_util.h>

#include "behaviorlib/flight_common/flight_monitoring.h"
#include "behaviorlib/flight_common/flight_support.h"
#include "behaviorlib/operator_interaction/operator_beliefs.h"

namespace behaviorlib::operator_interaction {
namespace {

BehaviorOptions requestOptions() {
  BehaviorOptions o;
  o.frequency_hz = 20.0;
  // onDeactivate makes one call to the coordinator (at most 0.5 s).
  o.watchdog_timeout = std::chrono::milliseconds(2000);
  return o;
}

}  // namespace

RequestOperatorAssistanceBehavior::RequestOperatorAssistanceBehavior(
    const server::BeliefClient* beliefs)
    : Behavior(requestOptions()), beliefs_(beliefs) {}

RequestOperatorAssistanceBehavior::~RequestOperatorAssistanceBehavior() { watch_.reset(); }

absl::Status RequestOperatorAssistanceBehavior::onConfigure(
    const config::v1::RequestOperatorAssistanceConfig& config) {
  read_failure_timeout_ = seconds(config.read_failure_timeout_s());
  poll_period_s_ = config.poll_period_s();
  return absl::OkStatus();
}

google::protobuf::Value RequestOperatorAssistanceBehavior::requestValue(
    const std::string& state) const {
  google::protobuf::Value request;
  auto& fields = *request.mutable_struct_value()->mutable_fields();
  fields["robot_id"] = stringValue(robotId());
  fields["question"] = stringValue(parameters().question());
  fields["answer_key"] = stringValue(answer_key_);
  fields["timeout_s"] = numberValue(parameters().timeout_s());
  fields["time"] = stringValue(timeText(asked_at_));
  fields["state"] = stringValue(state);
  return request;
}

absl::Status RequestOperatorAssistanceBehavior::onActivate() {
  const auto& p = parameters();
  if (p.question().empty()) {
    return absl::InvalidArgumentError("parameter 'question': empty; ask the operator something");
  }
  // "REQUEST_OPERATOR_ASSISTANCE-<incarnation>-<n>": unique per process run.
  request_id_ = p.request_id().empty()
                    ? robotId() + "-" + activationId().substr(activationId().find('-') + 1)
                    : p.request_id();
  if (!validKeySegment(request_id_)) {
    return absl::InvalidArgumentError("parameter 'request_id': '" + request_id_ +
                                      "' is not a belief key segment (letters, digits, '_', "
                                      "'-', '.')");
  }
  answer_key_ =
      p.answer_key().empty() ? robotId() + "/operator_answers/" + request_id_ : p.answer_key();
  if (!validKey(answer_key_)) {
    return absl::InvalidArgumentError(
        "parameter 'answer_key': '" + answer_key_ +
        "' is not a belief key (letters, digits, '_', '-', '.', segments separated by '/')");
  }
  setMaximumExecutionTime(seconds(p.timeout_s()));
  asked_at_ = now();
  failing_since_.reset();
  watch_ = std::make_unique<AnswerWatch>(
      *beliefs_, AnswerWatch::Request{.request_key = "operator/requests/" + request_id_,
                                      .question = requestValue("open"),
                                      .answer_key = "operator/answers/" + request_id_,
                                      .copy_key = answer_key_,
                                      .writer = robotId() + "/REQUEST_OPERATOR_ASSISTANCE",
                                      .poll_period = std::chrono::milliseconds(
                                          static_cast<int64_t>(poll_period_s_ * 1000))});
  watch_->start();
  return absl::OkStatus();
}

void RequestOperatorAssistanceBehavior::onDeactivate() {
  if (!watch_) return;
  watch_->stop();
  const bool asked = watch_->questionVersion() > 0;
  const bool answered = watch_->state() == AnswerWatch::State::kAnswered;
  watch_.reset();
  if (!asked) return;
  const std::string state = answered                                            ? "answered"
                            : activeTime() >= seconds(parameters().timeout_s()) ? "timed_out"
                                                                                : "withdrawn";
  // Best effort: the operator's view of the request; the outcome is the
  // behavior's event either way.
  (void)beliefs_->write("operator/requests/" + request_id_, requestValue(state),
                        robotId() + "/REQUEST_OPERATOR_ASSISTANCE");
}

absl::Status RequestOperatorAssistanceBehavior::onModify(
    const v1::RequestOperatorAssistanceParameters& p) {
  if (p.question() != parameters().question() || p.answer_key() != parameters().answer_key() ||
      p.request_id() != parameters().request_id()) {
    return absl::InvalidArgumentError(
        "only timeout_s can change while the question is open; deactivate and ask again");
  }
  setMaximumExecutionTime(seconds(p.timeout_s()));
  return absl::OkStatus();
}

Situation RequestOperatorAssistanceBehavior::checkSituation() {
  if (!beliefs_) {
    return Situation::infeasible(
        v1::SITUATION_REASON_PEER_UNAVAILABLE,
        "no coordinator to ask the operator through: start the behavior system with "
        "--coordinator HOST:PORT");
  }
  return Situation::ok();
}

Verdict RequestOperatorAssistanceBehavior::checkGoal() {
  if (!watch_ || watch_->state() != AnswerWatch::State::kAnswered) return Verdict::keepGoing();
  std::string json;
  (void)google::protobuf::util::MessageToJsonString(watch_->answer()->value(), &json);
  return Verdict::finish("the operator answered " + json + " (copied to " + answer_key_ + ")");
}

Verdict RequestOperatorAssistanceBehavior::checkProcesses() {
  const auto failure = watch_ ? watch_->failure() : std::nullopt;
  const TimePoint t = now();
  if (!failure) {
    failing_since_.reset();
  } else if (!failing_since_) {
    failing_since_ = t;
  } else if (t - *failing_since_ > read_failure_timeout_) {
    return Verdict::finish("cannot reach belief memory at the coordinator " + beliefs_->address() +
                           " for " + flight::secondsText(t - *failing_since_) + ": " + *failure);
  }
  return Verdict::keepGoing();
}

}  // namespace behaviorlib::operator_interaction
