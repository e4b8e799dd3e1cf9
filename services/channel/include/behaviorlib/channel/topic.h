#pragma once

// Rules shared by the broker and its clients: which topic names are valid and
// which published samples are acceptable.
//
//   absl::Status s = behaviorlib::channel::validateTopicName("robots/drone1/pose");
//   if (!s.ok()) return s;  // INVALID_ARGUMENT naming the topic and the rule
//
//   const google::protobuf::Descriptor* type = nullptr;
//   absl::string_view reason;
//   s = behaviorlib::channel::checkSample("clock", any, &type, &reason);

#include <cstddef>
#include <cstdint>
#include <string>

#include "absl/status/status.h"
#include "absl/strings/string_view.h"

namespace google::protobuf {
class Any;
class Descriptor;
}  // namespace google::protobuf

namespace behaviorlib::channel {

/// The topic carrying simulated time (behaviorlib.v1.Clock samples).
inline constexpr absl::string_view kClockTopic = "clock";

/// Server-initial-metadata key the broker sends on a Subscribe stream once
/// the subscription is registered, so that clients know that every sample
/// published from then on reaches them. Its value is the topic's topic_seq
/// at registration: samples up to it were published before.
inline constexpr char kSubscribedMetadataKey[] = "behaviorlib-subscribed";

/// Server-initial-metadata keys of a subscription served through a
/// shared-memory ring (SubscribeRequest.shared_memory): the ring's name
/// (ShmRing::open) and the first sample number to read from it.
inline constexpr char kShmRingMetadataKey[] = "behaviorlib-shm";
inline constexpr char kShmFirstMetadataKey[] = "behaviorlib-shm-first";

/// Client-metadata key of a Publish stream whose publisher gates the topics
/// under the value (a prefix) by interest (DataChannel.WatchInterest): it
/// publishes them only while wanted, so the broker keeps no sample of one
/// nobody wants (it would grow stale) and a GetLatest of it waits for the
/// next.
inline constexpr char kGatedPrefixMetadataKey[] = "behaviorlib-gated-prefix";

/// Buffer limits of DELIVERY_MODE_QUEUE subscriptions (queue_size 0 means
/// the default).
inline constexpr uint32_t kDefaultQueueSize = 100;
inline constexpr uint32_t kMaxQueueSize = 10000;

/// Longest accepted topic name. Names become metric labels, so they are
/// bounded.
inline constexpr std::size_t kMaxTopicNameLength = 256;

/// OK when `topic` is "clock" or "robots/{robot_id}/{name...}" (at least one
/// name segment after the robot id; every segment non-empty and made of
/// letters, digits, '_', '-' and '.'), otherwise INVALID_ARGUMENT naming the
/// topic and the rule it breaks.
absl::Status validateTopicName(absl::string_view topic);

/// Topics every robot of a fleet publishes on (the swarm's positions and
/// messages, whose samples name their sender). A publisher bound to one robot
/// (server_kit::RobotScope) publishes under robots/<its robot>/ and here.
inline constexpr absl::string_view kSharedRobotsPrefix = "robots/swarm/";

/// Reasons a sample is rejected, used as the `reason` label of
/// behaviorlib_channel_rejected_samples_total.
namespace reject_reason {
inline constexpr absl::string_view kInvalidTopic = "invalid_topic";
inline constexpr absl::string_view kMissingSample = "missing_sample";
inline constexpr absl::string_view kUnknownType = "unknown_type";
inline constexpr absl::string_view kMalformedSample = "malformed_sample";
inline constexpr absl::string_view kTypeMismatch = "type_mismatch";
inline constexpr absl::string_view kTooManyTopics = "too_many_topics";
/// The publisher's identity is bound to another robot (RobotScope).
inline constexpr absl::string_view kNotPermitted = "not_permitted";
}  // namespace reject_reason

/// Checks a sample published on `topic` (only used in messages): its type_url
/// must name a message type compiled into this program (looked up in the
/// generated descriptor pool after the last '/') and its value must parse as
/// that type. On success sets `*type`; on failure returns INVALID_ARGUMENT
/// and sets `*reason` to one of reject_reason.
absl::Status checkSample(absl::string_view topic, const google::protobuf::Any& sample,
                         const google::protobuf::Descriptor** type, absl::string_view* reason);

/// The full message type name in an Any type_url ("type.googleapis.com/a.B"
/// -> "a.B").
absl::string_view typeNameOfUrl(absl::string_view type_url);

}  // namespace behaviorlib::channel
