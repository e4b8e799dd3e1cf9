#pragma once

// The coordinator as a class: its parts (event log, registry, journal,
// belief memory, fleet control, missions, safety, the gRPC service) wired
// together and serving on one port. main() parses the flags into
// CoordinatorOptions and runs one until a shutdown signal; a test builds one
// in-process where starting a process would add nothing.
//
//   CoordinatorOptions options;
//   options.listen = "127.0.0.1:0";
//   auto coordinator = Coordinator::start(std::move(options));
//   if (!coordinator.ok()) ...;
//   (*coordinator)->grpcPort();
//   (*coordinator)->shutdown();   // also done by the destructor

#include <chrono>
#include <cstddef>
#include <memory>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "coordinator/catalog/catalog.h"
#include "coordinator/control/mission_manager.h"
#include "coordinator/registry/systems_config.h"

namespace behaviorlib::coordinator {

/// A coordinator's settings: the command line, parsed and checked.
struct CoordinatorOptions {
  /// gRPC address host:port (port 0 picks a free port).
  std::string listen = "127.0.0.1:50060";
  /// Prometheus /metrics address (port 0 picks one; empty: no metrics).
  std::string metrics_listen = "127.0.0.1:0";
  /// Systems to follow from the start (besides those that register).
  std::vector<ConfiguredSystem> systems;
  /// Directory of the journal (belief memory, missions, registrations);
  /// empty: nothing survives a restart.
  std::string state_dir;
  /// How long a system may be unreachable before its behaviors end
  /// PROCESS_FAILURE.
  std::chrono::nanoseconds grace_period = std::chrono::seconds(1);
  /// Heartbeats the systems are asked for.
  std::chrono::nanoseconds heartbeat_interval = std::chrono::seconds(1);
  /// Events retained for WatchEvents replay.
  size_t event_buffer = 10000;
  /// The behavior catalog whose plans ActivateBehavior applies; null: none.
  std::shared_ptr<const Catalog> catalog;
  /// robot id -> FlightController address, for EmergencyLand, Kill and the
  /// safety rules.
  std::vector<std::pair<std::string, std::string>> flight_controllers;
  /// The data channel, for the safety rules' battery and pose watch.
  std::string channel_address;
  /// Geofence for robots whose mission has none.
  std::optional<Geofence> geofence;
  /// Battery ratio at or below which a flying robot is landed.
  double critical_battery = 0.10;
  /// Hover before a safety landing, in the vehicles' time (`clock`).
  std::chrono::nanoseconds hover_before_land = std::chrono::seconds(1);
  /// The vehicles' time for the safety rules: "steady" (the host's) or
  /// "sim" (the simulator's, from the `clock` topic of `channel_address`).
  std::string clock = "steady";
  /// Threads for blocking calls (plans, safety actions).
  int workers = 4;
  /// After a restart, how long a journaled mission waits for its robot's
  /// systems before it is marked FAILED.
  std::chrono::nanoseconds resume_wait = std::chrono::seconds(60);
  /// Directory that StartMission.file_path may name files in; empty: no
  /// path is accepted (clients send the mission's text).
  std::string mission_dir;
  /// What belief memory may hold (RESOURCE_EXHAUSTED beyond).
  BeliefLimits belief_limits;
  /// The journal is compacted online once it grows past this many bytes.
  uint64_t journal_compact_bytes = 64ull << 20;
  /// Ended missions kept: the most recent this many, none older than the age.
  size_t max_ended_missions = 1000;
  /// WatchVehicle streams open at once (each a broker subscription); one
  /// caller may hold a quarter of them.
  size_t max_vehicle_watches = 64;
  std::chrono::seconds max_ended_mission_age{7 * 24 * 3600};

  /// INVALID_ARGUMENT naming the flag of the first setting out of its range.
  absl::Status validate() const;
};

/// --flight-controller: "robot=host:port[,robot=host:port...]".
absl::StatusOr<std::vector<std::pair<std::string, std::string>>> parseFlightControllers(
    const std::string& text);
/// --geofence: "min_x,min_y,min_z,max_x,max_y,max_z" in metres, each min
/// below its max; empty: none.
absl::StatusOr<std::optional<Geofence>> parseGeofence(const std::string& text);

class Coordinator {
 public:
  /// Validates the options (INVALID_ARGUMENT), opens and compacts the
  /// journal (INVALID_ARGUMENT naming it when it cannot), restores beliefs, missions and
  /// registrations, binds the ports (UNAVAILABLE when it cannot) and serves.
  static absl::StatusOr<std::unique_ptr<Coordinator>> start(CoordinatorOptions options);
  /// shutdown(), if not done yet.
  ~Coordinator();
  Coordinator(const Coordinator&) = delete;
  Coordinator& operator=(const Coordinator&) = delete;

  int grpcPort() const;
  int metricsPort() const;
  /// The event log's incarnation (changes with every start).
  const std::string& incarnation() const;
  /// Writes grpc_port= and metrics_port= lines to `path`.
  bool writePortFile(const std::string& path, std::string* error) const;

  /// Ends the event streams (subscribers get what is queued, then
  /// UNAVAILABLE with their resume point), then the safety rules, missions
  /// (running ones stay RUNNING in the journal), fleet control, the links to
  /// the systems, and the server.
  void shutdown();

 private:
  struct Parts;
  explicit Coordinator(std::unique_ptr<Parts> parts);
  std::unique_ptr<Parts> parts_;
};

}  // namespace behaviorlib::coordinator
