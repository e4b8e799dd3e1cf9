// coordinator: the fleet's coordinator (behaviorlib.v1.Coordinator). Behavior
// systems register with it (or are listed in --systems); it follows every
// system's events, serves them as one resumable stream, supervises the
// systems and routes lifecycle calls by robot and behavior.
//
//   coordinator --listen 127.0.0.1:50060 --systems deploy/config/systems.yaml
//       --catalog deploy/config/catalog.yaml --state-dir /var/lib/behaviorlib
//       --flight-controller drone1=127.0.0.1:50070 --channel 127.0.0.1:50051
//
// With --catalog, ActivateBehavior applies the catalog's plans; missions,
// belief memory and (with --flight-controller) the safety rules are served.
//
// Exits 0 after SIGTERM/SIGINT, 1 when it cannot bind, 2 on bad flags or a
// bad --systems file.

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "behaviorlib/clock.h"
#include "behaviorlib/server_kit/flags.h"
#include "behaviorlib/server_kit/server_runtime.h"
#include "coordinator/process/coordinator_process.h"

namespace {

// "a,b,,c" -> {"a", "b", "c"}.
std::vector<std::string> splitList(const std::string& text) {
  std::vector<std::string> out;
  size_t start = 0;
  while (start <= text.size()) {
    const size_t comma = std::min(text.find(',', start), text.size());
    if (comma > start) out.push_back(text.substr(start, comma - start));
    start = comma + 1;
  }
  return out;
}

}  // namespace

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
  int event_buffer = 10000;
  std::string catalog_path;
  std::string flight_controllers;
  std::string channel_address;
  std::string geofence_text;
  double critical_battery = 0.10;
  double hover_before_land_s = 1.0;
  int workers = 4;
  double resume_wait_s = 60;
  behaviorlib::server::FlagSet flags(
      "the coordinator (behaviorlib.v1.Coordinator): registry of behavior systems, one "
      "resumable event stream for the fleet, supervision, lifecycle calls by robot and "
      "behavior");
  flags.add("listen", &listen, "gRPC address host:port (port 0 picks a free port)");
  flags.add("metrics-listen", &metrics_listen,
            "Prometheus /metrics address host:port (port 0 picks a free port; empty disables)");
  flags.add("port-file", &port_file, "write the bound ports here (grpc_port=, metrics_port=)");
  flags.add("state-dir", &state_dir,
            "directory of the coordinator's journal (belief memory and missions survive a "
            "restart); empty: "
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
  flags.add("catalog", &catalog_path,
            "behavior catalog (YAML, see deploy/config/catalog.yaml): ActivateBehavior applies "
            "its plans (conflicts deactivated, requirements activated); empty: no rules");
  flags.add("flight-controller", &flight_controllers,
            "robot=host:port[,robot=host:port...]: each robot's FlightController, for "
            "EmergencyLand, Kill and the safety rules (motion controller failure or lease lost: "
            "hover then land; critical battery: land; geofence)");
  flags.add("channel", &channel_address,
            "data channel broker host:port, for the robots' pose estimates (geofence rule)");
  flags.add("geofence", &geofence_text,
            "min_x,min_y,min_z,max_x,max_y,max_z in metres (world ENU) for robots whose mission "
            "has no geofence; empty: none");
  flags.add("critical-battery", &critical_battery,
            "battery state of charge (0..1) under which a flying robot is landed");
  flags.add("hover-before-land-s", &hover_before_land_s,
            "wall seconds a robot hovers before the safety policy lands it");
  flags.add("workers", &workers, "threads for blocking calls (plans, safety actions)");
  flags.add("resume-wait-s", &resume_wait_s,
            "after a restart, wall seconds a journaled mission waits for its robot's systems to "
            "register again before it is marked FAILED");
  int exit_code = 0;
  if (!flags.parse(argc, argv, &exit_code)) return exit_code;
  if (!(critical_battery >= 0 && critical_battery <= 1)) {
    fatal(program, "--critical-battery must be within [0, 1]");
    return 2;
  }
  if (!(hover_before_land_s >= 0 && hover_before_land_s <= 60)) {
    fatal(program, "--hover-before-land-s must be within [0, 60]");
    return 2;
  }
  if (!(workers >= 1 && workers <= 64)) {
    fatal(program, "--workers must be within [1, 64]");
    return 2;
  }
  if (!(resume_wait_s >= 0 && resume_wait_s <= 3600)) {
    fatal(program, "--resume-wait-s must be within [0, 3600]");
    return 2;
  }
  std::vector<std::pair<std::string, std::string>> robot_fcs;
  for (const std::string& item : splitList(flight_controllers)) {
    const auto eq = item.find('=');
    if (eq == std::string::npos || eq == 0 || eq + 1 == item.size()) {
      fatal(program, "--flight-controller: '" + item +
                         "' is not robot=host:port (e.g. drone1=127.0.0.1:50070)");
      return 2;
    }
    robot_fcs.emplace_back(item.substr(0, eq), item.substr(eq + 1));
  }
  std::optional<coord::Geofence> geofence;
  if (!geofence_text.empty()) {
    std::vector<std::string> parts = splitList(geofence_text);
    coord::Geofence fence;
    bool ok = parts.size() == 6;
    for (size_t i = 0; ok && i < 6; ++i) {
      char* end = nullptr;
      const double v = std::strtod(parts[i].c_str(), &end);
      ok = end != parts[i].c_str() && *end == '\0' && std::isfinite(v);
      (i < 3 ? fence.min_m[i] : fence.max_m[i - 3]) = v;
    }
    for (size_t i = 0; ok && i < 3; ++i) ok = fence.min_m[i] < fence.max_m[i];
    if (!ok) {
      fatal(program,
            "--geofence: expected min_x,min_y,min_z,max_x,max_y,max_z in metres with "
            "each min below its max, got '" +
                geofence_text + "'");
      return 2;
    }
    geofence = fence;
  }
  std::shared_ptr<const coord::Catalog> catalog;
  if (!catalog_path.empty()) {
    auto loaded = coord::Catalog::load(catalog_path);
    if (!loaded.ok()) {
      fatal(program, "--catalog: " + std::string(loaded.status().message()));
      return 2;
    }
    catalog = std::make_shared<const coord::Catalog>(std::move(*loaded));
  }
  if (!(grace_s >= 0.05 && grace_s <= 600)) {
    fatal(program, "--grace-period-s must be within [0.05, 600]");
    return 2;
  }
  if (!(heartbeat_s >= 0.05 && heartbeat_s <= 600)) {
    fatal(program, "--heartbeat-interval-s must be within [0.05, 600]");
    return 2;
  }
  if (!(event_buffer >= 1 && event_buffer <= 10000000)) {
    fatal(program, "--event-buffer must be within [1, 10000000]");
    return 2;
  }
  coord::CoordinatorOptions options;
  options.listen = listen;
  options.metrics_listen = metrics_listen;
  if (!systems_path.empty()) {
    auto loaded = coord::loadSystemsConfig(systems_path);
    if (!loaded.ok()) {
      fatal(program, "--systems: " + std::string(loaded.status().message()));
      return 2;
    }
    options.systems = std::move(*loaded);
  }
  options.state_dir = state_dir;
  options.grace_period = behaviorlib::seconds(grace_s);
  options.heartbeat_interval = behaviorlib::seconds(heartbeat_s);
  options.event_buffer = static_cast<size_t>(event_buffer);
  options.catalog = catalog;
  options.flight_controllers = robot_fcs;
  options.channel_address = channel_address;
  options.geofence = geofence;
  options.critical_battery = critical_battery;
  options.hover_before_land = behaviorlib::seconds(hover_before_land_s);
  options.workers = workers;
  options.resume_wait = behaviorlib::seconds(resume_wait_s);
  const size_t configured = options.systems.size();

  auto coordinator = coord::Coordinator::start(std::move(options));
  if (!coordinator.ok()) {
    fatal(program, std::string(coordinator.status().message()));
    return coordinator.status().code() == absl::StatusCode::kInvalidArgument ? 2 : 1;
  }
  std::string error;
  if (!(*coordinator)->writePortFile(port_file, &error)) {
    (*coordinator)->shutdown();
    return fatal(program, error);
  }
  std::fprintf(stderr,
               "%s: serving behaviorlib.v1.Coordinator on port %d (metrics port %d), "
               "incarnation %s, %zu configured systems, grace period %.2f s\n",
               program.c_str(), (*coordinator)->grpcPort(), (*coordinator)->metricsPort(),
               (*coordinator)->incarnation().c_str(), configured, grace_s);

  const int sig = ServerRuntime::waitForShutdownSignal();
  std::fprintf(stderr, "%s: signal %d, shutting down\n", program.c_str(), sig);
  (*coordinator)->shutdown();
  return 0;
}
