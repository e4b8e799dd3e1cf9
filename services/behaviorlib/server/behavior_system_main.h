#pragma once

// The main() of a behavior-system process: one process hosting a group of
// behaviors on one port (the paper's behavior systems), each served as its
// own typed gRPC service plus the generic BehaviorSystem service, with health,
// reflection, Prometheus metrics and orderly SIGTERM handling.
//
//   int main(int argc, char** argv) {
//     return behaviorlib::server::runBehaviorSystem(
//         argc, argv, "basic_quadrotor_behaviors", [](BehaviorSystemBuilder& b) {
//           b.add<WaitBehavior, behaviorlib::v1::Wait>();
//         });
//   }
//
// Flags: --robot-id, --listen, --metrics-listen, --port-file, --channel,
// --clock (steady|sim), --config (YAML), --coordinator. Run with --help.

#include <grpcpp/grpcpp.h>
#include <grpcpp/impl/service_type.h>

#include <functional>
#include <map>
#include <memory>
#include <stdexcept>
#include <string>
#include <vector>

#include "behaviorlib/behavior_execution_manager.h"
#include "behaviorlib/server/lifecycle_calls.h"
#include "behaviorlib/server/typed_behavior_service.h"

namespace behaviorlib::server {

/// Collects the behaviors of a system and their typed services.
class BehaviorSystemBuilder {
 public:
  explicit BehaviorSystemBuilder(const AcceptGate& gate) : gate_(gate) {}

  /// Hosts BehaviorT and serves it as the typed service S. The behavior's
  /// name must equal S's `(behaviorlib.v1.behavior).name` option.
  template <class BehaviorT, class S>
  BehaviorSystemBuilder& add() {
    auto behavior = std::make_unique<BehaviorT>();
    checkServiceMatches(*behavior, S::service_full_name());
    services_.push_back(std::make_unique<TypedBehaviorService<S>>(*behavior, gate_));
    service_names_[behavior->name()] = S::service_full_name();
    behaviors_.push_back(std::move(behavior));
    return *this;
  }

  /// Hosts a behavior reachable only through the generic BehaviorSystem
  /// service (tests, tools).
  BehaviorSystemBuilder& addGeneric(std::unique_ptr<BehaviorExecutionManager> behavior) {
    behaviors_.push_back(std::move(behavior));
    return *this;
  }

  std::vector<std::unique_ptr<BehaviorExecutionManager>>& behaviors() { return behaviors_; }
  std::vector<std::unique_ptr<grpc::Service>>& services() { return services_; }
  const std::map<std::string, std::string>& serviceNames() const { return service_names_; }

 private:
  // Throws std::logic_error (a programming error) on a mismatch.
  static void checkServiceMatches(const BehaviorExecutionManager& behavior,
                                  const char* service_full_name);

  const AcceptGate& gate_;
  std::vector<std::unique_ptr<BehaviorExecutionManager>> behaviors_;
  std::vector<std::unique_ptr<grpc::Service>> services_;
  std::map<std::string, std::string> service_names_;
};

/// Parses flags, starts everything, serves until SIGTERM/SIGINT, then ends
/// every active behavior with INTERRUPTED (the events reach subscribers) and
/// exits 0. Returns the process exit code.
int runBehaviorSystem(int argc, char** argv, const std::string& system_name,
                      const std::function<void(BehaviorSystemBuilder&)>& register_behaviors);

}  // namespace behaviorlib::server
