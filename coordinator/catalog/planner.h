#pragma once

// Activation plans under the catalog's rules. To activate a behavior on a
// robot, the coordinator builds a plan from the catalog and the robot's
// active behaviors, then applies it in a fixed order, serialized per robot:
//
//   1. deactivate what conflicts: active behaviors that hold a resource the
//      planned behaviors hold (they finish INTERRUPTED), and active behaviors
//      that would lose a required capability;
//   2. for each missing requirement (its default provider, requirements
//      first) and finally the target: CheckSituation, then Activate. A
//      requirement the plan activates on its own gets the catalog's
//      `defaults` (nobody else gives it parameters); the target gets the
//      caller's parameters alone, and its unset fields take the proto's
//      defaults in the behavior system: one place (decision 45).
//
// If a step fails, everything the plan activated is deactivated again (in
// reverse order) and the error names the step. A dry run is makePlan()
// without applyPlan().
//
//   Plan plan = makePlan(catalog, {"robot": "drone1", ...}).value();
//   PlanResult done = applyPlan(plan, actions).value();

#include <google/protobuf/struct.pb.h>

#include <chrono>
#include <functional>
#include <set>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "behaviorlib/v1/coordinator.pb.h"
#include "coordinator/catalog/catalog.h"

namespace behaviorlib::coordinator {

enum class StepKind { kDeactivate, kCheckSituation, kActivate };

/// "deactivate", "check_situation", "activate".
const char* stepKindName(StepKind kind);

struct PlanStep {
  StepKind kind = StepKind::kActivate;
  std::string behavior;
  /// For kActivate: the caller's parameters for the target; the catalog's
  /// defaults for a requirement the plan activates.
  google::protobuf::Struct parameters;
  /// Why the step is there, for people: "the target", "provides
  /// self_localization required by FOLLOW_PATH", "holds motion_reference,
  /// which FOLLOW_PATH needs".
  std::string reason;
};

struct Plan {
  std::string robot_id;
  std::string target;
  std::vector<PlanStep> steps;
};

struct PlanRequest {
  std::string robot_id;
  std::string target;
  google::protobuf::Struct parameters;
  /// Behaviors active on the robot now.
  std::set<std::string> active;
  /// Behaviors some registered system of the robot hosts.
  std::set<std::string> available;
};

/// Builds the plan. NOT_FOUND when the target is not available on the
/// robot; FAILED_PRECONDITION when it is already active, or a requirement
/// has no default provider available; INVALID_ARGUMENT when the catalog makes
/// the target conflict with its own requirements. Messages name the robot,
/// the behaviors and the capability or resource involved.
absl::StatusOr<Plan> makePlan(const Catalog& catalog, const PlanRequest& request);

/// Appends the plan's steps as the API's ActivationPlanStep messages.
void planToProto(const Plan& plan, google::protobuf::RepeatedPtrField<v1::ActivationPlanStep>* out);

/// What applying `plan` leaves active, from `active` (its deactivations
/// removed, its activations added): for planning the steps after it.
void applyToActive(const Plan& plan, std::set<std::string>* active);

/// Carries out plan steps (the coordinator's FleetControl, coordinator/control/,
/// routes them to the robot's behavior systems; tests fake them).
class PlanActions {
 public:
  virtual ~PlanActions() = default;
  /// OK when the behavior could be activated now; FAILED_PRECONDITION with
  /// the reason otherwise.
  virtual absl::Status checkSituation(const std::string& behavior) = 0;
  /// Returns the activation id.
  virtual absl::StatusOr<std::string> activate(const std::string& behavior,
                                               const google::protobuf::Struct& parameters) = 0;
  /// Must be OK when the behavior is no longer active.
  virtual absl::Status deactivate(const std::string& behavior) = 0;
};

struct ApplyOptions {
  /// A behavior whose requirement the plan has just activated may need a
  /// moment before its situation holds (the first pose estimate is not
  /// published yet): its CheckSituation is retried every `settle_poll` for up
  /// to `settle_timeout` (wall time). Zero: no retry.
  std::chrono::milliseconds settle_timeout{2000};
  std::chrono::milliseconds settle_poll{50};
  /// Without such a requirement, a refusal is still retried for this long:
  /// a situation is computed from streamed state (the flight status, the
  /// pose estimate), which may lag the change that just happened (the lease
  /// the previous behavior released a moment ago).
  std::chrono::milliseconds lag_timeout{500};
  /// How to wait between retries (tests make it instant).
  std::function<void(std::chrono::milliseconds)> sleep;
};

struct PlanResult {
  /// Activation id of the target.
  std::string activation_id;
  /// Every behavior the plan activated (requirements, then the target),
  /// with its activation id.
  std::vector<std::pair<std::string, std::string>> activated;
  /// Every behavior the plan deactivated.
  std::vector<std::string> deactivated;
};

/// Applies `plan` in order. On a failing step, deactivates what the plan
/// activated and returns the step's error code with a message naming the
/// step ("step 4 of 5 (activate FOLLOW_PATH): ...").
absl::StatusOr<PlanResult> applyPlan(const Plan& plan, PlanActions& actions,
                                     const ApplyOptions& options = {});

}  // namespace behaviorlib::coordinator
