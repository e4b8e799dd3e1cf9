#pragma once

// The main() of a behavior-system process: one process hosting a group of
// behaviors on one port (the paper's behavior systems), each served as its
// own typed gRPC service plus the generic BehaviorSystem service, with health,
// reflection, Prometheus metrics and orderly SIGTERM handling.
//
//   int main(int argc, char** argv) {
//     return behaviorlib::server::runBehaviorSystem(
//         argc, argv, "basic_quadrotor_behaviors", [](BehaviorSystemBuilder& b) {
//           b.add<WaitBehavior>();
//         });
//   }
//
// Flags: --robot-id, --listen, --advertise, --metrics-listen, --port-file, --channel,
// --clock (steady|sim), --config (YAML), --coordinator, --flight-controller.
// Run with --help.
//
// Behaviors that need the process's connections (the data channel, the
// flight controller's address) take them from builder.context(), either in
// their constructor (add<> forwards arguments) or through a resource the
// builder keeps alive for the process's life:
//
//   [](BehaviorSystemBuilder& b) {
//     auto& vehicle = b.own(std::make_unique<RemoteVehicle>(b.context()));
//     b.add<TakeOffBehavior>(vehicle);
//   }

#include <grpcpp/grpcpp.h>
#include <grpcpp/impl/service_type.h>
#include <yaml-cpp/yaml.h>

#include <functional>
#include <map>
#include <memory>
#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

#include "absl/status/statusor.h"
#include "behaviorlib/behavior_execution_manager.h"
#include "behaviorlib/clock.h"
#include "behaviorlib/server/belief_client.h"
#include "behaviorlib/server/lifecycle_calls.h"
#include "behaviorlib/server/typed_behavior_service.h"

namespace behaviorlib::channel {
class ChannelClient;
}  // namespace behaviorlib::channel

namespace behaviorlib::server {

class SetpointLedger;

/// What a behavior-system process offers its behaviors beyond the
/// BehaviorContext each behavior gets at start(): the connections and
/// settings made from its flags. Everything here lives until the process
/// has stopped every behavior.
struct SystemContext {
  /// The system's name ("basic_quadrotor_behaviors").
  std::string system;
  /// --robot-id.
  std::string robot_id;
  /// The behaviors' clock (--clock).
  const Clock* clock = nullptr;
  /// The data channel (--channel); null when the process runs without one.
  channel::ChannelClient* channel = nullptr;
  /// --flight-controller: the FlightController's address ("host:port");
  /// empty when none was given.
  std::string flight_controller;
  /// The whole --config document (may be null), and its file.
  YAML::Node config;
  std::string config_file;
  /// The coordinator's belief memory (--coordinator); null without one.
  const BeliefClient* beliefs = nullptr;
  /// Following the simulator's time grants (--follow-time) with that
  /// simulator as the --flight-controller: counts the setpoints streamed to
  /// it, which applies them before it steps on (setpoint_ledger.h); null
  /// otherwise.
  SetpointLedger* setpoints = nullptr;
};

/// Collects the behaviors of a system and their typed services.
class BehaviorSystemBuilder {
 public:
  explicit BehaviorSystemBuilder(const AcceptGate& gate, SystemContext context = {})
      : gate_(gate), context_(std::move(context)) {}

  /// The process's connections and settings, for behaviors and resources.
  const SystemContext& context() const { return context_; }

  /// Keeps `resource` (shared by several behaviors: a vehicle connection, a
  /// cache of topics) alive until every behavior has been stopped, and
  /// returns it.
  template <class T>
  T& own(std::unique_ptr<T> resource) {
    T& ref = *resource;
    resources_.push_back(std::shared_ptr<void>(std::move(resource)));
    return ref;
  }

  /// Decodes the system's own keys of the --config document (all but the
  /// library's `behaviors`) into C, a configuration message (decision 45):
  /// INVALID_ARGUMENT with file:line for an unknown key or a bad value. A
  /// system that never calls it accepts no key but `behaviors`.
  template <class C>
  absl::StatusOr<C> systemConfiguration() {
    system_configuration_type_ = C::descriptor();
    C out;
    if (absl::Status s = decodeSystemConfiguration(&out); !s.ok()) return s;
    return out;
  }
  absl::Status decodeSystemConfiguration(google::protobuf::Message* out);
  /// Whether the system decoded its own keys (systemConfiguration()).
  bool systemConfigurationRead() const { return system_configuration_read_; }
  /// Every key the --config file may hold, by section, for --help-config.
  std::string documentConfiguration() const;

  /// Hosts BehaviorT (constructed from `args`) and serves it as the typed
  /// service generated for its parameters message. The caller includes the
  /// generated X.behaviors.h of the proto file that declares the behavior;
  /// it declares `behaviorServiceOf`, which maps the parameters to the
  /// service.
  template <class BehaviorT, class... Args>
  BehaviorSystemBuilder& add(Args&&... args) {
    using Params = typename BehaviorT::Parameters;
    using S = decltype(behaviorServiceOf(static_cast<const Params*>(nullptr)));
    auto behavior = std::make_unique<BehaviorExecutionManager>(
        std::make_unique<BehaviorT>(std::forward<Args>(args)...));
    checkServiceMatches(*behavior, S::service_full_name());
    services_.push_back(std::make_unique<TypedBehaviorService<S>>(*behavior, gate_));
    service_names_[behavior->name()] = S::service_full_name();
    behaviors_.push_back(std::move(behavior));
    return *this;
  }

  /// Hosts a behavior reachable only through the generic BehaviorSystem
  /// service (tests, tools).
  BehaviorSystemBuilder& addGeneric(std::unique_ptr<BehaviorBase> behavior) {
    behaviors_.push_back(std::make_unique<BehaviorExecutionManager>(std::move(behavior)));
    return *this;
  }

  /// Adds work outside the behaviors' ticks that the deterministic mode
  /// waits for before the system reports a grant (e.g. a mapper inserting
  /// the scans it received): `caught_up` says whether it is done.
  void addCatchUpCheck(std::function<bool()> caught_up) {
    catch_up_checks_.push_back(std::move(caught_up));
  }
  const std::vector<std::function<bool()>>& catchUpChecks() const { return catch_up_checks_; }

  std::vector<std::unique_ptr<BehaviorExecutionManager>>& behaviors() { return behaviors_; }
  std::vector<std::unique_ptr<grpc::Service>>& services() { return services_; }
  const std::map<std::string, std::string>& serviceNames() const { return service_names_; }

 private:
  // Throws std::logic_error (a programming error) on a mismatch.
  static void checkServiceMatches(const BehaviorExecutionManager& behavior,
                                  const char* service_full_name);

  const AcceptGate& gate_;
  SystemContext context_;
  // Declared before behaviors_: destroyed after them.
  std::vector<std::shared_ptr<void>> resources_;
  std::vector<std::unique_ptr<BehaviorExecutionManager>> behaviors_;
  std::vector<std::unique_ptr<grpc::Service>> services_;
  std::map<std::string, std::string> service_names_;
  std::vector<std::function<bool()>> catch_up_checks_;
  bool system_configuration_read_ = false;
  const google::protobuf::Descriptor* system_configuration_type_ = nullptr;
};

/// A behavior system's settings: its command line, parsed.
struct BehaviorSystemOptions {
  /// The system's name ("basic_quadrotor_behaviors").
  std::string system;
  std::string robot_id = "drone1";
  /// gRPC address host:port (port 0 picks a free port).
  std::string listen = "127.0.0.1:50061";
  /// What the coordinator dials to reach the system (empty: --listen's
  /// host with the bound port).
  std::string advertise;
  /// After a link loss this long (the system's clock), activate
  /// `link_loss_action` (LinkLossWatch; zero or empty: never).
  Duration link_loss_timeout{0};
  std::string link_loss_action;
  /// Prometheus /metrics address (port 0 picks one; empty: no metrics).
  std::string metrics_listen = "127.0.0.1:0";
  /// The data channel broker; empty: none.
  std::string channel;
  /// "steady" (host monotonic time) or "sim" (the channel's clock topic).
  std::string clock = "steady";
  /// The --config document (may be null), and its file (for messages).
  YAML::Node config;
  std::string config_file;
  /// Register with this coordinator; empty: no registration.
  std::string coordinator;
  /// The FlightController's address for flight behaviors; empty: none.
  std::string flight_controller;
  /// Follow this simulator's time grants (deterministic mode; needs clock
  /// "sim"); empty: no.
  std::string follow_time;
  /// Prefix of the process's log lines (default: the system's name).
  std::string log_prefix;
};

/// A behavior-system process as a class: its clock, channel, behaviors,
/// services, metrics, registration and time following, serving on one port.
/// runBehaviorSystem() runs one until a shutdown signal; a test builds one
/// in-process.
class BehaviorSystemProcess {
 public:
  /// INVALID_ARGUMENT for inconsistent options or behaviors that do not
  /// start (onConfigure), UNAVAILABLE when a port cannot be bound.
  static absl::StatusOr<std::unique_ptr<BehaviorSystemProcess>> start(
      BehaviorSystemOptions options,
      const std::function<void(BehaviorSystemBuilder&)>& register_behaviors);
  /// shutdown(), if not done yet.
  ~BehaviorSystemProcess();
  BehaviorSystemProcess(const BehaviorSystemProcess&) = delete;
  BehaviorSystemProcess& operator=(const BehaviorSystemProcess&) = delete;

  int grpcPort() const;
  int metricsPort() const;
  /// The event log's incarnation (changes with every start).
  const std::string& incarnation() const;
  /// The hosted behaviors' names, in registration order.
  std::vector<std::string> behaviorNames() const;
  /// Writes grpc_port= and metrics_port= lines to `path` (nothing when empty).
  bool writePortFile(const std::string& path, std::string* error) const;
  /// In order: leaves the simulator's barrier, refuses new lifecycle calls,
  /// ends active behaviors with INTERRUPTED (their events reach the
  /// subscribers and the coordinator), unregisters, ends the event streams,
  /// stops serving.
  void shutdown();

 private:
  struct Parts;
  explicit BehaviorSystemProcess(std::unique_ptr<Parts> parts);
  std::unique_ptr<Parts> parts_;
};

/// Parses flags, starts a BehaviorSystemProcess, serves until SIGTERM/SIGINT,
/// then shuts it down (every active behavior ends INTERRUPTED) and exits 0.
/// Returns the process exit code.
int runBehaviorSystem(int argc, char** argv, const std::string& system_name,
                      const std::function<void(BehaviorSystemBuilder&)>& register_behaviors);

}  // namespace behaviorlib::server
