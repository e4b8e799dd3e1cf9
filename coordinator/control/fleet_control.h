#pragma once

// FleetControl: the coordinator's blocking operations on the fleet, shared by
// the gRPC service (ActivateBehavior with the catalog's plan), the missions
// (it is their MissionActions) and the safety policy.
//
//   FleetControl fleet(registry, log, catalog, {});
//   auto done = fleet.activateBehavior({.robot_id = "drone1", .behavior = "FOLLOW_PATH",
//                                       .parameters = params});
//   // done->plan: CheckSituation, deactivate what conflicts, activate what is
//   // missing, activate the target; applied under the robot's lock.
//   auto finished = fleet.awaitFinished("drone1", done->activation.activation_id(), 10s);
//
// Activations of one robot are serialized (one plan at a time per robot);
// different robots proceed in parallel. After each activation or
// deactivation of a plan, FleetControl waits until the system's event has
// reached the coordinator's event log, so that the next plan sees the robot
// as it is. It follows the log itself (an index of activations seen and
// finished), so awaitFinished also answers for an activation that finished
// before it was asked.
//
// Calls block: callers are the service's worker pool and mission threads,
// never gRPC's callback threads. Thread-safe.

#include <google/protobuf/struct.pb.h>
#include <grpcpp/grpcpp.h>

#include <chrono>
#include <deque>
#include <functional>
#include <map>
#include <memory>
#include <optional>
#include <set>
#include <string>
#include <unordered_map>

#include "absl/base/thread_annotations.h"
#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/synchronization/mutex.h"
#include "behaviorlib/v1/behavior.pb.h"
#include "coordinator/catalog/catalog.h"
#include "coordinator/catalog/planner.h"
#include "coordinator/events/fleet_event_log.h"
#include "coordinator/mission/mission_runner.h"
#include "coordinator/registry/registry.h"

namespace behaviorlib::coordinator {

/// A behavior system's error, reworded to name the robot and system, with the
/// system's details (reason, field violations) kept and the robot and system
/// added to its metadata. An error without a reason of the system's own in
/// which the system could not be reached (UNAVAILABLE, DEADLINE_EXCEEDED) is
/// SYSTEM_UNAVAILABLE.
absl::Status systemError(const grpc::Status& status, const Registry::Route& route);

struct FleetControlOptions {
  /// Deadline of each call to a behavior system.
  std::chrono::milliseconds call_timeout{10000};
  /// How long a plan step waits for its event to reach the coordinator.
  std::chrono::milliseconds event_timeout{3000};
  /// Retrying CheckSituation of a behavior whose requirement was just
  /// activated (see ApplyOptions).
  ApplyOptions apply;
  /// Finished activations remembered for awaitFinished.
  size_t remembered_activations = 100000;
};

class FleetControl final : public MissionActions {
 public:
  /// `catalog` may be empty (no rules: every activation is the target only).
  FleetControl(Registry& registry, FleetEventLog& log, std::shared_ptr<const Catalog> catalog,
               FleetControlOptions options = {});
  ~FleetControl() override;
  FleetControl(const FleetControl&) = delete;
  FleetControl& operator=(const FleetControl&) = delete;

  const Catalog* catalog() const { return catalog_.get(); }

  struct ActivateRequest {
    std::string robot_id;
    std::string behavior;
    google::protobuf::Struct parameters;
    std::string request_id;
    /// Only make the plan.
    bool dry_run = false;
    /// Only activate the target (no plan).
    bool skip_plan = false;
  };
  struct ActivateResult {
    std::string system;
    /// The target's activation (empty for a dry run).
    v1::ActivateResponse activation;
    Plan plan;
  };
  /// Plans and applies (see the header comment). Status codes: those of
  /// makePlan (NOT_FOUND, FAILED_PRECONDITION, INVALID_ARGUMENT), those of the
  /// failing step with the step named, UNAVAILABLE when a system is down,
  /// CANCELLED after stop().
  absl::StatusOr<ActivateResult> activateBehavior(const ActivateRequest& request);

  /// Deactivates one behavior (INTERRUPTED) under the robot's lock and waits
  /// for its finished event to reach the log; OK when it was inactive. `system` receives the
  /// hosting system.
  absl::StatusOr<v1::DeactivateResponse> deactivateBehavior(const std::string& robot_id,
                                                            const std::string& behavior,
                                                            const std::string& activation_id,
                                                            std::string* system = nullptr);

  /// The robot's active (or paused) behaviors as the event stream tells,
  /// with their activation ids.
  std::map<std::string, std::string> activeBehaviors(const std::string& robot_id) const;

  /// What a plan for `robot_id` starts from: the behaviors its systems that
  /// are up host (`available`) and those active or paused now (`active`).
  /// The rest of the request is the caller's; nothing is called.
  PlanRequest planningView(const std::string& robot_id) const;

  /// Ends every blocking call in progress (CANCELLED) and refuses new ones.
  void stop();

  // MissionActions.
  absl::StatusOr<std::string> activate(const std::string& robot, const std::string& behavior,
                                       const google::protobuf::Struct& parameters,
                                       const std::string& request_id) override;
  absl::Status deactivate(const std::string& robot, const std::string& behavior) override;
  absl::Status pause(const std::string& robot, const std::string& behavior) override;
  absl::Status resume(const std::string& robot, const std::string& behavior) override;
  std::optional<FinishedActivation> awaitFinished(const std::string& robot,
                                                  const std::string& activation_id,
                                                  std::chrono::milliseconds timeout) override;

 private:
  class StepActions;

  // The robot's serialization lock: one plan or deactivation at a time per
  // robot. Never taken twice by one thread: a plan's steps deactivate with
  // deactivateLocked().
  absl::Mutex& robotLock(const std::string& robot_id);
  // deactivateBehavior()'s work, the robot's lock held by the caller.
  absl::StatusOr<v1::DeactivateResponse> deactivateLocked(const Registry::Route& route,
                                                          const std::string& robot_id,
                                                          const std::string& behavior,
                                                          const std::string& activation_id);
  // Calls a system; the status names robot, system and address.
  absl::Status route(const std::string& robot_id, const std::string& behavior,
                     Registry::Route* out) const;
  absl::StatusOr<v1::ActivateResponse> callActivate(const Registry::Route& route,
                                                    const std::string& behavior,
                                                    const google::protobuf::Struct& parameters,
                                                    const std::string& request_id);
  absl::StatusOr<v1::DeactivateResponse> callDeactivate(const Registry::Route& route,
                                                        const std::string& behavior,
                                                        const std::string& activation_id);
  absl::Status callCheckSituation(const Registry::Route& route, const std::string& behavior);
  /// Whether the behavior's own system says it is active (true when it does
  /// not answer).
  bool callStillActive(const Registry::Route& route, const std::string& behavior);
  /// Pause or Resume on the behavior's system.
  template <class Request, class Response>
  absl::Status callLifecycle(const std::string& robot, const std::string& behavior,
                             grpc::Status (v1::BehaviorSystem::Stub::*method)(grpc::ClientContext*,
                                                                              const Request&,
                                                                              Response*));

  // Event index, fed by a subscription to the log.
  void drainEvents();
  /// Waits until the activated (or finished) event of `activation_id` is in
  /// the log; false on timeout or stop.
  bool awaitSeen(const std::string& activation_id, std::chrono::milliseconds timeout);
  bool awaitFinishedSeen(const std::string& activation_id, std::chrono::milliseconds timeout);
  /// Waits (index_mutex_ held) until `found` holds or the fleet stops, at
  /// most `timeout`.
  void awaitIndexLocked(const std::function<bool()>& found, std::chrono::milliseconds timeout)
      ABSL_EXCLUSIVE_LOCKS_REQUIRED(index_mutex_);
  /// Remembers `activation_id` (index_mutex_ held), evicting the oldest.
  void rememberLocked(const std::string& activation_id) ABSL_EXCLUSIVE_LOCKS_REQUIRED(index_mutex_);
  /// Records that a Deactivate of `activation_id` returned OK: until its
  /// finished event arrives, the registry's view may still call it active.
  void noteDeactivated(const std::string& activation_id);
  /// The robot's behaviors as the registry sees them, less the activations
  /// known to have ended (a finished event seen, or a Deactivate that
  /// returned OK): so the coordinator reads its own writes.
  std::vector<SystemLink::BehaviorView> robotView(const std::string& robot_id) const;

  Registry& registry_;
  FleetEventLog& log_;
  std::shared_ptr<const Catalog> catalog_;
  const FleetControlOptions options_;

  absl::Mutex locks_mutex_;
  std::map<std::string, std::unique_ptr<absl::Mutex>> robot_locks_ ABSL_GUARDED_BY(locks_mutex_);

  mutable absl::Mutex index_mutex_;
  bool stopped_ ABSL_GUARDED_BY(index_mutex_) = false;
  // By activation id.
  std::unordered_map<std::string, FinishedActivation> finished_ ABSL_GUARDED_BY(index_mutex_);
  // Activated or finished.
  std::set<std::string> seen_ ABSL_GUARDED_BY(index_mutex_);
  // Deactivate returned OK; finished event maybe not seen.
  std::set<std::string> deactivated_ ABSL_GUARDED_BY(index_mutex_);
  // Eviction order.
  std::deque<std::string> seen_order_ ABSL_GUARDED_BY(index_mutex_);
  std::unique_ptr<FleetSubscription> subscription_ ABSL_GUARDED_BY(index_mutex_);
};

}  // namespace behaviorlib::coordinator
