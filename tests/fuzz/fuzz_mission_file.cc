// Fuzzes mission files (coordinator/mission/mission_file.h): parseMission on
// the raw bytes, then what the coordinator does with a parsed mission before
// and while it flies: checkMission against the registrations of the real
// behaviors (their parameter schemas, as the behavior systems describe
// them), belief bindings resolved from belief memory, and each step's
// parameters converted and validated as the behavior system hosting it does
// (params::fromStruct, params::applyDefaultsAndValidate).

#include <google/protobuf/descriptor.h>
#include <google/protobuf/message.h>
#include <google/protobuf/struct.pb.h>

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "behaviorlib/parameters.h"
#include "behaviorlib/v1/behavior.pb.h"
#include "coordinator/belief/belief_store.h"
#include "coordinator/mission/mission_file.h"
#include "fuzz_support.h"

namespace {

namespace pb = google::protobuf;
namespace fuzz = behaviorlib::fuzz;
using behaviorlib::coordinator::BeliefStore;
using behaviorlib::coordinator::MissionAction;
using behaviorlib::coordinator::MissionSpec;
using behaviorlib::coordinator::MissionStep;
namespace v1 = behaviorlib::v1;

// Belief memory with the keys the shipped missions bind.
const BeliefStore& beliefs() {
  static const BeliefStore* const store = [] {
    auto* s = new BeliefStore;
    auto restore = [&](const std::string& key, const pb::Value& value, uint64_t version) {
      v1::Belief b;
      b.set_key(key);
      *b.mutable_value() = value;
      b.set_version(version);
      s->restore(b);
    };
    pb::Value path;
    for (int i = 0; i < 3; ++i) {
      pb::Struct point;
      (*point.mutable_fields())["x"].set_number_value(i);
      (*point.mutable_fields())["y"].set_number_value(2.0 * i);
      (*point.mutable_fields())["z"].set_number_value(1.5);
      *path.mutable_list_value()->add_values()->mutable_struct_value() = point;
    }
    restore("drone1/path", path, 1);
    pb::Value dir;
    dir.set_string_value("/tmp/out");
    restore("drone1/output_dir", dir, 2);
    pb::Value yes;
    yes.set_bool_value(true);
    restore("operator_answer", yes, 3);
    pb::Value number;
    number.set_number_value(2.5);
    restore("drone1/altitude", number, 4);
    v1::Belief deleted;
    deleted.set_key("drone1/deleted");
    deleted.set_deleted(true);
    deleted.set_version(5);
    s->restore(deleted);
    return s;
  }();
  return *store;
}

// What the behavior system does with an activation's parameters.
void activate(const MissionStep& step, const pb::Struct& parameters) {
  const pb::Descriptor* type = fuzz::parameterTypeOf(step.behavior);
  if (type == nullptr) return;
  std::unique_ptr<pb::Message> message(
      pb::MessageFactory::generated_factory()->GetPrototype(type)->New());
  if (!behaviorlib::params::fromStruct(parameters, message.get()).ok()) return;
  (void)behaviorlib::params::applyDefaultsAndValidate(message.get());
  (void)behaviorlib::params::toStruct(*message).ByteSizeLong();
}

void runSteps(const std::vector<MissionStep>& steps, int depth);

void runAction(const MissionAction& action, int depth) {
  for (const MissionAction* a = &action; a != nullptr; a = a->then.get()) {
    runSteps(a->fallback, depth + 1);
  }
}

// What the mission runner does with each step: its condition's key, its
// parameters and its `remember` resolved from belief memory.
void runSteps(const std::vector<MissionStep>& steps, int depth) {
  if (depth > 64) return;  // the YAML depth limit bounds it already
  for (const MissionStep& step : steps) {
    if (step.condition) (void)beliefs().get(step.condition->key);
    auto resolved = beliefs().resolve(step.parameters);
    activate(step, resolved.ok() ? *resolved : step.parameters);
    (void)beliefs().resolve(step.remember);
    for (const auto& [cause, action] : step.on) runAction(action, depth);
    // A call's or a loop's steps, and a parallel step's branches.
    runSteps(step.body, depth + 1);
    if (step.parallel) {
      for (const auto& branch : step.parallel->branches) runSteps(branch.steps, depth + 1);
    }
  }
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::string text(reinterpret_cast<const char*>(data), size);
  const absl::StatusOr<MissionSpec> mission =
      behaviorlib::coordinator::parseMission(text, fuzz::kFileName);
  if (!mission.ok()) {
    fuzz::checkParseError(mission.status(), "parseMission");
    return 0;
  }
  const auto& descriptions = fuzz::behaviorDescriptions();
  (void)behaviorlib::coordinator::checkMission(
      *mission,
      [&](const std::string& /*robot*/,
          const std::string& behavior) -> const v1::BehaviorDescription* {
        const auto it = descriptions.find(behavior);
        return it == descriptions.end() ? nullptr : &it->second;
      });
  runSteps(mission->recurrent, 0);
  runSteps(mission->steps, 0);
  runSteps(mission->safety, 0);
  if (mission->geofence) (void)mission->geofence->contains(0.0, 0.0, 1.0);
  return 0;
}
