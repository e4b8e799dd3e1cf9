// simulator: the quadrotor simulation service. Serves FlightController (the
// platform interface) and Simulator (time, state, faults) on one port, and
// publishes simulated time, ground truth and the sensors on the data channel
// (topics in simulator/service/channel_publisher.h).

#include <chrono>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <sstream>
#include <string>

#include "absl/flags/flag.h"
#include "absl/strings/str_split.h"
#include "behaviorlib/clock.h"
#include "behaviorlib/server_kit/flags.h"
#include "behaviorlib/server_kit/server_runtime.h"
#include "simulator/sensors/sensor_config.h"
#include "simulator/service/simulator_process.h"

ABSL_FLAG(std::string, listen, "127.0.0.1:50070",
          "gRPC address host:port (port 0 picks a free port)");
ABSL_FLAG(std::string, metrics_listen, "127.0.0.1:0",
          "Prometheus /metrics address (empty disables)");
ABSL_FLAG(std::string, port_file, "", "write the bound ports here (grpc_port=, metrics_port=)");
ABSL_FLAG(std::string, channel, "", "data channel broker address; empty: publish nothing");
ABSL_FLAG(std::string, vehicle_channels, "",
          "ROBOT=HOST:PORT,...: a vehicle's topics (and the clock) go to a broker of its own, as "
          "its autopilot would publish on the vehicle (a fleet across hosts); needs --channel");
ABSL_FLAG(std::string, world, "",
          "world file, or the name of a shipped world (empty_field, rooms, aircraft); empty: an "
          "empty field");
ABSL_FLAG(std::string, worlds_dir, BEHAVIORLIB_WORLDS_DIR, "where the shipped worlds are");
ABSL_FLAG(std::string, vehicles, "drone1",
          "comma-separated robot ids for a world without start poses; vehicle i starts landed at "
          "x = 2 i m");
ABSL_FLAG(std::string, time_scale, "1",
          "simulated seconds per wall second (0.1..1000), or 'max': the deterministic mode, time "
          "advanced by quanta as fast as every follower (Simulator.FollowTime) keeps up");
ABSL_FLAG(bool, lock_step, false, "advance time only through Simulator.Step");
ABSL_FLAG(double, quantum_ms, 10.0,
          "deterministic mode: simulated milliseconds per grant (1..100; at most the shortest "
          "behavior tick period)");
ABSL_FLAG(int, min_followers, 0,
          "deterministic mode: time starts once this many followers joined (0..1000)");
ABSL_FLAG(double, follower_timeout_s, 5.0,
          "deterministic mode: wall seconds a follower may take to catch up before time goes on "
          "without it (0.1..600)");
ABSL_FLAG(double, idle_time_scale, 20.0,
          "deterministic mode: while no follower is busy, simulated time runs at most this many "
          "times real time (1..1000; 0: no limit). Then only what is outside the barrier acts "
          "(the coordinator, tools, tests), in wall time: a safety action's lease renewals, a "
          "mission's next step");
ABSL_FLAG(std::string, clock_publish, "line",
          "free-running, how simulated time goes on the 'clock' topic: 'line' (its pace line "
          "when it changes and once a wall second; readers extrapolate) or 'every-tick' (a "
          "sample every 5 ms of simulated time)");
ABSL_FLAG(bool, gate_topics, true,
          "publish a vehicle's topic only while the broker says someone wants it "
          "(DataChannel.WatchInterest); false: publish every sample");
ABSL_FLAG(bool, enable_fault_injection, false,
          "accept Simulator.InjectFailure (sensor, motor, battery and wind faults; see "
          "simulator.proto)");
ABSL_FLAG(std::string, sensor_config, "",
          "YAML file of sensor rates, noise, lidar and camera settings (see "
          "simulator/sensors/README.md); empty: the defaults");
ABSL_FLAG(uint64_t, seed, 1, "seed of the sensor noise (a positive integer; Reset can change it)");

int main(int argc, char** argv) {
  using behaviorlib::server_kit::fatal;
  using behaviorlib::server_kit::ServerRuntime;
  namespace sim = behaviorlib::sim;
  ServerRuntime::blockShutdownSignals();
  const std::string program = "simulator";
  behaviorlib::server_kit::parseFlags(
      argc, argv,
      "quadrotor simulator: FlightController + Simulator services, state and time on the data "
      "channel");
  const std::string time_scale_arg = absl::GetFlag(FLAGS_time_scale);
  const bool lock_step = absl::GetFlag(FLAGS_lock_step);
  const double quantum_ms = absl::GetFlag(FLAGS_quantum_ms);
  const int min_followers = absl::GetFlag(FLAGS_min_followers);
  const double follower_timeout_s = absl::GetFlag(FLAGS_follower_timeout_s);
  const double idle_time_scale = absl::GetFlag(FLAGS_idle_time_scale);
  const std::string clock_publish = absl::GetFlag(FLAGS_clock_publish);
  const bool deterministic = time_scale_arg == "max";
  double time_scale = 1.0;
  if (!deterministic) {
    char* end = nullptr;
    time_scale = std::strtod(time_scale_arg.c_str(), &end);
    if (time_scale_arg.empty() || *end != '\0') {
      fatal(program,
            "--time-scale must be within [0.1, 1000] or 'max', got '" + time_scale_arg + "'");
      return 2;
    }
  }
  if (clock_publish != "line" && clock_publish != "every-tick") {
    fatal(program, "--clock-publish must be 'line' or 'every-tick', not '" + clock_publish + "'");
    return 2;
  }
  const uint64_t seed = absl::GetFlag(FLAGS_seed);
  sim::SensorConfig sensor_config;
  if (const std::string sensor_config_path = absl::GetFlag(FLAGS_sensor_config);
      !sensor_config_path.empty()) {
    absl::StatusOr<sim::SensorConfig> loaded = sim::loadSensorConfig(sensor_config_path);
    if (!loaded.ok()) {
      fatal(program, "--sensor-config: " + std::string(loaded.status().message()));
      return 2;
    }
    sensor_config = std::move(*loaded);
  }

  sim::SimulatorOptions options;
  options.listen = absl::GetFlag(FLAGS_listen);
  options.metrics_listen = absl::GetFlag(FLAGS_metrics_listen);
  options.channel = absl::GetFlag(FLAGS_channel);
  for (absl::string_view item :
       absl::StrSplit(absl::GetFlag(FLAGS_vehicle_channels), ',', absl::SkipEmpty())) {
    std::pair<std::string, std::string> route = absl::StrSplit(item, absl::MaxSplits('=', 1));
    if (route.first.empty() || route.second.empty() ||
        !options.vehicle_channels.emplace(route.first, route.second).second) {
      fatal(program, "--vehicle-channels: '" + std::string(item) +
                         "' is not ROBOT=HOST:PORT (each robot once, and --channel set)");
      return 2;
    }
  }
  options.world = absl::GetFlag(FLAGS_world);
  options.worlds_dir = absl::GetFlag(FLAGS_worlds_dir);
  options.vehicles.clear();
  std::istringstream ids(absl::GetFlag(FLAGS_vehicles));
  for (std::string id; std::getline(ids, id, ',');) {
    if (!id.empty()) options.vehicles.push_back(id);
  }
  options.deterministic = deterministic;
  options.time_scale = time_scale;
  options.lock_step = lock_step;
  options.quantum = std::chrono::duration_cast<std::chrono::nanoseconds>(
      std::chrono::duration<double, std::milli>(quantum_ms));
  options.min_followers = min_followers;
  options.follower_timeout = behaviorlib::seconds(follower_timeout_s);
  options.idle_time_scale = idle_time_scale;
  options.fault_injection = absl::GetFlag(FLAGS_enable_fault_injection);
  options.clock_every_tick = clock_publish == "every-tick";
  options.gate_topics = absl::GetFlag(FLAGS_gate_topics);
  options.sensor_config = std::move(sensor_config);
  options.seed = seed;
  // The ranges are SimulatorOptions' (an in-process simulator is checked
  // the same way).
  if (absl::Status valid = options.validate(); !valid.ok()) {
    fatal(program, std::string(valid.message()));
    return 2;
  }

  auto simulator = sim::SimulatorProcess::start(std::move(options));
  if (!simulator.ok()) return fatal(program, simulator.status());
  std::string error;
  if (!(*simulator)->writePortFile(absl::GetFlag(FLAGS_port_file), &error)) {
    return fatal(program, error);
  }
  std::string robot_ids;
  for (const auto& id : (*simulator)->robotIds()) {
    robot_ids += (robot_ids.empty() ? "" : ",") + id;
  }
  if (deterministic) {
    std::fprintf(stderr,
                 "%s: vehicles [%s], gRPC on port %d, metrics on port %d, deterministic (time "
                 "scale max, quanta of %g ms, waiting for %d followers)\n",
                 program.c_str(), robot_ids.c_str(), (*simulator)->grpcPort(),
                 (*simulator)->metricsPort(), quantum_ms, min_followers);
  } else {
    std::fprintf(stderr,
                 "%s: vehicles [%s], gRPC on port %d, metrics on port %d, time scale %g%s\n",
                 program.c_str(), robot_ids.c_str(), (*simulator)->grpcPort(),
                 (*simulator)->metricsPort(), time_scale, lock_step ? " (lock-step)" : "");
  }

  ServerRuntime::waitForShutdownSignal();
  std::fprintf(stderr, "%s: shutting down\n", program.c_str());
  (*simulator)->shutdown();
  return 0;
}
