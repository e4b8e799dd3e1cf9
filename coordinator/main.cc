// coordinator: the fleet's coordinator (behaviorlib.v1.Coordinator). Behavior
// systems register with it (or are listed in --systems); it follows every
// system's events, serves them as one resumable stream, supervises the
// systems and routes lifecycle calls by robot and behavior.
//
//   coordinator --listen 127.0.0.1:50060 --systems deploy/config/systems.yaml
//
// Exits 0 after SIGTERM/SIGINT, 1 when it cannot bind, 2 on bad flags or a
// bad --systems file.

#include <grpcpp/grpcpp.h>

#include <chrono>
#include <cstdio>
#include <filesystem>
#include <memory>
#include <string>

#include "behaviorlib/server/flags.h"
#include "behaviorlib/server/server_runtime.h"
#include "coordinator/belief/belief_store.h"
#include "coordinator/durable/journal.h"
#include "coordinator/service/coordinator_metrics.h"
#include "coordinator/service/coordinator_service.h"
#include "coordinator/service/fleet_event_log.h"
#include "coordinator/service/registry.h"
#include "coordinator/service/systems_config.h"

int main(int argc, char** argv) {
  using behaviorlib::server::fatal;
  using behaviorlib::server::ServerRuntime;
  namespace coord = behaviorlib::coordinator;
  // Before any thread exists, so that every thread inherits the mask.
  ServerRuntime::blockShutdownSignals();
  const std::string program = "coordinator";

  std::string listen = "127.0.0.1:50060";
  std::string metrics_listen = "127.0.0.1:0";
  std::string port_file;
  std::string systems_path;
  std::string state_dir;
  double grace_s = 1.0;
  double heartbeat_s = 1.0;
  double event_buffer = 10000;
  behaviorlib::server::FlagSet flags(
      "the coordinator (behaviorlib.v1.Coordinator): registry of behavior systems, one "
      "resumable event stream for the fleet, supervision, lifecycle calls by robot and "
      "behavior");
  flags.add("listen", &listen, "gRPC address host:port (port 0 picks a free port)");
  flags.add("metrics-listen", &metrics_listen,
            "Prometheus /metrics address host:port (port 0 picks a free port; empty disables)");
  flags.add("port-file", &port_file, "write the bound ports here (grpc_port=, metrics_port=)");
  flags.add("state-dir", &state_dir,
            "directory of the coordinator's journal (belief memory survives a restart); empty: "
            "belief memory in memory only");
  flags.add("systems", &systems_path,
            "YAML file of behavior systems to contact at start and whenever they come back: "
            "systems: [{robot_id, address}]");
  flags.add("grace-period-s", &grace_s,
            "wall seconds a system's health check must keep failing after its event stream "
            "broke before its active behaviors are finished with PROCESS_FAILURE");
  flags.add("heartbeat-interval-s", &heartbeat_s,
            "how often registered systems are asked to send Heartbeat (wall seconds)");
  flags.add("event-buffer", &event_buffer,
            "events retained for WatchEvents replay (since_seq), oldest evicted first");
  int exit_code = 0;
  if (!flags.parse(argc, argv, &exit_code)) return exit_code;
  if (!(grace_s >= 0.05 && grace_s <= 600)) {
    fatal(program, "--grace-period-s must be within [0.05, 600]");
    return 2;
  }
  if (!(heartbeat_s >= 0.05 && heartbeat_s <= 600)) {
    fatal(program, "--heartbeat-interval-s must be within [0.05, 600]");
    return 2;
  }
  if (!(event_buffer >= 1 && event_buffer <= 1e7)) {
    fatal(program, "--event-buffer must be within [1, 10000000]");
    return 2;
  }
  std::vector<coord::ConfiguredSystem> configured;
  if (!systems_path.empty()) {
    auto loaded = coord::loadSystemsConfig(systems_path);
    if (!loaded.ok()) {
      fatal(program, "--systems: " + std::string(loaded.status().message()));
      return 2;
    }
    configured = std::move(*loaded);
  }

  ServerRuntime runtime;
  std::string error;
  if (!runtime.startMetrics(metrics_listen, &error)) return fatal(program, error);

  coord::CoordinatorMetrics metrics(runtime.registry());
  coord::FleetEventLogOptions log_options;
  log_options.capacity = static_cast<size_t>(event_buffer);
  coord::FleetEventLog log(log_options);
  coord::RegistryOptions registry_options;
  registry_options.link.grace =
      std::chrono::duration_cast<std::chrono::nanoseconds>(std::chrono::duration<double>(grace_s));
  coord::Registry registry(log, metrics, registry_options);
  // Belief memory, restored from the journal.
  std::unique_ptr<coord::Journal> journal;
  coord::BeliefStore beliefs_restore;  // replay target before the journal is attached
  if (!state_dir.empty()) {
    std::error_code ec;
    std::filesystem::create_directories(state_dir, ec);
    auto opened = coord::Journal::open(state_dir + "/coordinator.journal",
                                       [&](const behaviorlib::v1::JournalRecord& record) {
                                         if (record.has_belief())
                                           beliefs_restore.restore(record.belief());
                                       });
    if (!opened.ok()) {
      fatal(program, "--state-dir: " + std::string(opened.status().message()));
      return 2;
    }
    journal = std::move(*opened);
  } else {
    std::fprintf(stderr, "%s: no --state-dir: belief memory is lost when the coordinator stops\n",
                 program.c_str());
  }
  coord::BeliefStore beliefs(journal.get());
  for (const auto& belief : beliefs_restore.snapshot()) beliefs.restore(belief);
  coord::CoordinatorServiceOptions service_options;
  service_options.beliefs = &beliefs;
  service_options.heartbeat_interval =
      std::chrono::milliseconds(static_cast<int64_t>(heartbeat_s * 1000.0));
  coord::CoordinatorService service(registry, log, metrics, service_options);

  grpc::ServerBuilder builder;
  builder.RegisterService(&service);
  if (!runtime.startServer(builder, listen, {behaviorlib::v1::Coordinator::service_full_name()},
                           &error)) {
    return fatal(program, error);
  }
  if (!runtime.writePortFile(port_file, &error)) {
    runtime.shutdown(std::chrono::milliseconds(0));
    return fatal(program, error);
  }
  for (const auto& system : configured) registry.addConfigured(system);
  std::fprintf(stderr,
               "%s: serving behaviorlib.v1.Coordinator on port %d (metrics port %d), "
               "incarnation %s, %zu configured systems, grace period %.2f s\n",
               program.c_str(), runtime.grpcPort(), runtime.metricsPort(),
               log.incarnation().c_str(), configured.size(), grace_s);

  const int sig = ServerRuntime::waitForShutdownSignal();
  std::fprintf(stderr, "%s: signal %d, shutting down\n", program.c_str(), sig);
  // Subscribers first (they get what is queued, then UNAVAILABLE with their
  // resume point), then the links to the systems, then the server: in-flight
  // calls forwarded to systems are cancelled along with their server call.
  service.shutdownStreams();
  registry.stop();
  runtime.shutdown(std::chrono::milliseconds(1000));
  return 0;
}
