#pragma once

// The coordinator's registry: one SystemLink per behavior-system process,
// found by robot and system name (or by address for a --systems entry not
// reached yet), and the routing of a robot's behavior to its hosting system.
//
//   Registry registry(log, metrics, {.link = {.grace = std::chrono::seconds(1)}});
//   registry.addConfigured({.robot_id = "drone1", .address = "127.0.0.1:50061"});
//   grpc::Status s = registry.registerSystem(request, description);
//   Registry::Route route;
//   if (registry.route("drone1", "WAIT", &route).ok()) route.stub->...;
//   registry.stop();

#include <grpcpp/grpcpp.h>

#include <functional>
#include <memory>
#include <string>
#include <vector>

#include "absl/base/thread_annotations.h"
#include "absl/synchronization/mutex.h"
#include "behaviorlib/durable/v1/journal.pb.h"
#include "behaviorlib/v1/behavior.grpc.pb.h"
#include "behaviorlib/v1/coordinator.pb.h"
#include "behaviorlib/v1/mission.pb.h"
#include "coordinator/events/fleet_event_log.h"
#include "coordinator/metrics/coordinator_metrics.h"
#include "coordinator/registry/system_link.h"
#include "coordinator/registry/systems_config.h"

namespace behaviorlib::coordinator {

struct RegistryOptions {
  LinkOptions link;
  /// Called after a system registered (registered = true) or unregistered,
  /// under no lock of the registry (the coordinator journals it).
  std::function<void(const durable::v1::SystemRecord& record)> on_membership;
};

class Registry {
 public:
  Registry(FleetEventLog& log, CoordinatorMetrics& metrics, RegistryOptions options);
  /// Stops every link.
  ~Registry();
  Registry(const Registry&) = delete;
  Registry& operator=(const Registry&) = delete;

  /// Starts following a system listed in the --systems file.
  void addConfigured(const ConfiguredSystem& system);

  /// Registers the system of `request`, whose ListBehaviors at
  /// request.address() answered `description` (identity already checked).
  /// FAILED_PRECONDITION when another system of the robot already hosts one
  /// of its behaviors.
  grpc::Status registerSystem(const v1::RegisterSystemRequest& request,
                              const v1::ListBehaviorsResponse& description);
  /// OK, NOT_FOUND (register again) or FAILED_PRECONDITION (another live
  /// incarnation holds the robot and system).
  grpc::Status heartbeat(const v1::HeartbeatRequest& request);
  /// OK or NOT_FOUND.
  grpc::Status unregister(const v1::UnregisterSystemRequest& request);

  void listSystems(const std::string& robot_id, v1::ListSystemsResponse* response) const;
  void listBehaviors(const std::string& robot_id, const std::string& behavior,
                     v1::ListFleetBehaviorsResponse* response) const;
  /// The robot's behaviors as plans see them (names and states only).
  std::vector<SystemLink::BehaviorView> robotBehaviors(const std::string& robot_id) const;

  /// Where a robot's behavior is served.
  struct Route {
    std::shared_ptr<v1::BehaviorSystem::Stub> stub;
    std::string robot_id;
    std::string system;
    std::string address;
  };
  /// NOT_FOUND naming the robot or the behavior when unknown; UNAVAILABLE
  /// when the hosting system is down, unregistered or not reached yet.
  grpc::Status route(const std::string& robot_id, const std::string& behavior, Route* out) const;

  /// Stops and joins every link.
  void stop();

 private:
  // Links still in use (neither retired nor, for registered systems,
  // leaving) matching robot and system, or the address of a not yet reached
  // configured entry.
  std::shared_ptr<SystemLink> findLocked(const std::string& robot_id, const std::string& system,
                                         const std::string& address) const
      ABSL_EXCLUSIVE_LOCKS_REQUIRED(mutex_);
  void onRetired(SystemLink* link);
  void updateGaugeLocked() ABSL_EXCLUSIVE_LOCKS_REQUIRED(mutex_);

  FleetEventLog& log_;
  CoordinatorMetrics& metrics_;
  RegistryOptions options_;
  mutable absl::Mutex mutex_;
  bool stopped_ ABSL_GUARDED_BY(mutex_) = false;
  std::vector<std::shared_ptr<SystemLink>> links_ ABSL_GUARDED_BY(mutex_);
  // Links that ended (unregistered); joined at stop().
  std::vector<std::shared_ptr<SystemLink>> retired_ ABSL_GUARDED_BY(mutex_);
};

}  // namespace behaviorlib::coordinator
