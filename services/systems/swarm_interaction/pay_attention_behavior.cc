#include "behaviorlib/swarm_interaction/pay_attention_behavior.h"

#include <google/protobuf/util/json_util.h>
#include <google/protobuf/util/time_util.h>

#include "behaviorlib/flight_common/flight_monitoring.h"
#include "behaviorlib/flight_common/flight_support.h"
#include "behaviorlib/swarm_interaction/swarm_topics.h"

namespace behaviorlib::swarm {
namespace {

namespace pb = google::protobuf;

constexpr channel::SubscribeOptions kQueued{.mode = v1::DELIVERY_MODE_QUEUE, .queue_size = 1000};

pb::Value stringValue(const std::string& s) {
  pb::Value v;
  v.set_string_value(s);
  return v;
}

pb::Value numberValue(double d) {
  pb::Value v;
  v.set_number_value(d);
  return v;
}

// The belief of a received message: {from, text, payload, recipient_ids,
// stamp}; payload is the parsed payload_json (null when none).
pb::Value messageValue(const v1::SwarmMessage& m) {
  pb::Value value;
  auto& fields = *value.mutable_struct_value()->mutable_fields();
  fields["from"] = stringValue(m.header().robot_id());
  fields["text"] = stringValue(m.text());
  pb::Value payload;
  payload.set_null_value(pb::NULL_VALUE);
  if (!m.payload_json().empty()) {
    // Checked by malformedMessage() before it was queued.
    (void)pb::util::JsonStringToMessage(m.payload_json(), &payload);
  }
  fields["payload"] = payload;
  auto* recipients = fields["recipient_ids"].mutable_list_value();
  for (const auto& id : m.recipient_ids()) *recipients->add_values() = stringValue(id);
  fields["stamp"] = stringValue(pb::util::TimeUtil::ToString(m.header().stamp()));
  return value;
}

}  // namespace

PayAttentionToRobotMessagesBehavior::PayAttentionToRobotMessagesBehavior(
    channel::ChannelClient* channel, const server::BeliefClient* beliefs)
    : Behavior(flight::flightBehaviorOptions(Duration::zero())),
      channel_(channel),
      beliefs_(beliefs) {}

PayAttentionToRobotMessagesBehavior::~PayAttentionToRobotMessagesBehavior() { stop(); }

absl::Status PayAttentionToRobotMessagesBehavior::onConfigure(
    const config::v1::PayAttentionToRobotMessagesConfig& config) {
  channel_timeout_ = seconds(config.channel_timeout_s());
  write_period_s_ = config.write_period_s();
  return absl::OkStatus();
}

void PayAttentionToRobotMessagesBehavior::countMalformed(const std::string& why) {
  if (!recording_) return;
  ++malformed_;
  last_malformed_ = why;
}

void PayAttentionToRobotMessagesBehavior::onMessage(const v1::SubscribeResponse& sample) {
  v1::SwarmMessage message;
  if (!sample.sample().UnpackTo(&message)) {
    return countMalformed("a sample of type " + sample.sample().type_url() + " on " +
                          kMessagesTopic);
  }
  if (auto why = malformedMessage(message)) return countMalformed(*why);
  if (message.header().robot_id() == robotId() ||
      !addressedTo(message.recipient_ids(), robotId())) {
    return;
  }
  if (!recording_) return;
  pending_messages_.push_back(std::move(message));
}

void PayAttentionToRobotMessagesBehavior::onPosition(const v1::SubscribeResponse& sample) {
  v1::SwarmPosition position;
  if (!sample.sample().UnpackTo(&position)) {
    return countMalformed("a sample of type " + sample.sample().type_url() + " on " +
                          kPositionsTopic);
  }
  if (auto why = malformedPosition(position)) return countMalformed(*why);
  const std::string sender = position.header().robot_id();
  if (sender == robotId() || !addressedTo(position.recipient_ids(), robotId())) return;
  if (!recording_) return;
  ++positions_received_;
  pending_positions_[sender] = std::move(position);
}

void PayAttentionToRobotMessagesBehavior::recordWrites(const WriteOutcome& outcome) {
  if (!outcome.failing) {
    write_failing_ = false;
    write_error_.reset();
    return;
  }
  if (!write_failing_) write_error_ = outcome.error;
  write_failing_ = true;
}

PayAttentionToRobotMessagesBehavior::BatchResult PayAttentionToRobotMessagesBehavior::writeBatch(
    const server::BeliefClient& beliefs, Batch batch) {
  BatchResult result;
  result.count = batch.count;
  auto write = [&](const std::string& key, const pb::Value& value, const std::string& type) {
    auto written = beliefs.write(key, value, batch.writer, type);
    if (written.ok()) {
      result.outcome = {};
      return true;
    }
    if (!result.outcome.failing) result.outcome.error = std::string(written.status().message());
    result.outcome.failing = true;
    return false;
  };
  for (const auto& [sender, position] : batch.positions) {
    std::string json;
    pb::util::JsonPrintOptions print;
    print.preserve_proto_field_names = true;
    pb::Value value;
    if (pb::util::MessageToJsonString(position, &json, print).ok() &&
        pb::util::JsonStringToMessage(json, &value).ok()) {
      write(batch.prefix + sender + "/position", value, position.GetTypeName());
    }
  }
  while (!batch.messages.empty()) {
    if (!write(batch.prefix + "messages/" + std::to_string(result.count + 1),
               messageValue(batch.messages.front()), "")) {
      break;  // kept for the next round, in order
    }
    ++result.count;
    batch.messages.pop_front();
    write(batch.prefix + "message_count", numberValue(static_cast<double>(result.count)), "");
  }
  result.unwritten = std::move(batch.messages);
  result.malformed_written =
      batch.malformed_changed && write(batch.prefix + "malformed_count",
                                       numberValue(static_cast<double>(batch.malformed)), "");
  result.malformed = batch.malformed;
  return result;
}

void PayAttentionToRobotMessagesBehavior::startWrites() {
  const auto wall = std::chrono::steady_clock::now();
  if (writing_ || wall < next_write_) return;
  const std::string prefix = robotId() + "/swarm/";
  if (!count_) {
    // Numbering goes on from an earlier activation (or process).
    writing_ = true;
    const server::BeliefClient* beliefs = beliefs_;
    inBackground<absl::StatusOr<v1::Belief>>(
        [beliefs, key = prefix + "message_count"] { return beliefs->read(key); },
        [this](const absl::StatusOr<v1::Belief>& previous) {
          writing_ = false;
          if (previous.ok() || previous.status().code() == absl::StatusCode::kNotFound) {
            count_ = previous.ok() ? static_cast<uint64_t>(previous->value().number_value()) : 0;
            recordWrites({});
            startWrites();
            return;
          }
          recordWrites({true, std::string(previous.status().message())});
          next_write_ = std::chrono::steady_clock::now() + std::chrono::milliseconds(200);
        });
    return;
  }
  const bool malformed_changed = malformed_ != malformed_written_;
  if (pending_positions_.empty() && pending_messages_.empty() && !malformed_changed) return;
  Batch batch;
  batch.prefix = prefix;
  batch.writer = robotId() + "/PAY_ATTENTION_TO_ROBOT_MESSAGES";
  batch.positions.swap(pending_positions_);
  batch.messages.swap(pending_messages_);
  batch.malformed = malformed_;
  batch.malformed_changed = malformed_changed;
  batch.count = *count_;
  writing_ = true;
  const server::BeliefClient* beliefs = beliefs_;
  inBackground<BatchResult>(
      [beliefs, batch = std::move(batch)] { return writeBatch(*beliefs, batch); },
      [this](const BatchResult& result) {
        writing_ = false;
        count_ = result.count;
        if (result.malformed_written) malformed_written_ = result.malformed;
        // Unwritten messages go back in front of newer ones.
        for (auto it = result.unwritten.rbegin(); it != result.unwritten.rend(); ++it) {
          pending_messages_.push_front(*it);
        }
        recordWrites(result.outcome);
        next_write_ = std::chrono::steady_clock::now() +
                      std::chrono::duration_cast<std::chrono::steady_clock::duration>(
                          std::chrono::duration<double>(write_period_s_));
      });
}

absl::Status PayAttentionToRobotMessagesBehavior::onActivate() {
  pending_positions_.clear();
  pending_messages_.clear();
  malformed_written_ = malformed_;
  positions_received_ = 0;
  write_failing_ = false;
  write_error_.reset();
  count_.reset();
  writing_ = false;
  next_write_ = {};
  recording_ = true;
  messages_sub_ = channel_->subscribe(
      kMessagesTopic, kQueued,
      onWorker<v1::SubscribeResponse>([this](const v1::SubscribeResponse& s) { onMessage(s); }));
  positions_sub_ = channel_->subscribe(
      kPositionsTopic, kQueued,
      onWorker<v1::SubscribeResponse>([this](const v1::SubscribeResponse& s) { onPosition(s); }));
  activated_at_ = last_position_at_ = now();
  positions_seen_ = 0;
  disconnected_since_.reset();
  failing_since_.reset();
  active_ = true;
  startWrites();
  return absl::OkStatus();
}

void PayAttentionToRobotMessagesBehavior::onExecute() { startWrites(); }

void PayAttentionToRobotMessagesBehavior::stop() {
  recording_ = false;
  messages_sub_.reset();
  positions_sub_.reset();
}

void PayAttentionToRobotMessagesBehavior::onDeactivate() {
  active_ = false;
  stop();
}

void PayAttentionToRobotMessagesBehavior::onPause() { recording_ = false; }

void PayAttentionToRobotMessagesBehavior::onResume() { recording_ = true; }

Situation PayAttentionToRobotMessagesBehavior::checkSituation() {
  if (!channel_) {
    return Situation::infeasible(
        v1::SITUATION_REASON_CONFIGURATION,
        "no data channel configured: start the behavior system with --channel HOST:PORT");
  }
  if (!beliefs_) {
    return Situation::infeasible(
        v1::SITUATION_REASON_PEER_UNAVAILABLE,
        "no belief memory to record messages in: start the behavior system with --coordinator "
        "HOST:PORT");
  }
  return Situation::ok();
}

Verdict PayAttentionToRobotMessagesBehavior::checkProcesses() {
  const TimePoint t = now();
  // The subscriptions reconnect by themselves; a broker gone for longer is
  // a stale channel.
  const bool connected = messages_sub_->connected() && positions_sub_->connected();
  if (connected) {
    disconnected_since_.reset();
  } else if (!disconnected_since_) {
    disconnected_since_ = t;
  } else if (t - *disconnected_since_ > channel_timeout_) {
    const auto& sub = messages_sub_->connected() ? positions_sub_ : messages_sub_;
    return Verdict::finish("the swarm's channel is stale: not subscribed at the broker " +
                           channel_->address() + " for " +
                           flight::secondsText(t - *disconnected_since_) + " (" +
                           std::string(sub->status().message()) + ")");
  }
  const uint64_t received = positions_received_;
  std::optional<std::string> write_error;
  if (write_failing_) write_error = write_error_.value_or("unknown error");
  if (received != positions_seen_) {
    positions_seen_ = received;
    last_position_at_ = t;
  }
  const double max_silence_s = parameters().max_silence_s();
  if (max_silence_s > 0 &&
      std::chrono::duration<double>(t - last_position_at_).count() > max_silence_s) {
    return Verdict::finish("the swarm's channel is stale: no position of another robot on " +
                           std::string(kPositionsTopic) + " for " +
                           flight::secondsText(t - last_position_at_) + " (max_silence_s " +
                           flight::fixed2(max_silence_s) + ")");
  }
  if (!write_error) {
    failing_since_.reset();
  } else if (!failing_since_) {
    failing_since_ = t;
  } else if (t - *failing_since_ > channel_timeout_) {
    return Verdict::finish("cannot write belief memory at the coordinator " + beliefs_->address() +
                           " for " + flight::secondsText(t - *failing_since_) + ": " +
                           *write_error);
  }
  return Verdict::keepGoing();
}

}  // namespace behaviorlib::swarm
