// Fuzzes behavior parameters as people and files write them, through the
// real entry points that make a google.protobuf.Struct of them:
//
//   source 0  JSON text -> Struct (JsonStringToMessage): behaviorctl
//             activate/modify, the JSON form of the gRPC API;
//   source 1  YAML text -> Struct as the mission and catalog readers do
//             (server_kit::loadYaml, then yaml::Reader::value under
//             server_kit::guardYamlParse): a step's `parameters`, a behavior's
//             `defaults`;
//   source 2  JSON text -> Value (JsonStringToMessage), written to belief
//             memory (BeliefStore::write: behaviorctl belief set), then bound
//             into each parameter by "${belief.<key>}" (BeliefStore::resolve,
//             as the mission runner does);
//
// then, as the behavior system does: params::fromStruct into a parameter
// message, applyDefaultsAndValidate, mergeUpdate (Modify) and toStruct.
//
// Input: byte 0 picks the message (low nibble) and the source (high
// nibble); the rest is the text.
//
// Besides sanitizer findings the target aborts when the documented contract
// breaks (behaviorlib::fuzz::exerciseParameters in fuzz_support.h, shared
// with fuzz_parameters_struct.cc).

#include <google/protobuf/descriptor.h>
#include <google/protobuf/message.h>
#include <google/protobuf/struct.pb.h>
#include <google/protobuf/util/json_util.h>
#include <yaml-cpp/yaml.h>

#include <cstdint>
#include <string>

#include "behaviorlib/server_kit/yaml_guard.h"
#include "coordinator/belief/belief_store.h"
#include "coordinator/common/yaml_support.h"
#include "fuzz_support.h"

namespace {

namespace pb = google::protobuf;
namespace fuzz = behaviorlib::fuzz;

// A mission step's `parameters` (coordinator/mission/mission_file.cc).
bool fromYaml(const std::string& text, pb::Struct* out) {
  YAML::Node root;
  if (!behaviorlib::coordinator::yaml::load(text, "fuzz.yaml", &root).ok()) return false;
  const behaviorlib::coordinator::yaml::Reader reader("fuzz.yaml");
  const absl::Status guarded = behaviorlib::server_kit::guardYamlParse("fuzz.yaml", [&] {
    if (!root.IsMap()) return reader.error(root, "parameters: expected a mapping");
    pb::Value value;
    if (auto s = reader.value(root, "parameters", &value); !s.ok()) return s;
    *out = value.struct_value();
    return absl::OkStatus();
  });
  return guarded.ok();
}

// A belief written as JSON, bound into every parameter in turn.
void fromBelief(const std::string& text, const pb::Message& prototype) {
  pb::Value value;
  if (!pb::util::JsonStringToMessage(text, &value).ok()) return;
  behaviorlib::coordinator::BeliefStore beliefs;
  if (!beliefs.write("fuzz/value", value, "operator").ok()) return;
  const pb::Descriptor& d = *prototype.GetDescriptor();
  for (int i = 0; i < d.field_count(); ++i) {
    pb::Struct bound;
    (*bound.mutable_fields())[d.field(i)->name()].set_string_value("${belief.fuzz/value}");
    const absl::StatusOr<pb::Struct> resolved = beliefs.resolve(bound);
    if (!resolved.ok()) {
      fuzz::broken("a bound belief that is in memory does not resolve", prototype);
    }
    fuzz::exerciseParameters(*resolved, prototype);
  }
  // Inside a longer string, the value's text replaces the binding.
  pb::Struct embedded;
  (*embedded.mutable_fields())["robot_ids"].mutable_list_value()->add_values()->set_string_value(
      "drone-${belief.fuzz/value}-${belief.fuzz/value}");
  const absl::StatusOr<pb::Struct> resolved = beliefs.resolve(embedded);
  if (resolved.ok()) fuzz::exerciseParameters(*resolved, prototype);
}

}  // namespace

BEHAVIORLIB_FUZZ_SILENCE_PROTOBUF_LOGS()

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  if (size < 1) return 0;
  const auto types = fuzz::parameterTypes();
  const pb::Message& prototype = *types[(data[0] & 0x0f) % types.size()];
  const int source = (data[0] >> 4) % 3;
  const std::string text(reinterpret_cast<const char*>(data + 1), size - 1);
  pb::Struct in;
  switch (source) {
    case 0:
      if (!pb::util::JsonStringToMessage(text, &in).ok()) return 0;
      fuzz::exerciseParameters(in, prototype);
      break;
    case 1:
      if (!fromYaml(text, &in)) return 0;
      fuzz::exerciseParameters(in, prototype);
      break;
    default:
      fromBelief(text, prototype);
      break;
  }
  return 0;
}
