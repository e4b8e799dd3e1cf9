#include "behaviorlib/server/behavior_system_main.h"

#include <google/protobuf/descriptor.h>
#include <google/protobuf/empty.pb.h>
#include <yaml-cpp/yaml.h>

#include <cstdio>
#include <iostream>

#include "absl/flags/flag.h"
#include "behaviorlib/behavior_host.h"
#include "behaviorlib/channel/channel_client.h"
#include "behaviorlib/channel/sim_clock.h"
#include "behaviorlib/clock.h"
#include "behaviorlib/config/v1/execution.pb.h"
#include "behaviorlib/configuration.h"
#include "behaviorlib/server/behavior_metrics.h"
#include "behaviorlib/server/behavior_system_service.h"
#include "behaviorlib/server/coordinator_registration.h"
#include "behaviorlib/server/link_loss.h"
#include "behaviorlib/server/setpoint_ledger.h"
#include "behaviorlib/server/time_follower.h"
#include "behaviorlib/server_kit/confined_files.h"
#include "behaviorlib/server_kit/flags.h"
#include "behaviorlib/server_kit/server_runtime.h"
#include "behaviorlib/server_kit/yaml_guard.h"
#include "behaviorlib/v1/options.pb.h"

// The flags of every behavior-system process (runBehaviorSystem).
ABSL_FLAG(std::string, robot_id, "drone1", "robot this process serves");
ABSL_FLAG(std::string, listen, "127.0.0.1:50061",
          "gRPC address host:port (port 0 picks a free port)");
ABSL_FLAG(std::string, advertise, "",
          "the host:port the coordinator dials to reach this system, when not the --listen "
          "address (a relay or a NAT in front of it); empty: --listen's host and bound port");
ABSL_FLAG(double, link_loss_timeout_s, 0.0,
          "once the coordinator has been unreachable this long (the vehicle's time), activate "
          "--link-loss-action (0: never)");
ABSL_FLAG(std::string, link_loss_action, "",
          "a behavior of this system to activate with its default parameters after a link loss "
          "(e.g. LAND)");
ABSL_FLAG(std::string, metrics_listen, "127.0.0.1:0",
          "Prometheus /metrics address host:port (port 0 picks a free port; empty disables)");
ABSL_FLAG(std::string, port_file, "", "write the bound ports here (grpc_port=, metrics_port=)");
ABSL_FLAG(std::string, channel, "", "data channel broker address host:port");
ABSL_FLAG(std::string, clock, "steady",
          "behavior clock: 'steady' (host monotonic time) or 'sim' (the channel's 'clock' "
          "topic, published by the simulator)");
ABSL_FLAG(std::string, config, "",
          "YAML file: behaviors: {NAME: {frequency_hz, maximum_execution_time_s, "
          "watchdog_timeout_s, ...}}");
ABSL_FLAG(bool, help_config, false,
          "print every key the --config file may hold, with its type, unit, range, default and "
          "description (the behaviors' configuration messages), and exit");
ABSL_FLAG(std::string, coordinator, "",
          "coordinator address host:port: register there (retrying until it is up) with this "
          "process's real bound port, send heartbeats, register again after a coordinator "
          "restart, unregister on SIGTERM; empty: no registration");
ABSL_FLAG(std::string, flight_controller, "",
          "FlightController address host:port (the simulator's, or an autopilot bridge's) for "
          "flight behaviors; empty: they report that no flight controller is configured");
ABSL_FLAG(std::string, follow_time, "",
          "simulator address host:port: follow its time grants (deterministic mode, simulator "
          "--time-scale max): each granted time is reported back once every behavior ran what "
          "was due, and the simulator waits for it; needs --clock sim");

namespace behaviorlib::server {

namespace {
constexpr size_t kMaxConfigBytes = 1 << 20;
}  // namespace

absl::Status BehaviorSystemBuilder::decodeSystemConfiguration(google::protobuf::Message* out) {
  system_configuration_read_ = true;
  return config::decode(
      context_.config,
      config::Source{.file = context_.config_file, .section = "", .skip = {"behaviors"}}, {out});
}

std::string BehaviorSystemBuilder::documentConfiguration() const {
  std::string out = "--config of " + context_.system + " (YAML; decision 45):\n";
  if (system_configuration_type_ != nullptr) {
    out += config::document({system_configuration_type_}, "  ");
  }
  out += "behaviors:\n  <every behavior>: the library's keys\n";
  out += config::document({config::v1::ExecutionConfig::descriptor()}, "    ");
  for (const auto& behavior : behaviors_) {
    const std::string keys = config::document({&behavior->configurationType()}, "    ");
    out += "  " + behavior->name() + ":" + (keys.empty() ? " no keys of its own\n" : "\n" + keys);
  }
  return out;
}

void BehaviorSystemBuilder::checkServiceMatches(const BehaviorExecutionManager& behavior,
                                                const char* service_full_name) {
  const auto* service =
      google::protobuf::DescriptorPool::generated_pool()->FindServiceByName(service_full_name);
  if (!service) throw std::logic_error(std::string("unknown service ") + service_full_name);
  const auto& info = service->options().GetExtension(v1::behavior);
  if (info.name() != behavior.name()) {
    throw std::logic_error("behavior " + behavior.name() + " registered with service " +
                           service_full_name + ", which declares behavior '" + info.name() + "'");
  }
  if (info.parameters_type() != behavior.parametersType().full_name()) {
    throw std::logic_error("behavior " + behavior.name() + " takes " +
                           behavior.parametersType().full_name() + " but service " +
                           service_full_name + " declares " + info.parameters_type());
  }
}

// Declared in construction order: destroyed in reverse, after shutdown().
struct BehaviorSystemProcess::Parts {
  explicit Parts(BehaviorSystemOptions o) : options(std::move(o)), gate(options.robot_id) {}

  BehaviorSystemOptions options;
  std::unique_ptr<channel::ChannelClient> channel_client;
  std::unique_ptr<Clock> clock;
  channel::SimClock* sim_clock = nullptr;
  AcceptGate gate;
  std::unique_ptr<BeliefClient> belief_client;
  std::unique_ptr<SetpointLedger> setpoints;  // following the time grants
  std::unique_ptr<BehaviorSystemBuilder> builder;
  // Before the host, which calls its awaitTurn() until it stops.
  std::unique_ptr<TimeFollower> follower;
  std::unique_ptr<BehaviorHost> host;
  server_kit::ServerRuntime runtime;
  std::unique_ptr<BehaviorMetrics> metrics;
  std::unique_ptr<BehaviorSystemService> system_service;
  std::unique_ptr<CoordinatorRegistration> registration;
  std::unique_ptr<LinkLossWatch> link_loss;
  bool host_started = false;
  bool stopped = false;
};

absl::StatusOr<std::unique_ptr<BehaviorSystemProcess>> BehaviorSystemProcess::start(
    BehaviorSystemOptions options,
    const std::function<void(BehaviorSystemBuilder&)>& register_behaviors) {
  if (options.log_prefix.empty()) options.log_prefix = options.system;
  if (!options.follow_time.empty() && options.clock != "sim") {
    return absl::InvalidArgumentError(
        "--follow-time needs --clock sim (the grants set simulated time)");
  }
  if (options.clock != "steady" && options.clock != "sim") {
    return absl::InvalidArgumentError("--clock must be 'steady' or 'sim', not '" + options.clock +
                                      "'");
  }
  if (options.clock == "sim" && options.channel.empty()) {
    return absl::InvalidArgumentError(
        "--clock sim needs --channel (simulated time comes from its 'clock' topic)");
  }
  auto p = std::make_unique<Parts>(std::move(options));
  const BehaviorSystemOptions& o = p->options;
  if (!o.channel.empty()) p->channel_client = std::make_unique<channel::ChannelClient>(o.channel);
  if (o.clock == "steady") {
    p->clock = std::make_unique<SteadyClock>();
  } else {
    // Extrapolates the simulator's time line; runs on at the last time scale
    // when the simulator dies, so that staleness checks notice it.
    // Following the time grants, the grants are the time: the clock topic
    // would only repeat them.
    auto simulated = o.follow_time.empty() ? std::make_unique<channel::SimClock>(*p->channel_client)
                                           : std::make_unique<channel::SimClock>();
    p->sim_clock = simulated.get();
    p->clock = std::move(simulated);
  }

  SystemContext context;
  context.system = o.system;
  context.robot_id = o.robot_id;
  context.clock = p->clock.get();
  context.channel = p->channel_client.get();
  context.flight_controller = o.flight_controller;
  context.config = o.config;
  context.config_file = o.config_file;
  if (!o.coordinator.empty()) {
    p->belief_client = std::make_unique<BeliefClient>(o.coordinator);
    context.beliefs = p->belief_client.get();
  }
  // Only when the setpoints go to the simulator that grants the time: another
  // platform's streams would never reach the simulator's barrier.
  if (!o.follow_time.empty() && o.flight_controller == o.follow_time) {
    p->setpoints = std::make_unique<SetpointLedger>();
    context.setpoints = p->setpoints.get();
  }
  p->builder = std::make_unique<BehaviorSystemBuilder>(p->gate, std::move(context));
  register_behaviors(*p->builder);
  if (!p->builder->systemConfigurationRead()) {
    google::protobuf::Empty none;
    if (absl::Status s = p->builder->decodeSystemConfiguration(&none); !s.ok()) {
      return absl::InvalidArgumentError("--config: " + std::string(s.message()));
    }
  }

  if (!o.follow_time.empty()) {
    p->follower =
        std::make_unique<TimeFollower>(o.follow_time, o.system + "/" + o.robot_id, *p->sim_clock,
                                       p->channel_client.get(), o.robot_id, p->setpoints.get());
  }
  BehaviorHostOptions host_options;
  host_options.robot_id = o.robot_id;
  host_options.system = o.system;
  if (p->follower) {
    host_options.before_command = [follower = p->follower.get()] { follower->awaitTurn(); };
  }
  p->host = std::make_unique<BehaviorHost>(host_options, *p->clock);
  for (auto& behavior : p->builder->behaviors()) p->host->add(std::move(behavior));

  p->metrics = std::make_unique<BehaviorMetrics>(p->runtime.registry(), o.robot_id, o.system);
  // A behavior blocked by the watchdog reports its typed service NOT_SERVING.
  p->host->setObserverFactory(p->metrics->observerFactory(
      [runtime = &p->runtime, service_names = p->builder->serviceNames()](
          const std::string& behavior, bool blocked) {
        if (auto it = service_names.find(behavior); it != service_names.end()) {
          runtime->setServing(it->second, !blocked);
        }
      }));
  std::string error;
  if (!p->runtime.startMetrics(o.metrics_listen, &error)) return absl::UnavailableError(error);
  if (absl::Status s = p->host->start(o.config, o.config_file); !s.ok()) {
    return absl::InvalidArgumentError("cannot start behaviors: " + std::string(s.message()));
  }
  p->host_started = true;
  if (!o.link_loss_action.empty() && p->host->find(o.link_loss_action) == nullptr) {
    return absl::InvalidArgumentError("--link-loss-action " + o.link_loss_action +
                                      " is not a behavior of " + o.system);
  }

  p->system_service =
      std::make_unique<BehaviorSystemService>(*p->host, p->gate, p->builder->serviceNames());
  grpc::ServerBuilder server_builder;
  std::vector<std::string> names = {v1::BehaviorSystem::service_full_name()};
  server_builder.RegisterService(p->system_service.get());
  for (auto& service : p->builder->services()) server_builder.RegisterService(service.get());
  for (const auto& [behavior, service] : p->builder->serviceNames()) names.push_back(service);
  if (!p->runtime.startServer(server_builder, o.listen, names, &error)) {
    p->host->stop();
    p->stopped = true;
    return absl::UnavailableError(error);
  }
  p->registration = startCoordinatorRegistration(o.coordinator, o.listen, p->runtime.grpcPort(),
                                                 *p->host, o.log_prefix, o.advertise);
  if (p->registration && o.link_loss_timeout > Duration::zero() && !o.link_loss_action.empty()) {
    CoordinatorRegistration* registration = p->registration.get();
    p->link_loss = std::make_unique<LinkLossWatch>(
        LinkLossOptions{.timeout = o.link_loss_timeout, .action = o.link_loss_action}, *p->clock,
        [registration] { return registration->registered(); }, *p->host, o.log_prefix);
  }
  if (p->follower) {
    Parts* parts = p.get();
    p->follower->start(
        [parts](TimePoint t) {
          if (!parts->host->caughtUp(t)) return false;
          // Work on the clock outside the ticks (lease renewals).
          if (!parts->clock->listenersCaughtUp(t)) return false;
          for (const auto& check : parts->builder->catchUpChecks()) {
            if (!check()) return false;
          }
          return true;
        },
        [parts] { return parts->host->idle(); });
  }
  return std::unique_ptr<BehaviorSystemProcess>(new BehaviorSystemProcess(std::move(p)));
}

BehaviorSystemProcess::BehaviorSystemProcess(std::unique_ptr<Parts> parts)
    : parts_(std::move(parts)) {}

BehaviorSystemProcess::~BehaviorSystemProcess() { shutdown(); }

int BehaviorSystemProcess::grpcPort() const { return parts_->runtime.grpcPort(); }
int BehaviorSystemProcess::metricsPort() const { return parts_->runtime.metricsPort(); }
const std::string& BehaviorSystemProcess::incarnation() const {
  return parts_->host->events().incarnation();
}

std::vector<std::string> BehaviorSystemProcess::behaviorNames() const {
  std::vector<std::string> names;
  for (const auto& b : parts_->host->behaviors()) names.push_back(b->name());
  return names;
}

bool BehaviorSystemProcess::writePortFile(const std::string& path, std::string* error) const {
  return parts_->runtime.writePortFile(path, error);
}

void BehaviorSystemProcess::shutdown() {
  Parts& p = *parts_;
  if (p.stopped) return;
  p.stopped = true;
  // Order matters: refuse new lifecycle calls, end activations (their
  // INTERRUPTED events go to subscribers), let the streams drain, then stop
  // serving.
  p.link_loss.reset();                 // unregistering is no link loss
  if (p.follower) p.follower->stop();  // leaves the simulator's barrier first
  p.gate.close();
  p.host->stop();
  // Unregistering names the last event's seq: the coordinator reads the
  // stream up to it, so the INTERRUPTED events above still reach it.
  if (p.registration) p.registration->stop();
  p.system_service->shutdownStreams();
  // Every call of ours has finished by now (the gate is closed, the host
  // stopped, the streams drained): the grace period only covers health and
  // reflection calls. Keep it short: gRPC waits for it in full while any
  // client merely keeps an idle connection open.
  p.runtime.shutdown(std::chrono::milliseconds(500));
}

int runBehaviorSystem(int argc, char** argv, const std::string& system_name,
                      const std::function<void(BehaviorSystemBuilder&)>& register_behaviors) {
  server_kit::ServerRuntime::blockShutdownSignals();
  const std::string program = system_name;
  server_kit::parseFlags(
      argc, argv,
      "behavior system " + system_name +
          ": hosts its behaviors as gRPC services (typed per behavior, plus "
          "behaviorlib.v1.BehaviorSystem); --help-config lists the keys of its --config file");
  if (absl::GetFlag(FLAGS_help_config)) {
    // The behaviors made without connections, only to read their
    // configuration types.
    AcceptGate gate;
    SystemContext context;
    context.system = system_name;
    context.robot_id = absl::GetFlag(FLAGS_robot_id);
    BehaviorSystemBuilder builder(gate, std::move(context));
    register_behaviors(builder);
    std::fputs(builder.documentConfiguration().c_str(), stdout);
    return 0;
  }
  BehaviorSystemOptions options;
  options.system = system_name;
  options.robot_id = absl::GetFlag(FLAGS_robot_id);
  options.listen = absl::GetFlag(FLAGS_listen);
  options.advertise = absl::GetFlag(FLAGS_advertise);
  if (const double s = absl::GetFlag(FLAGS_link_loss_timeout_s); !(s >= 0.0 && s <= 3600.0)) {
    server_kit::fatal(program,
                      "--link-loss-timeout-s must be within [0, 3600], got " + std::to_string(s));
    return 2;
  } else {
    options.link_loss_timeout =
        std::chrono::duration_cast<Duration>(std::chrono::duration<double>(s));
  }
  options.link_loss_action = absl::GetFlag(FLAGS_link_loss_action);
  options.metrics_listen = absl::GetFlag(FLAGS_metrics_listen);
  options.channel = absl::GetFlag(FLAGS_channel);
  options.clock = absl::GetFlag(FLAGS_clock);
  options.coordinator = absl::GetFlag(FLAGS_coordinator);
  options.flight_controller = absl::GetFlag(FLAGS_flight_controller);
  options.follow_time = absl::GetFlag(FLAGS_follow_time);
  if (const std::string path = absl::GetFlag(FLAGS_config); !path.empty()) {
    absl::StatusOr<std::string> text = server_kit::readFileCapped(path, kMaxConfigBytes);
    absl::Status loaded =
        text.ok() ? server_kit::loadYaml(*text, path, &options.config) : text.status();
    options.config_file = path;
    if (!loaded.ok()) {
      server_kit::fatal(program,
                        "cannot read --config " + path + ": " + std::string(loaded.message()));
      return 2;
    }
  }

  auto system = BehaviorSystemProcess::start(std::move(options), register_behaviors);
  if (!system.ok()) return server_kit::fatal(program, system.status());
  std::string error;
  if (!(*system)->writePortFile(absl::GetFlag(FLAGS_port_file), &error)) {
    (*system)->shutdown();
    return server_kit::fatal(program, error);
  }
  std::string hosted;
  for (const auto& name : (*system)->behaviorNames()) hosted += (hosted.empty() ? "" : ", ") + name;
  std::fprintf(stderr,
               "%s: robot %s, behaviors [%s], gRPC on port %d, metrics on port %d, clock %s, "
               "incarnation %s\n",
               program.c_str(), absl::GetFlag(FLAGS_robot_id).c_str(), hosted.c_str(),
               (*system)->grpcPort(), (*system)->metricsPort(), absl::GetFlag(FLAGS_clock).c_str(),
               (*system)->incarnation().c_str());

  const int sig = server_kit::ServerRuntime::waitForShutdownSignal();
  std::fprintf(stderr, "%s: signal %d, interrupting active behaviors and shutting down\n",
               program.c_str(), sig);
  (*system)->shutdown();
  return 0;
}

}  // namespace behaviorlib::server
