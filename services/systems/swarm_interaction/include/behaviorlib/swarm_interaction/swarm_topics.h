#pragma once

// What the swarm_interaction behaviors share: the two data-channel topics
// every robot of the swarm publishes to and reads from, and the checks of
// what arrives on them.
//
//   robots/swarm/messages   SwarmMessage   INFORM_ROBOTS -> PAY_ATTENTION_TO_ROBOT_MESSAGES
//   robots/swarm/positions  SwarmPosition  INFORM_POSITION_TO_ROBOTS -> (the same)
//
// The channel's topics are robots/{robot_id}/{name}; the robot id "swarm"
// names the topics of the whole swarm (no vehicle may be called "swarm").

#include <google/protobuf/repeated_ptr_field.h>

#include <optional>
#include <string>

#include "behaviorlib/clock.h"
#include "behaviorlib/v1/types.pb.h"

namespace behaviorlib::swarm {

inline constexpr char kMessagesTopic[] = "robots/swarm/messages";
inline constexpr char kPositionsTopic[] = "robots/swarm/positions";

/// True when `id` can be a segment of a belief key and a topic: non-empty,
/// letters, digits, '_', '-', '.'.
bool validRobotId(const std::string& id);

/// Whether a sample with these recipients is for `robot_id` (empty: for all).
bool addressedTo(const google::protobuf::RepeatedPtrField<std::string>& recipients,
                 const std::string& robot_id);

/// Why a received message is malformed (it is then counted and skipped), or
/// nullopt when it is well formed.
std::optional<std::string> malformedMessage(const v1::SwarmMessage& message);
/// The same for a received position.
std::optional<std::string> malformedPosition(const v1::SwarmPosition& position);

/// Whether `json` is JSON text (one value).
bool isJson(const std::string& json);

/// A time point of the behavior clock as a proto Timestamp.
google::protobuf::Timestamp toTimestamp(TimePoint t);

}  // namespace behaviorlib::swarm
