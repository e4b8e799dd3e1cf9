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

absl::Status PayAttentionToRobotMessagesBehavior::onConfigure(const YAML::Node& config) {
  if (auto s = flight::readSeconds(config, "channel_timeout_s", 0, 600, &channel_timeout_);
      !s.ok()) {
    return s;
  }
  return flight::readNumber(config, "write_period_s", 0, 60, &write_period_s_);
}

void PayAttentionToRobotMessagesBehavior::countMalformed(const std::string& why) {
  std::lock_guard lock(mutex_);
  if (!recording_) return;
  ++malformed_;
  last_malformed_ = why;
  wake_.notify_all();
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
  std::lock_guard lock(mutex_);
  if (!recording_) return;
  pending_messages_.push_back(std::move(message));
  wake_.notify_all();
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
  std::lock_guard lock(mutex_);
  if (!recording_) return;
  ++positions_received_;
  pending_positions_[sender] = std::move(position);
  wake_.notify_all();
}

bool PayAttentionToRobotMessagesBehavior::writeBelief(const std::string& key,
                                                      const pb::Value& value,
                                                      const std::string& type) {
  const std::string writer = robotId() + "/PAY_ATTENTION_TO_ROBOT_MESSAGES";
  auto written = beliefs_->write(key, value, writer, type);
  std::lock_guard lock(mutex_);
  if (written.ok()) {
    write_failing_ = false;
    write_error_.reset();
    return true;
  }
  if (!write_failing_) write_error_ = std::string(written.status().message());
  write_failing_ = true;
  return false;
}

void PayAttentionToRobotMessagesBehavior::writerLoop() {
  const std::string prefix = robotId() + "/swarm/";
  const std::string count_key = prefix + "message_count";
  // Numbering goes on from an earlier activation (or process).
  uint64_t count = 0;
  for (;;) {
    auto previous = beliefs_->read(count_key);
    if (previous.ok() || previous.status().code() == absl::StatusCode::kNotFound) {
      if (previous.ok()) count = static_cast<uint64_t>(previous->value().number_value());
      std::lock_guard lock(mutex_);
      write_failing_ = false;
      write_error_.reset();
      break;
    }
    std::unique_lock lock(mutex_);
    if (!write_failing_) write_error_ = std::string(previous.status().message());
    write_failing_ = true;
    if (wake_.wait_for(lock, std::chrono::milliseconds(200), [&] { return !running_; })) return;
  }
  const auto period = std::chrono::duration_cast<std::chrono::steady_clock::duration>(
      std::chrono::duration<double>(write_period_s_));
  for (;;) {
    std::map<std::string, v1::SwarmPosition> positions;
    std::deque<v1::SwarmMessage> messages;
    uint64_t malformed = 0;
    bool malformed_changed = false;
    {
      std::unique_lock lock(mutex_);
      wake_.wait(lock, [&] {
        return !running_ || !pending_positions_.empty() || !pending_messages_.empty() ||
               malformed_ != malformed_written_;
      });
      if (!running_) return;
      positions.swap(pending_positions_);
      messages.swap(pending_messages_);
      malformed = malformed_;
      malformed_changed = malformed_ != malformed_written_;
    }
    for (const auto& [sender, position] : positions) {
      std::string json;
      pb::util::JsonPrintOptions print;
      print.preserve_proto_field_names = true;
      pb::Value value;
      if (pb::util::MessageToJsonString(position, &json, print).ok() &&
          pb::util::JsonStringToMessage(json, &value).ok()) {
        writeBelief(prefix + sender + "/position", value, position.GetTypeName());
      }
    }
    while (!messages.empty()) {
      if (!writeBelief(prefix + "messages/" + std::to_string(count + 1),
                       messageValue(messages.front()), "")) {
        break;  // kept for the next round, in order
      }
      ++count;
      messages.pop_front();
      writeBelief(count_key, numberValue(static_cast<double>(count)), "");
    }
    if (malformed_changed &&
        writeBelief(prefix + "malformed_count", numberValue(static_cast<double>(malformed)), "")) {
      std::lock_guard lock(mutex_);
      malformed_written_ = malformed;
    }
    std::unique_lock lock(mutex_);
    // Unwritten messages go back in front of newer ones.
    for (auto it = messages.rbegin(); it != messages.rend(); ++it) {
      pending_messages_.push_front(std::move(*it));
    }
    if (wake_.wait_for(lock, period, [&] { return !running_; })) return;
  }
}

absl::Status PayAttentionToRobotMessagesBehavior::onActivate() {
  stop();  // a writer of an earlier activation
  {
    std::lock_guard lock(mutex_);
    pending_positions_.clear();
    pending_messages_.clear();
    malformed_written_ = malformed_;
    positions_received_ = 0;
    write_failing_ = false;
    write_error_.reset();
    running_ = recording_ = true;
  }
  writer_ = std::thread([this] { writerLoop(); });
  messages_sub_ = channel_->subscribe(kMessagesTopic, kQueued,
                                      [this](const v1::SubscribeResponse& s) { onMessage(s); });
  positions_sub_ = channel_->subscribe(kPositionsTopic, kQueued,
                                       [this](const v1::SubscribeResponse& s) { onPosition(s); });
  activated_at_ = last_position_at_ = now();
  positions_seen_ = 0;
  disconnected_since_.reset();
  failing_since_.reset();
  active_ = true;
  return absl::OkStatus();
}

void PayAttentionToRobotMessagesBehavior::stop() {
  {
    std::lock_guard lock(mutex_);
    running_ = recording_ = false;
    wake_.notify_all();
  }
  // Joins the readers and the writer; never under mutex_.
  messages_sub_.reset();
  positions_sub_.reset();
  if (writer_.joinable()) writer_.join();
}

void PayAttentionToRobotMessagesBehavior::onDeactivate() {
  active_ = false;
  stop();
}

void PayAttentionToRobotMessagesBehavior::onPause() {
  std::lock_guard lock(mutex_);
  recording_ = false;
}

void PayAttentionToRobotMessagesBehavior::onResume() {
  std::lock_guard lock(mutex_);
  recording_ = true;
}

Situation PayAttentionToRobotMessagesBehavior::checkSituation() {
  if (!channel_) {
    return Situation::infeasible(
        "no data channel configured: start the behavior system with --channel HOST:PORT");
  }
  if (!beliefs_) {
    return Situation::infeasible(
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
  uint64_t received = 0;
  std::optional<std::string> write_error;
  {
    std::lock_guard lock(mutex_);
    received = positions_received_;
    if (write_failing_) write_error = write_error_.value_or("unknown error");
  }
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
