// coordinator: the fleet's coordinator (behaviorlib.v1.Coordinator). Behavior
// systems register with it (or are listed in --systems); it follows every
// system's events, serves them as one resumable stream, supervises the
// systems and routes lifecycle calls by robot and behavior.
//
//   coordinator --listen 127.0.0.1:50060 --systems systems.yaml
//       --catalog deploy/config/catalog.yaml --state-dir /var/lib/behaviorlib
//       --flight-controller drone1=127.0.0.1:50070 --channel 127.0.0.1:50051
//
// With --catalog, ActivateBehavior applies the catalog's plans; missions,
// belief memory and (with --flight-controller) the safety rules are served.
//
// Exits 0 after SIGTERM/SIGINT, 1 when it cannot bind or on an unknown flag
// or a malformed value, 2 on a value out of range or a bad --systems,
// --catalog or --state-dir.

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <memory>
#include <string>

#include "absl/flags/flag.h"
#include "behaviorlib/clock.h"
#include "behaviorlib/server_kit/flags.h"
#include "behaviorlib/server_kit/server_runtime.h"
#include "coordinator/process/coordinator_process.h"

namespace {
const behaviorlib::coordinator::CoordinatorOptions kDefaults;
}  // namespace

ABSL_FLAG(std::string, listen, kDefaults.listen,
          "gRPC address host:port (port 0 picks a free port)");
ABSL_FLAG(std::string, metrics_listen, kDefaults.metrics_listen,
          "Prometheus /metrics address host:port (port 0 picks a free port; empty disables)");
ABSL_FLAG(std::string, port_file, "", "write the bound ports here (grpc_port=, metrics_port=)");
ABSL_FLAG(std::string, state_dir, "",
          "directory of the coordinator's journal (belief memory and missions survive a "
          "restart); empty: belief memory in memory only");
ABSL_FLAG(std::string, systems, "",
          "YAML file of behavior systems to contact at start and whenever they come back: "
          "systems: [{robot_id, address}]");
ABSL_FLAG(double, grace_period_s, behaviorlib::toSeconds(kDefaults.grace_period),
          "wall seconds a system's health check must keep failing after its event stream broke "
          "before its active behaviors are finished with PROCESS_FAILURE");
ABSL_FLAG(double, heartbeat_interval_s, behaviorlib::toSeconds(kDefaults.heartbeat_interval),
          "how often registered systems are asked to send Heartbeat (wall seconds)");
ABSL_FLAG(int, event_buffer, static_cast<int>(kDefaults.event_buffer),
          "events retained for WatchEvents replay (since_seq), oldest evicted first");
ABSL_FLAG(std::string, catalog, "",
          "behavior catalog (YAML, see deploy/config/catalog.yaml): ActivateBehavior applies its "
          "plans (conflicts deactivated, requirements activated); empty: no rules");
ABSL_FLAG(std::string, flight_controller, "",
          "robot=host:port[,robot=host:port...]: each robot's FlightController, for "
          "EmergencyLand, Kill and the safety rules (motion controller failure or lease lost: "
          "hover then land; critical battery: land; geofence)");
ABSL_FLAG(std::string, channel, "",
          "data channel broker host:port, for the robots' pose estimates (geofence rule)");
ABSL_FLAG(std::string, geofence, "",
          "min_x,min_y,min_z,max_x,max_y,max_z in metres (world ENU) for robots whose mission "
          "has no geofence; empty: none");
ABSL_FLAG(double, critical_battery, kDefaults.critical_battery,
          "battery state of charge (0..1) under which a flying robot is landed");
ABSL_FLAG(double, hover_before_land_s, behaviorlib::toSeconds(kDefaults.hover_before_land),
          "seconds of the vehicles' time (--clock) a robot hovers before the safety policy "
          "lands it");
ABSL_FLAG(std::string, clock, kDefaults.clock,
          "the vehicles' time for the safety rules' hover before landing: 'steady' (the host's) "
          "or 'sim' (the simulator's, from --channel's 'clock' topic)");
ABSL_FLAG(int, workers, kDefaults.workers, "threads for blocking calls (plans, safety actions)");
ABSL_FLAG(double, resume_wait_s, behaviorlib::toSeconds(kDefaults.resume_wait),
          "after a restart, wall seconds a journaled mission waits for its robot's systems to "
          "register again before it is marked FAILED");

ABSL_FLAG(std::string, mission_dir, "",
          "directory whose mission files StartMission.file_path may name (no '..', no link "
          "out of it); empty: file paths are refused and clients send the mission's text");

ABSL_FLAG(int, max_beliefs, static_cast<int>(kDefaults.belief_limits.max_beliefs),
          "current beliefs belief memory may hold; a write of a new key beyond is "
          "RESOURCE_EXHAUSTED");
ABSL_FLAG(int, max_belief_bytes, static_cast<int>(kDefaults.belief_limits.max_value_bytes),
          "largest value of one belief, in bytes (serialized)");

ABSL_FLAG(int, max_vehicle_watches, static_cast<int>(kDefaults.max_vehicle_watches),
          "WatchVehicle streams open at once, each a data-channel subscription (one caller "
          "may hold a quarter of them)");
ABSL_FLAG(int, max_ended_missions, static_cast<int>(kDefaults.max_ended_missions),
          "ended missions kept for GetMission and ListMissions (the most recent)");
ABSL_FLAG(int64_t, max_ended_mission_age_s, kDefaults.max_ended_mission_age.count(),
          "ended missions older than this many seconds are forgotten");

ABSL_FLAG(int64_t, journal_compact_bytes, static_cast<int64_t>(kDefaults.journal_compact_bytes),
          "the journal is compacted online (beliefs, missions and registrations rewritten) once "
          "it grows past this many bytes");

int main(int argc, char** argv) {
  using behaviorlib::server_kit::fatal;
  using behaviorlib::server_kit::ServerRuntime;
  namespace coord = behaviorlib::coordinator;
  // Before any thread exists, so that every thread inherits the mask.
  ServerRuntime::blockShutdownSignals();
  const std::string program = "coordinator";
  behaviorlib::server_kit::parseFlags(
      argc, argv,
      "the coordinator (behaviorlib.v1.Coordinator): registry of behavior systems, one "
      "resumable event stream for the fleet, supervision, lifecycle calls by robot and "
      "behavior");
  auto usage_error = [&](const absl::Status& s) {
    fatal(program, std::string(s.message()));
    return 2;
  };

  coord::CoordinatorOptions options;
  options.listen = absl::GetFlag(FLAGS_listen);
  options.metrics_listen = absl::GetFlag(FLAGS_metrics_listen);
  options.state_dir = absl::GetFlag(FLAGS_state_dir);
  if (const std::string path = absl::GetFlag(FLAGS_systems); !path.empty()) {
    auto loaded = coord::loadSystemsConfig(path);
    if (!loaded.ok())
      return usage_error(
          absl::InvalidArgumentError("--systems: " + std::string(loaded.status().message())));
    options.systems = std::move(*loaded);
  }
  options.grace_period = behaviorlib::seconds(absl::GetFlag(FLAGS_grace_period_s));
  options.heartbeat_interval = behaviorlib::seconds(absl::GetFlag(FLAGS_heartbeat_interval_s));
  options.event_buffer = static_cast<size_t>(std::max(absl::GetFlag(FLAGS_event_buffer), 0));
  if (const std::string path = absl::GetFlag(FLAGS_catalog); !path.empty()) {
    auto loaded = coord::Catalog::load(path);
    if (!loaded.ok())
      return usage_error(
          absl::InvalidArgumentError("--catalog: " + std::string(loaded.status().message())));
    options.catalog = std::make_shared<const coord::Catalog>(std::move(*loaded));
  }
  auto controllers = coord::parseFlightControllers(absl::GetFlag(FLAGS_flight_controller));
  if (!controllers.ok()) return usage_error(controllers.status());
  options.flight_controllers = std::move(*controllers);
  options.channel_address = absl::GetFlag(FLAGS_channel);
  auto geofence = coord::parseGeofence(absl::GetFlag(FLAGS_geofence));
  if (!geofence.ok()) return usage_error(geofence.status());
  options.geofence = *geofence;
  options.critical_battery = absl::GetFlag(FLAGS_critical_battery);
  options.hover_before_land = behaviorlib::seconds(absl::GetFlag(FLAGS_hover_before_land_s));
  options.clock = absl::GetFlag(FLAGS_clock);
  options.workers = absl::GetFlag(FLAGS_workers);
  options.resume_wait = behaviorlib::seconds(absl::GetFlag(FLAGS_resume_wait_s));
  options.mission_dir = absl::GetFlag(FLAGS_mission_dir);
  options.journal_compact_bytes = static_cast<uint64_t>(absl::GetFlag(FLAGS_journal_compact_bytes));
  options.max_ended_missions = static_cast<size_t>(absl::GetFlag(FLAGS_max_ended_missions));
  options.max_vehicle_watches =
      static_cast<size_t>(std::max(0, absl::GetFlag(FLAGS_max_vehicle_watches)));
  options.max_ended_mission_age =
      std::chrono::seconds(absl::GetFlag(FLAGS_max_ended_mission_age_s));
  // Negative values become huge and are refused by validate().
  options.belief_limits.max_beliefs = static_cast<size_t>(absl::GetFlag(FLAGS_max_beliefs));
  options.belief_limits.max_value_bytes =
      static_cast<size_t>(absl::GetFlag(FLAGS_max_belief_bytes));
  const size_t configured = options.systems.size();
  const double grace_s = absl::GetFlag(FLAGS_grace_period_s);

  auto coordinator = coord::Coordinator::start(std::move(options));
  if (!coordinator.ok()) return fatal(program, coordinator.status());
  std::string error;
  if (!(*coordinator)->writePortFile(absl::GetFlag(FLAGS_port_file), &error)) {
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
