#include "behaviorlib/server/behavior_system_main.h"

#include <google/protobuf/descriptor.h>
#include <yaml-cpp/yaml.h>

#include <cstdio>
#include <iostream>

#include "absl/flags/flag.h"
#include "behaviorlib/behavior_host.h"
#include "behaviorlib/channel/channel_client.h"
#include "behaviorlib/channel/sim_clock.h"
#include "behaviorlib/clock.h"
#include "behaviorlib/server/behavior_metrics.h"
#include "behaviorlib/server/behavior_system_service.h"
#include "behaviorlib/server/coordinator_registration.h"
#include "behaviorlib/server/time_follower.h"
#include "behaviorlib/server_kit/flags.h"
#include "behaviorlib/server_kit/server_runtime.h"
#include "behaviorlib/v1/options.pb.h"

// The flags of every behavior-system process (runBehaviorSystem).
ABSL_FLAG(std::string, robot_id, "drone1", "robot this process serves");
ABSL_FLAG(std::string, listen, "127.0.0.1:50061",
          "gRPC address host:port (port 0 picks a free port)");
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

int runBehaviorSystem(int argc, char** argv, const std::string& system_name,
                      const std::function<void(BehaviorSystemBuilder&)>& register_behaviors) {
  ServerRuntime::blockShutdownSignals();
  const std::string program = system_name;

  parseFlags(argc, argv,
             "behavior system " + system_name +
                 ": hosts its behaviors as gRPC services (typed per behavior, plus "
                 "behaviorlib.v1.BehaviorSystem)");
  const std::string robot_id = absl::GetFlag(FLAGS_robot_id);
  const std::string listen = absl::GetFlag(FLAGS_listen);
  const std::string metrics_listen = absl::GetFlag(FLAGS_metrics_listen);
  const std::string port_file = absl::GetFlag(FLAGS_port_file);
  const std::string channel = absl::GetFlag(FLAGS_channel);
  const std::string clock_kind = absl::GetFlag(FLAGS_clock);
  const std::string config_path = absl::GetFlag(FLAGS_config);
  const std::string coordinator = absl::GetFlag(FLAGS_coordinator);
  const std::string flight_controller = absl::GetFlag(FLAGS_flight_controller);
  const std::string follow_time = absl::GetFlag(FLAGS_follow_time);
  if (!follow_time.empty() && clock_kind != "sim") {
    fatal(program, "--follow-time needs --clock sim (the grants set simulated time)");
    return 2;
  }

  YAML::Node config;
  if (!config_path.empty()) {
    try {
      config = YAML::LoadFile(config_path);
    } catch (const YAML::Exception& e) {
      fatal(program, "cannot read --config " + config_path + ": " + e.what());
      return 2;
    }
  }

  std::unique_ptr<channel::ChannelClient> channel_client;
  if (!channel.empty()) channel_client = std::make_unique<channel::ChannelClient>(channel);
  std::unique_ptr<Clock> clock;
  channel::SimClock* sim_clock = nullptr;
  if (clock_kind == "steady") {
    clock = std::make_unique<SteadyClock>();
  } else if (clock_kind == "sim") {
    if (!channel_client) {
      fatal(program, "--clock sim needs --channel (simulated time comes from its 'clock' topic)");
      return 2;
    }
    // Extrapolates the simulator's time line; runs on at the last time scale
    // when the simulator dies, so that staleness checks notice it.
    // Following the time grants, the grants are the time: the clock topic
    // would only repeat them.
    auto simulated = follow_time.empty() ? std::make_unique<channel::SimClock>(*channel_client)
                                         : std::make_unique<channel::SimClock>();
    sim_clock = simulated.get();
    clock = std::move(simulated);
  } else {
    fatal(program, "--clock must be 'steady' or 'sim', not '" + clock_kind + "'");
    return 2;
  }

  AcceptGate gate;
  SystemContext context;
  context.system = system_name;
  context.robot_id = robot_id;
  context.clock = clock.get();
  context.channel = channel_client.get();
  context.flight_controller = flight_controller;
  context.config = config;
  std::unique_ptr<BeliefClient> belief_client;
  if (!coordinator.empty()) {
    belief_client = std::make_unique<BeliefClient>(coordinator);
    context.beliefs = belief_client.get();
  }
  BehaviorSystemBuilder builder(gate, std::move(context));
  register_behaviors(builder);

  // Declared before the host, which calls its awaitTurn() until it stops.
  std::unique_ptr<TimeFollower> follower;
  if (!follow_time.empty()) {
    follower = std::make_unique<TimeFollower>(follow_time, system_name + "/" + robot_id, *sim_clock,
                                              channel_client.get());
  }
  BehaviorHostOptions host_options;
  host_options.robot_id = robot_id;
  host_options.system = system_name;
  if (follower) host_options.before_command = [&follower] { follower->awaitTurn(); };
  BehaviorHost host(host_options, *clock);
  for (auto& behavior : builder.behaviors()) host.add(std::move(behavior));

  ServerRuntime runtime;
  BehaviorMetrics metrics(runtime.registry(), robot_id, system_name);
  // A behavior blocked by the watchdog reports its typed service NOT_SERVING.
  const auto service_names = builder.serviceNames();
  host.setObserverFactory(
      metrics.observerFactory([&runtime, service_names](const std::string& behavior, bool blocked) {
        if (auto it = service_names.find(behavior); it != service_names.end()) {
          runtime.setServing(it->second, !blocked);
        }
      }));
  std::string error;
  if (!runtime.startMetrics(metrics_listen, &error)) return fatal(program, error);
  if (absl::Status s = host.start(config); !s.ok()) {
    return fatal(program, "cannot start behaviors: " + std::string(s.message()));
  }

  BehaviorSystemService system_service(host, gate, builder.serviceNames());
  grpc::ServerBuilder server_builder;
  std::vector<std::string> names = {v1::BehaviorSystem::service_full_name()};
  server_builder.RegisterService(&system_service);
  for (auto& service : builder.services()) server_builder.RegisterService(service.get());
  for (const auto& [behavior, service] : builder.serviceNames()) names.push_back(service);
  if (!runtime.startServer(server_builder, listen, names, &error)) {
    host.stop();
    return fatal(program, error);
  }
  if (!runtime.writePortFile(port_file, &error)) {
    runtime.shutdown(std::chrono::seconds(1));
    host.stop();
    return fatal(program, error);
  }
  std::string hosted;
  for (const auto& b : host.behaviors()) hosted += (hosted.empty() ? "" : ", ") + b->name();
  std::fprintf(stderr,
               "%s: robot %s, behaviors [%s], gRPC on port %d, metrics on port %d, clock %s, "
               "incarnation %s\n",
               program.c_str(), robot_id.c_str(), hosted.c_str(), runtime.grpcPort(),
               runtime.metricsPort(), clock_kind.c_str(), host.events().incarnation().c_str());
  auto registration =
      startCoordinatorRegistration(coordinator, listen, runtime.grpcPort(), host, program);
  if (follower) {
    follower->start(
        [&host, &builder, &clock](TimePoint t) {
          if (!host.caughtUp(t)) return false;
          // Work on the clock outside the ticks (lease renewals).
          if (!clock->listenersCaughtUp(t)) return false;
          for (const auto& check : builder.catchUpChecks()) {
            if (!check()) return false;
          }
          return true;
        },
        [&host] { return host.idle(); });
  }

  const int sig = ServerRuntime::waitForShutdownSignal();
  std::fprintf(stderr, "%s: signal %d, interrupting active behaviors and shutting down\n",
               program.c_str(), sig);
  // Order matters: refuse new lifecycle calls, end activations (their
  // INTERRUPTED events go to subscribers), let the streams drain, then stop
  // serving.
  if (follower) follower->stop();  // leaves the simulator's barrier first
  gate.close();
  host.stop();
  // Unregistering names the last event's seq: the coordinator reads the
  // stream up to it, so the INTERRUPTED events above still reach it.
  if (registration) registration->stop();
  system_service.shutdownStreams();
  // Every call of ours has finished by now (the gate is closed, the host
  // stopped, the streams drained): the grace period only covers health and
  // reflection calls. Keep it short: gRPC waits for it in full while any
  // client merely keeps an idle connection open.
  runtime.shutdown(std::chrono::milliseconds(500));
  return 0;
}

}  // namespace behaviorlib::server
