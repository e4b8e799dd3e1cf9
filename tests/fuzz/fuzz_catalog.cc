// Fuzzes the behavior catalog (coordinator/catalog/catalog.h):
// Catalog::parse on the raw bytes, then what the coordinator does with a
// catalog it accepted: checkRegistration against the registrations of the
// real behaviors, an activation plan (makePlan) for every behavior it lists,
// applied (applyPlan) through fake actions that convert each activation's
// parameters as the hosting behavior system does (params::fromStruct,
// applyDefaultsAndValidate); the target's situation check fails every other
// plan, so the rollback runs too.

#include <google/protobuf/descriptor.h>
#include <google/protobuf/message.h>
#include <google/protobuf/struct.pb.h>

#include <chrono>
#include <cstdint>
#include <memory>
#include <set>
#include <string>

#include "behaviorlib/parameters.h"
#include "behaviorlib/v1/behavior.pb.h"
#include "coordinator/catalog/catalog.h"
#include "coordinator/catalog/planner.h"
#include "fuzz_support.h"

namespace {

namespace pb = google::protobuf;
namespace fuzz = behaviorlib::fuzz;
using behaviorlib::coordinator::Catalog;

// Plan steps as a behavior system would take them.
class FakeActions final : public behaviorlib::coordinator::PlanActions {
 public:
  explicit FakeActions(std::string refuse) : refuse_(std::move(refuse)) {}

  absl::Status checkSituation(const std::string& behavior) override {
    if (behavior == refuse_) return absl::FailedPreconditionError("refused by the fuzzer");
    return absl::OkStatus();
  }
  absl::StatusOr<std::string> activate(const std::string& behavior,
                                       const pb::Struct& parameters) override {
    if (const pb::Descriptor* type = fuzz::parameterTypeOf(behavior); type != nullptr) {
      std::unique_ptr<pb::Message> message(
          pb::MessageFactory::generated_factory()->GetPrototype(type)->New());
      if (behaviorlib::params::fromStruct(parameters, message.get()).ok()) {
        (void)behaviorlib::params::applyDefaultsAndValidate(message.get());
      }
    }
    active_.insert(behavior);
    return behavior + "-1";
  }
  absl::Status deactivate(const std::string& behavior) override {
    if (active_.erase(behavior) == 0) return absl::FailedPreconditionError("not active");
    return absl::OkStatus();
  }

 private:
  std::string refuse_;
  std::set<std::string> active_;
};

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::string text(reinterpret_cast<const char*>(data), size);
  const absl::StatusOr<Catalog> catalog = Catalog::parse(text, fuzz::kFileName);
  if (!catalog.ok()) {
    fuzz::checkParseError(catalog.status(), "Catalog::parse");
    return 0;
  }
  for (const auto& [name, description] : fuzz::behaviorDescriptions()) {
    (void)catalog->checkRegistration(description, "fuzz_system");
  }
  for (const auto& [name, capability] : catalog->capabilities()) {
    (void)catalog->capability(name);
  }
  // The robot hosts every behavior the catalog or the registrations name.
  behaviorlib::coordinator::PlanRequest request;
  request.robot_id = "drone1";
  for (const auto& [name, behavior] : catalog->behaviors()) request.available.insert(name);
  for (const auto& [name, description] : fuzz::behaviorDescriptions()) {
    request.available.insert(name);
  }
  behaviorlib::coordinator::ApplyOptions apply;
  apply.settle_timeout = std::chrono::milliseconds(0);
  apply.lag_timeout = std::chrono::milliseconds(0);
  apply.sleep = [](std::chrono::milliseconds) {};
  int planned = 0;
  for (const auto& [name, behavior] : catalog->behaviors()) {
    if (++planned > 32) break;
    (void)catalog->find(name);
    request.target = name;
    const absl::StatusOr<behaviorlib::coordinator::Plan> plan =
        behaviorlib::coordinator::makePlan(*catalog, request);
    if (!plan.ok()) continue;
    FakeActions actions(planned % 2 == 0 ? name : "");
    (void)behaviorlib::coordinator::applyPlan(*plan, actions, apply);
    // Next plan: with what this one activated still active (conflicts).
    for (const auto& step : plan->steps) {
      if (step.kind == behaviorlib::coordinator::StepKind::kActivate) {
        request.active.insert(step.behavior);
      } else if (step.kind == behaviorlib::coordinator::StepKind::kDeactivate) {
        request.active.erase(step.behavior);
      }
    }
  }
  return 0;
}
