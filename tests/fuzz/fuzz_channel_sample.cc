// Fuzzes the data channel's samples (services/channel/include/behaviorlib/
// channel/topic.h) on both sides of the broker:
//
//   mode 0  one published sample: a topic (a real one or any text) checked
//           by validateTopicName, and an Any whose type_url is one of the
//           sample types published on the channel (or any text) and whose
//           value is the rest of the input, checked by checkSample as the
//           broker checks every sample it takes;
//   mode 1  a PublishRequest off the wire (binary), checked as the broker
//           does: each of its samples and those in `more`;
//   mode 2  a SubscribeResponse off the wire (binary) as a subscriber gets
//           it, unpacked into each sample type the way
//           ChannelClient::subscribeTyped does (sample().UnpackTo(&typed)).
//
// Input: byte 0 picks the mode; mode 0 reads its choices with
// FuzzedDataProvider.
//
// Besides sanitizer findings the target aborts when checkSample fails
// without INVALID_ARGUMENT and a reason, or accepts a sample that does not
// parse as its type or that a subscriber of its type cannot unpack.

#include <fuzzer/FuzzedDataProvider.h>
#include <google/protobuf/any.pb.h>
#include <google/protobuf/descriptor.h>
#include <google/protobuf/message.h>
#include <google/protobuf/struct.pb.h>

#include <cstdint>
#include <memory>
#include <string>

#include "absl/strings/string_view.h"
#include "behaviorlib/channel/topic.h"
#include "behaviorlib/v1/channel.pb.h"
#include "behaviorlib/v1/motion.pb.h"
#include "behaviorlib/v1/platform.pb.h"
#include "behaviorlib/v1/simulator.pb.h"
#include "behaviorlib/v1/types.pb.h"
#include "fuzz_support.h"

namespace {

namespace pb = google::protobuf;
namespace v1 = behaviorlib::v1;
namespace channel = behaviorlib::channel;
using behaviorlib::fuzz::broken;

// The sample types published and subscribed on the channel (simulator,
// behaviors, swarm, operator).
const pb::Message* const kSampleTypes[] = {
    &v1::Clock::default_instance(),
    &v1::PoseStamped::default_instance(),
    &v1::TwistStamped::default_instance(),
    &v1::Odometry::default_instance(),
    &v1::Imu::default_instance(),
    &v1::PositionFix::default_instance(),
    &v1::Altitude::default_instance(),
    &v1::BatteryState::default_instance(),
    &v1::LaserScan::default_instance(),
    &v1::PointCloud::default_instance(),
    &v1::Image::default_instance(),
    &v1::CameraInfo::default_instance(),
    &v1::Path::default_instance(),
    &v1::MarkerDetections::default_instance(),
    &v1::Text::default_instance(),
    &v1::SwarmMessage::default_instance(),
    &v1::SwarmPosition::default_instance(),
    &v1::FlightStatus::default_instance(),
    &v1::VehicleState::default_instance(),
    &v1::MotionReference::default_instance(),
    &v1::MotionControlStatus::default_instance(),
};

const char* const kTopics[] = {
    "clock",
    "robots/drone1/ground_truth/pose",
    "robots/drone1/self_localization/pose",
    "robots/drone1/lidar/scan",
    "robots/drone1/camera/image",
    "robots/drone1/imu",
    "robots/drone1/motion_reference",
    "robots/swarm/messages",
};

// The broker's check of one published sample.
void check(const std::string& topic, const pb::Any& sample) {
  (void)channel::validateTopicName(topic);
  (void)channel::typeNameOfUrl(sample.type_url());
  const pb::Descriptor* type = nullptr;
  absl::string_view reason;
  const absl::Status s = channel::checkSample(topic, sample, &type, &reason);
  if (!s.ok()) {
    if (s.code() != absl::StatusCode::kInvalidArgument || reason.empty()) {
      broken("checkSample failed without INVALID_ARGUMENT and a reason", s.ToString());
    }
    return;
  }
  if (type == nullptr) broken("checkSample accepted a sample without its type", sample.type_url());
  // What the broker accepted parses as its type.
  std::unique_ptr<pb::Message> typed(
      pb::MessageFactory::generated_factory()->GetPrototype(type)->New());
  if (!typed->ParseFromString(sample.value())) {
    broken("an accepted sample does not parse", sample.type_url());
  }
  // ... and a subscriber of that type gets it (ChannelClient::subscribeTyped
  // drops what UnpackTo refuses, without a trace).
  if (!sample.UnpackTo(typed.get())) {
    broken("checkSample accepted a sample its type's subscribers cannot unpack", sample.type_url());
  }
}

// A subscriber of each sample type (ChannelClient::subscribeTyped).
void unpack(const pb::Any& sample) {
  for (const pb::Message* prototype : kSampleTypes) {
    std::unique_ptr<pb::Message> typed(prototype->New());
    if (sample.UnpackTo(typed.get())) (void)typed->ByteSizeLong();
  }
}

}  // namespace

BEHAVIORLIB_FUZZ_SILENCE_PROTOBUF_LOGS()

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  if (size < 1) return 0;
  const uint8_t mode = data[0] % 3;
  const uint8_t* rest = data + 1;
  const size_t rest_size = size - 1;
  switch (mode) {
    case 0: {
      FuzzedDataProvider provider(rest, rest_size);
      const std::string topic = provider.ConsumeBool()
                                    ? std::string(provider.PickValueInArray(kTopics))
                                    : provider.ConsumeRandomLengthString(300);
      pb::Any sample;
      switch (provider.ConsumeIntegralInRange(0, 2)) {
        case 0:
          sample.set_type_url("type.googleapis.com/" +
                              provider.PickValueInArray(kSampleTypes)->GetTypeName());
          break;
        case 1:
          sample.set_type_url(provider.PickValueInArray(kSampleTypes)->GetTypeName());
          break;
        default:
          sample.set_type_url(provider.ConsumeRandomLengthString(200));
          break;
      }
      sample.set_value(provider.ConsumeRemainingBytesAsString());
      check(topic, sample);
      unpack(sample);
      break;
    }
    case 1: {
      v1::PublishRequest request;
      if (!request.ParseFromArray(rest, static_cast<int>(rest_size))) return 0;
      if (!request.topic().empty() || request.has_sample())
        check(request.topic(), request.sample());
      for (const auto& more : request.more()) check(more.topic(), more.sample());
      break;
    }
    default: {
      v1::SubscribeResponse response;
      if (!response.ParseFromArray(rest, static_cast<int>(rest_size))) return 0;
      (void)channel::validateTopicName(response.topic());
      unpack(response.sample());
      break;
    }
  }
  return 0;
}
