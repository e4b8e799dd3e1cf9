#include "behaviorlib/swarm_interaction/swarm_topics.h"

#include <google/protobuf/struct.pb.h>
#include <google/protobuf/util/json_util.h>
#include <google/protobuf/util/time_util.h>

#include <algorithm>
#include <cmath>

namespace behaviorlib::swarm {

bool validRobotId(const std::string& id) {
  return !id.empty() && std::all_of(id.begin(), id.end(), [](char c) {
    return (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z') || (c >= '0' && c <= '9') || c == '_' ||
           c == '-' || c == '.';
  });
}

bool addressedTo(const google::protobuf::RepeatedPtrField<std::string>& recipients,
                 const std::string& robot_id) {
  return recipients.empty() ||
         std::find(recipients.begin(), recipients.end(), robot_id) != recipients.end();
}

bool isJson(const std::string& json) {
  google::protobuf::Value value;
  return google::protobuf::util::JsonStringToMessage(json, &value).ok();
}

std::optional<std::string> malformedMessage(const v1::SwarmMessage& message) {
  const std::string& sender = message.header().robot_id();
  if (!validRobotId(sender)) return "a message without a valid sender (header.robot_id)";
  if (message.text().empty() && message.payload_json().empty()) {
    return "a message from " + sender + " with neither text nor payload";
  }
  if (!message.payload_json().empty() && !isJson(message.payload_json())) {
    return "a message from " + sender + " whose payload_json is not JSON";
  }
  return std::nullopt;
}

std::optional<std::string> malformedPosition(const v1::SwarmPosition& position) {
  const std::string& sender = position.header().robot_id();
  if (!validRobotId(sender)) return "a position without a valid sender (header.robot_id)";
  const auto& p = position.pose().position_m();
  if (!position.pose().has_position_m() || !std::isfinite(p.x()) || !std::isfinite(p.y()) ||
      !std::isfinite(p.z())) {
    return "a position from " + sender + " without a finite position_m";
  }
  return std::nullopt;
}

google::protobuf::Timestamp toTimestamp(TimePoint t) {
  return google::protobuf::util::TimeUtil::NanosecondsToTimestamp(t.time_since_epoch().count());
}

}  // namespace behaviorlib::swarm
