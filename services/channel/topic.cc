#include "behaviorlib/channel/topic.h"

#include <google/protobuf/any.pb.h>
#include <google/protobuf/descriptor.h>
#include <google/protobuf/message.h>

#include <memory>
#include <vector>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "behaviorlib/v1/coordinator.pb.h"
#include "behaviorlib/v1/mission.pb.h"
#include "behaviorlib/v1/motion.pb.h"
#include "behaviorlib/v1/platform.pb.h"
#include "behaviorlib/v1/types.pb.h"

namespace behaviorlib::channel {
namespace {

constexpr absl::string_view kRule =
    "topics are \"clock\" or \"robots/{robot_id}/{name}\" where every '/'-separated segment is "
    "non-empty and made of letters, digits, '_', '-' and '.'";

bool segmentCharOk(char c) {
  return (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z') || (c >= '0' && c <= '9') || c == '_' ||
         c == '-' || c == '.';
}

absl::Status badTopic(absl::string_view topic, absl::string_view problem) {
  return absl::InvalidArgumentError(
      absl::StrCat("invalid topic '", topic, "': ", problem, "; ", kRule));
}

// Samples of the standard data types (types.proto) and of the platform's
// status (platform.proto, published by the simulator) must be accepted even
// by a binary that never names one of them: a static library's object file,
// and so its descriptor registration, is only linked when something
// references it.
[[maybe_unused]] const google::protobuf::Descriptor* const kLinkStandardTypes =
    v1::Clock::descriptor();
[[maybe_unused]] const google::protobuf::Descriptor* const kLinkPlatformTypes =
    v1::FlightStatus::descriptor();
// Motion references and motion-controller status (motion.proto), exchanged
// by the motion behaviors.
[[maybe_unused]] const google::protobuf::Descriptor* const kLinkMotionTypes =
    v1::MotionReference::descriptor();

}  // namespace

absl::Status validateTopicName(absl::string_view topic) {
  if (topic == kClockTopic) return absl::OkStatus();
  if (topic.empty()) return badTopic(topic, "the name is empty");
  if (topic.size() > kMaxTopicNameLength) {
    return badTopic(topic.substr(0, 64),
                    absl::StrCat("the name is longer than ", kMaxTopicNameLength, " characters"));
  }
  std::vector<absl::string_view> segments = absl::StrSplit(topic, '/');
  if (segments.front() != "robots") return badTopic(topic, "it must start with \"robots/\"");
  if (segments.size() < 3) {
    return badTopic(topic, "it needs a robot id and a name after \"robots/\"");
  }
  for (absl::string_view segment : segments) {
    if (segment.empty()) return badTopic(topic, "it has an empty segment");
    for (char c : segment) {
      if (!segmentCharOk(c)) {
        return badTopic(
            topic, absl::StrCat("segment '", segment, "' contains a character (0x",
                                absl::Hex(static_cast<unsigned char>(c)), ") that is not allowed"));
      }
    }
  }
  return absl::OkStatus();
}

absl::string_view typeNameOfUrl(absl::string_view type_url) {
  auto slash = type_url.rfind('/');
  return slash == absl::string_view::npos ? type_url : type_url.substr(slash + 1);
}

absl::Status checkSample(absl::string_view topic, const google::protobuf::Any& sample,
                         const google::protobuf::Descriptor** type, absl::string_view* reason) {
  if (sample.type_url().empty()) {
    *reason = reject_reason::kMissingSample;
    return absl::InvalidArgumentError(
        absl::StrCat("sample on topic '", topic, "' is missing (empty Any type_url)"));
  }
  // Any::UnpackTo needs "<prefix>/<full name>": a sample without the '/'
  // would be accepted here and then dropped by every typed subscriber.
  if (sample.type_url().find('/') == std::string::npos) {
    *reason = reject_reason::kUnknownType;
    return absl::InvalidArgumentError(
        absl::StrCat("sample on topic '", topic, "' has type_url '", sample.type_url(),
                     "' without a '/': expected \"<prefix>/<full message name>\" as "
                     "Any::PackFrom writes it (type.googleapis.com/behaviorlib.v1.Pose)"));
  }
  // A flight recording's replay publishes the coordinator's messages too
  // (robots/{id}/recording/..., decision 36): referenced here so that a
  // static link keeps their descriptors in the generated pool.
  static const google::protobuf::Descriptor* const kRecordingTypes[] = {
      v1::FleetEvent::descriptor(), v1::MissionStatus::descriptor(), v1::Belief::descriptor()};
  (void)kRecordingTypes;
  const absl::string_view type_name = typeNameOfUrl(sample.type_url());
  const google::protobuf::Descriptor* descriptor =
      google::protobuf::DescriptorPool::generated_pool()->FindMessageTypeByName(
          std::string(type_name));
  if (descriptor == nullptr) {
    *reason = reject_reason::kUnknownType;
    return absl::InvalidArgumentError(absl::StrCat(
        "sample on topic '", topic, "' has unknown type '", sample.type_url(),
        "'; samples must be messages known to the broker (e.g. behaviorlib.v1.* data types)"));
  }
  const google::protobuf::Message* prototype =
      google::protobuf::MessageFactory::generated_factory()->GetPrototype(descriptor);
  std::unique_ptr<google::protobuf::Message> parsed(prototype->New());
  if (!parsed->ParseFromString(sample.value())) {
    *reason = reject_reason::kMalformedSample;
    return absl::InvalidArgumentError(absl::StrCat("sample on topic '", topic,
                                                   "' is malformed: its bytes do not parse as ",
                                                   descriptor->full_name()));
  }
  *type = descriptor;
  return absl::OkStatus();
}

}  // namespace behaviorlib::channel
