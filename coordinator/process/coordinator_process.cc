#include "coordinator/process/coordinator_process.h"

#include <grpcpp/grpcpp.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <map>
#include <set>
#include <sstream>
#include <thread>

#include "absl/status/status.h"
#include "absl/synchronization/mutex.h"
#include "behaviorlib/channel/channel_client.h"
#include "behaviorlib/channel/sim_clock.h"
#include "behaviorlib/clock.h"
#include "behaviorlib/flight_common/topics.h"
#include "behaviorlib/server_kit/server_runtime.h"
#include "coordinator/api/blocking_pool.h"
#include "coordinator/api/coordinator_service.h"
#include "coordinator/belief/belief_store.h"
#include "coordinator/control/fleet_control.h"
#include "coordinator/durable/journal.h"
#include "coordinator/events/fleet_event_log.h"
#include "coordinator/metrics/coordinator_metrics.h"
#include "coordinator/process/replayed_state.h"
#include "coordinator/registry/registry.h"
#include "coordinator/safety/safety.h"
#include "coordinator/telemetry/vehicle_telemetry.h"

namespace behaviorlib::coordinator {

namespace {

// The vehicles' latest samples, as the missions' `when:` conditions read
// them: the broker's newest sample of each topic, asked when a condition is
// evaluated (no subscription stays open).
class ChannelVehicleReader final : public VehicleReader {
 public:
  explicit ChannelVehicleReader(channel::ChannelClient& channel) : channel_(channel) {}
  absl::StatusOr<v1::FlightStatus> flightStatus(const std::string& robot) override {
    return latest<v1::FlightStatus>(flight::flightStateTopic(robot));
  }
  absl::StatusOr<v1::PoseStamped> poseEstimate(const std::string& robot) override {
    return latest<v1::PoseStamped>(flight::poseEstimateTopic(robot));
  }

 private:
  template <class T>
  absl::StatusOr<T> latest(const std::string& topic) {
    absl::StatusOr<v1::SubscribeResponse> sample =
        channel_.getLatest(topic, std::chrono::milliseconds(500));
    if (!sample.ok()) return sample.status();
    T message;
    if (!sample->sample().UnpackTo(&message)) {
      return absl::InvalidArgumentError(topic + " does not carry " +
                                        std::string(T::descriptor()->full_name()));
    }
    return message;
  }

  channel::ChannelClient& channel_;
};

template <class D>
std::chrono::milliseconds millis(D d) {
  return std::chrono::duration_cast<std::chrono::milliseconds>(d);
}

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

absl::Status CoordinatorOptions::validate() const {
  struct Range {
    const char* flag;
    double value, min, max;
  };
  const Range ranges[] = {
      {"--critical-battery", critical_battery, 0, 1},
      {"--hover-before-land-s", behaviorlib::toSeconds(hover_before_land), 0, 60},
      {"--workers", static_cast<double>(workers), 1, 64},
      {"--resume-wait-s", behaviorlib::toSeconds(resume_wait), 0, 3600},
      {"--grace-period-s", behaviorlib::toSeconds(grace_period), 0.05, 600},
      {"--heartbeat-interval-s", behaviorlib::toSeconds(heartbeat_interval), 0.05, 600},
      {"--event-buffer", static_cast<double>(event_buffer), 1, 10000000},
      {"--max-beliefs", static_cast<double>(belief_limits.max_beliefs), 1, 10000000},
      {"--journal-compact-bytes", static_cast<double>(journal_compact_bytes), 4096,
       static_cast<double>(1ull << 40)},
      {"--max-vehicle-watches", static_cast<double>(max_vehicle_watches), 1, 10000},
      {"--max-ended-missions", static_cast<double>(max_ended_missions), 0, 1000000},
      {"--max-ended-mission-age-s", static_cast<double>(max_ended_mission_age.count()), 1,
       10 * 365 * 24 * 3600.0},
      {"--max-belief-bytes", static_cast<double>(belief_limits.max_value_bytes), 16, 4 << 20},
  };
  for (const Range& r : ranges) {
    if (!(r.value >= r.min && r.value <= r.max)) {
      std::ostringstream out;
      out << r.flag << " must be within [" << r.min << ", " << r.max << "], got " << r.value;
      return absl::InvalidArgumentError(out.str());
    }
  }
  if (clock != "steady" && clock != "sim") {
    return absl::InvalidArgumentError("--clock must be 'steady' or 'sim', got '" + clock + "'");
  }
  if (clock == "sim" && channel_address.empty()) {
    return absl::InvalidArgumentError(
        "--clock sim needs --channel (simulated time comes from its 'clock' topic)");
  }
  return absl::OkStatus();
}

absl::StatusOr<std::vector<std::pair<std::string, std::string>>> parseFlightControllers(
    const std::string& text) {
  std::vector<std::pair<std::string, std::string>> out;
  for (const std::string& item : splitList(text)) {
    const auto eq = item.find('=');
    if (eq == std::string::npos || eq == 0 || eq + 1 == item.size()) {
      return absl::InvalidArgumentError("--flight-controller: '" + item +
                                        "' is not robot=host:port (e.g. drone1=127.0.0.1:50070)");
    }
    out.emplace_back(item.substr(0, eq), item.substr(eq + 1));
  }
  return out;
}

absl::StatusOr<std::optional<Geofence>> parseGeofence(const std::string& text) {
  if (text.empty()) return std::optional<Geofence>();
  const std::vector<std::string> parts = splitList(text);
  Geofence fence;
  bool ok = parts.size() == 6;
  for (size_t i = 0; ok && i < 6; ++i) {
    char* end = nullptr;
    const double v = std::strtod(parts[i].c_str(), &end);
    ok = end != parts[i].c_str() && *end == '\0' && std::isfinite(v);
    (i < 3 ? fence.min_m[i] : fence.max_m[i - 3]) = v;
  }
  for (size_t i = 0; ok && i < 3; ++i) ok = fence.min_m[i] < fence.max_m[i];
  if (!ok) {
    return absl::InvalidArgumentError(
        "--geofence: expected min_x,min_y,min_z,max_x,max_y,max_z in metres with each min "
        "below its max, got '" +
        text + "'");
  }
  return std::optional<Geofence>(fence);
}

// Declared in construction order: destroyed in reverse, after shutdown().
struct Coordinator::Parts {
  server_kit::ServerRuntime runtime;
  std::unique_ptr<CoordinatorMetrics> metrics;
  std::unique_ptr<FleetEventLog> log;
  // Registrations are journaled once the journal is open, so that a
  // restarted coordinator knows where its systems are.
  std::atomic<Journal*> registry_journal{nullptr};
  std::unique_ptr<Registry> registry;
  std::unique_ptr<Journal> journal;
  std::unique_ptr<BeliefStore> beliefs;
  std::unique_ptr<BlockingPool> pool;
  std::unique_ptr<FleetControl> fleet;
  // The vehicles' simulated time (--clock sim), for the safety rules and the
  // missions' waits (declared before the missions: their runners read it
  // until they stop).
  std::unique_ptr<channel::SimClock> vehicle_clock;
  // The data channel (--channel), read by the missions' `when:` conditions
  // and the telemetry calls.
  std::unique_ptr<channel::ChannelClient> vehicle_channel;
  std::unique_ptr<ChannelVehicleReader> vehicle_reader;
  // GetVehicleSample and WatchVehicle (--channel).
  std::unique_ptr<VehicleTelemetry> telemetry;
  std::unique_ptr<MissionManager> missions;
  std::unique_ptr<SafetyController> safety;
  std::unique_ptr<CoordinatorService> service;
  bool stopped = false;

  // The current registrations, for the journal's snapshots.
  absl::Mutex systems_mutex;
  std::map<std::pair<std::string, std::string>, durable::v1::SystemRecord> systems
      ABSL_GUARDED_BY(systems_mutex);
  // Online compaction: a thread that compacts the journal past a size.
  absl::Mutex compactor_mutex;
  bool compactor_stop ABSL_GUARDED_BY(compactor_mutex) = false;
  std::thread compactor;

  /// What the journal must hold: every mission, registration and belief.
  std::vector<durable::v1::JournalRecord> snapshot() {
    std::vector<durable::v1::JournalRecord> out = missions->snapshot();
    {
      absl::MutexLock lock(&systems_mutex);
      for (const auto& [key, system] : systems) *out.emplace_back().mutable_system() = system;
    }
    for (const auto& belief : beliefs->snapshot()) *out.emplace_back().mutable_belief() = belief;
    return out;
  }
  // A start() that fails after the compactor began still stops it.
  ~Parts() { stopCompactor(); }

  void stopCompactor() {
    {
      absl::MutexLock lock(&compactor_mutex);
      compactor_stop = true;
    }
    if (compactor.joinable()) compactor.join();
  }
};

absl::StatusOr<std::unique_ptr<Coordinator>> Coordinator::start(CoordinatorOptions options) {
  if (absl::Status s = options.validate(); !s.ok()) return s;
  auto p = std::make_unique<Parts>();
  std::string error;
  if (!p->runtime.startMetrics(options.metrics_listen, &error)) {
    return absl::UnavailableError(error);
  }
  p->metrics = std::make_unique<CoordinatorMetrics>(p->runtime.registry());
  FleetEventLogOptions log_options;
  log_options.capacity = options.event_buffer;
  p->log = std::make_unique<FleetEventLog>(log_options);

  RegistryOptions registry_options;
  Parts* parts = p.get();
  registry_options.on_membership = [parts](const durable::v1::SystemRecord& r) {
    {
      absl::MutexLock lock(&parts->systems_mutex);
      const auto key = std::make_pair(r.robot_id(), r.system());
      if (r.unregistered()) {
        parts->systems.erase(key);
      } else {
        parts->systems[key] = r;
      }
    }
    Journal* j = parts->registry_journal.load();
    if (j == nullptr) return;
    durable::v1::JournalRecord record;
    *record.mutable_system() = r;
    if (auto s = j->append(record); !s.ok()) {
      std::fprintf(stderr, "coordinator: cannot journal the registration of %s/%s: %s\n",
                   r.robot_id().c_str(), r.system().c_str(), std::string(s.message()).c_str());
    }
  };
  registry_options.link.grace = options.grace_period;
  // Missed heartbeats make the links probe a system whose stream stays open.
  registry_options.link.heartbeat_interval = millis(options.heartbeat_interval);
  p->registry = std::make_unique<Registry>(*p->log, *p->metrics, registry_options);

  // Belief memory, missions and registrations, restored from the journal.
  ReplayedState replayed;  // replay target before the journal is attached
  if (!options.state_dir.empty()) {
    std::error_code ec;
    std::filesystem::create_directories(options.state_dir, ec);
    auto opened =
        Journal::open(options.state_dir + "/coordinator.journal",
                      [&](const durable::v1::JournalRecord& record) { replayed.apply(record); });
    if (!opened.ok()) {
      return absl::InvalidArgumentError("--state-dir: " + std::string(opened.status().message()));
    }
    p->journal = std::move(*opened);
  } else {
    std::fprintf(stderr,
                 "coordinator: no --state-dir: belief memory is lost when the coordinator stops\n");
  }
  p->beliefs = std::make_unique<BeliefStore>(p->journal.get(), options.belief_limits);
  for (const auto& belief : replayed.beliefs.snapshot()) p->beliefs->restore(belief);
  p->pool = std::make_unique<BlockingPool>(options.workers);
  p->fleet = std::make_unique<FleetControl>(*p->registry, *p->log, options.catalog);
  MissionManagerOptions mission_options;
  mission_options.resume_wait = millis(options.resume_wait);
  mission_options.max_ended_missions = options.max_ended_missions;
  mission_options.max_ended_age = options.max_ended_mission_age;
  auto mission_files = server_kit::ConfinedDirectory::open("mission files", options.mission_dir,
                                                           mission_options.max_mission_bytes);
  if (!mission_files.ok()) return mission_files.status();
  mission_options.mission_files = std::move(*mission_files);
  mission_options.metrics = p->metrics.get();
  if (options.clock == "sim") {
    // The vehicles' time: the missions' waits and the safety policy's.
    p->vehicle_clock = std::make_unique<channel::SimClock>(options.channel_address);
    mission_options.clock = p->vehicle_clock.get();
  }
  if (!options.channel_address.empty()) {
    p->vehicle_channel = std::make_unique<channel::ChannelClient>(options.channel_address);
    p->vehicle_reader = std::make_unique<ChannelVehicleReader>(*p->vehicle_channel);
    mission_options.vehicles = p->vehicle_reader.get();
    // A robot is known when one of its systems is registered or a
    // --flight-controller names it.
    std::set<std::string> controlled;
    for (const auto& entry : options.flight_controllers) controlled.insert(entry.first);
    VehicleTelemetryLimits limits;
    limits.max_watches = options.max_vehicle_watches;
    limits.max_watches_per_caller = std::max<size_t>(1, options.max_vehicle_watches / 4);
    p->telemetry = std::make_unique<VehicleTelemetry>(
        *p->vehicle_channel, p->vehicle_clock.get(),
        [registry = p->registry.get(), controlled](const std::string& robot) {
          return controlled.count(robot) != 0 || !registry->robotBehaviors(robot).empty();
        },
        limits,
        [gauge = &p->metrics->vehicle_watches](size_t open) {
          gauge->Set(static_cast<double>(open));
        });
  }
  p->missions = std::make_unique<MissionManager>(*p->fleet, *p->registry, *p->beliefs,
                                                 p->journal.get(), mission_options);
  for (const auto& status : replayed.missions) p->missions->restore(status);
  {
    absl::MutexLock lock(&p->systems_mutex);
    for (const auto& [key, system] : replayed.systems) p->systems.emplace(key, system);
  }
  if (p->journal) {
    // Start from a compact journal: the current beliefs, missions and systems.
    if (auto s = p->journal->compact(p->snapshot()); !s.ok()) {
      return absl::InvalidArgumentError("--state-dir: cannot compact the journal: " +
                                        std::string(s.message()));
    }
    // Then compact it whenever it has grown past the threshold.
    p->compactor = std::thread([parts, threshold = options.journal_compact_bytes] {
      for (;;) {
        {
          absl::MutexLock lock(&parts->compactor_mutex);
          parts->compactor_mutex.AwaitWithTimeout(
              absl::Condition(
                  +[](bool* stop) { return *stop; }, &parts->compactor_stop),
              absl::Seconds(1));
          if (parts->compactor_stop) return;
        }
        if (parts->journal->sizeBytes() <= threshold) continue;
        if (auto s = parts->journal->compactOnline([parts] { return parts->snapshot(); });
            !s.ok()) {
          std::fprintf(stderr, "coordinator: cannot compact the journal: %s\n",
                       std::string(s.message()).c_str());
        }
      }
    });
  }
  p->registry_journal.store(p->journal.get());

  SafetyOptions safety_options;
  safety_options.critical_battery_ratio = options.critical_battery;
  safety_options.hover_before_land = millis(options.hover_before_land);
  safety_options.geofence = options.geofence;
  safety_options.channel_address = options.channel_address;
  safety_options.metrics = p->metrics.get();
  if (!options.flight_controllers.empty()) {
    if (p->vehicle_clock) safety_options.clock = p->vehicle_clock.get();
    p->safety =
        std::make_unique<SafetyController>(*p->fleet, *p->missions, *p->log, safety_options);
    for (const auto& [robot, address] : options.flight_controllers) {
      p->safety->addRobot(robot, address);
    }
  }
  CoordinatorServiceOptions service_options;
  service_options.beliefs = p->beliefs.get();
  service_options.missions = p->missions.get();
  service_options.safety = p->safety.get();
  service_options.telemetry = p->telemetry.get();
  service_options.heartbeat_interval = millis(options.heartbeat_interval);
  p->service = std::make_unique<CoordinatorService>(*p->registry, *p->log, *p->metrics, *p->fleet,
                                                    *p->pool, service_options);

  grpc::ServerBuilder builder;
  builder.RegisterService(p->service.get());
  // Control calls are audited beside the journal.
  if (!options.state_dir.empty()) p->runtime.setDefaultAuditLog(options.state_dir + "/audit.jsonl");
  if (!p->runtime.startServer(builder, options.listen, {v1::Coordinator::service_full_name()},
                              &error)) {
    return absl::UnavailableError(error);
  }
  for (const auto& system : options.systems) p->registry->addConfigured(system);
  // Systems registered before a restart are contacted at once (they also
  // register again at their next heartbeat).
  for (const auto& entry : replayed.systems) {
    const durable::v1::SystemRecord& system = entry.second;
    const bool listed =
        std::any_of(options.systems.begin(), options.systems.end(),
                    [&](const ConfiguredSystem& c) { return c.address == system.address(); });
    if (listed) continue;
    ConfiguredSystem known;
    known.robot_id = system.robot_id();
    known.address = system.address();
    p->registry->addConfigured(known);
  }
  if (p->safety) p->safety->start();
  p->missions->resumeRestored();
  return std::unique_ptr<Coordinator>(new Coordinator(std::move(p)));
}

Coordinator::Coordinator(std::unique_ptr<Parts> parts) : parts_(std::move(parts)) {}

Coordinator::~Coordinator() { shutdown(); }

int Coordinator::grpcPort() const { return parts_->runtime.grpcPort(); }
int Coordinator::metricsPort() const { return parts_->runtime.metricsPort(); }
const std::string& Coordinator::incarnation() const { return parts_->log->incarnation(); }

bool Coordinator::writePortFile(const std::string& path, std::string* error) const {
  return parts_->runtime.writePortFile(path, error);
}

void Coordinator::shutdown() {
  Parts& p = *parts_;
  if (p.stopped) return;
  p.stopped = true;
  p.stopCompactor();
  // Subscribers first, then the links to the systems, then the server:
  // in-flight calls forwarded to systems are cancelled with their server call.
  p.service->shutdownStreams();
  if (p.safety) p.safety->stop();
  p.missions->stop();  // running missions stay RUNNING in the journal
  p.fleet->stop();
  p.pool->stop();
  p.registry->stop();
  p.runtime.shutdown(std::chrono::milliseconds(1000));
}

}  // namespace behaviorlib::coordinator
