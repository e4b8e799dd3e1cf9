// The checks of behavior parameters (fuzz_support.h) that
// fuzz_parameters_struct and fuzz_parameters_json run on what they convert.

#include <google/protobuf/message.h>
#include <google/protobuf/struct.pb.h>
#include <google/protobuf/util/message_differencer.h>

#include <cstdio>
#include <cstdlib>
#include <memory>
#include <span>

#include "behaviorlib/parameters.h"
#include "behaviorlib/v1/behaviors/attention_to_visual_markers.pb.h"
#include "behaviorlib/v1/behaviors/basic_quadrotor_behaviors.pb.h"
#include "behaviorlib/v1/behaviors/navigation_with_lidar.pb.h"
#include "behaviorlib/v1/behaviors/quadrotor_motion_with_pid_control.pb.h"
#include "behaviorlib/v1/behaviors/swarm_interaction.pb.h"
#include "fuzz_support.h"
#include "test_parameters.pb.h"

namespace behaviorlib::fuzz {
namespace {

namespace pb = google::protobuf;

// parameterTypes(), with what each one brings.
const pb::Message* const kTypes[] = {
    // repeated nested messages (path_m: [Vector3]), optional doubles
    &v1::FollowPathParameters::default_instance(),
    // map<string, double>
    &v1::PayAttentionToQrCodesParameters::default_instance(),
    // singular nested messages, a required one, uint32
    &v1::GeneratePathWithOccupancyGridParameters::default_instance(),
    // repeated strings
    &v1::InformRobotsParameters::default_instance(),
    // uint32 with a range, bool
    &v1::EstimatePositionWithSensorParameters::default_instance(),
    &v1::TakeOffParameters::default_instance(),
    // enums, 64-bit and unsigned integers, float, bytes, oneof, maps with
    // integer keys and message values, a recursive type
    &test::AllKinds::default_instance(),
    &test::Choice::default_instance(),
    &test::Tree::default_instance(),
    &test::Strict::default_instance(),
};

bool sameStruct(const pb::Struct& a, const pb::Struct& b) {
  return pb::util::MessageDifferencer::Equals(a, b);
}

// toStruct's output converts back to a message with the same Struct.
void roundTrip(const pb::Message& m) {
  const pb::Struct out = params::toStruct(m);
  std::unique_ptr<pb::Message> back(m.New());
  if (!params::fromStruct(out, back.get()).ok()) broken("fromStruct refuses toStruct's output", m);
  if (!sameStruct(params::toStruct(*back), out)) broken("toStruct/fromStruct round trip", m);
}

}  // namespace

std::span<const pb::Message* const> parameterTypes() { return kTypes; }

void broken(const char* what, const pb::Message& m) {
  std::fprintf(stderr, "%s (%s): %s\n", what, m.GetDescriptor()->full_name().c_str(),
               m.ShortDebugString().c_str());
  std::abort();
}

void exerciseParameters(const pb::Struct& in, const pb::Message& prototype) {
  std::unique_ptr<pb::Message> m(prototype.New());
  const absl::Status parsed = params::fromStruct(in, m.get());
  if (!parsed.ok()) {
    if (parsed.code() != absl::StatusCode::kInvalidArgument) {
      std::fprintf(stderr, "fromStruct: %s\n", parsed.ToString().c_str());
      broken("fromStruct failed with a code other than INVALID_ARGUMENT", *m);
    }
    return;
  }
  roundTrip(*m);
  // Modify: the update as converted, before defaults.
  std::unique_ptr<pb::Message> update(m->New());
  update->CopyFrom(*m);
  if (!params::applyDefaultsAndValidate(m.get()).ok()) return;
  roundTrip(*m);
  if (!params::applyDefaultsAndValidate(m.get()).ok()) broken("validation not idempotent", *m);
  // Modify (BehaviorExecutionManager): the update merged into the current
  // parameters, then defaults and rules again. Merging an update into the
  // parameters it made changes nothing.
  std::unique_ptr<pb::Message> merged(m->New());
  merged->CopyFrom(*m);
  params::mergeUpdate(*update, merged.get());
  if (!params::applyDefaultsAndValidate(merged.get()).ok()) broken("merged message invalid", *m);
  if (!sameStruct(params::toStruct(*merged), params::toStruct(*m))) {
    broken("merging an update into the message it made changed it", *m);
  }
}

}  // namespace behaviorlib::fuzz
