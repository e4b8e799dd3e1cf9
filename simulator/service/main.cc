// simulator: the quadrotor simulation service. Serves FlightController (the
// platform interface) and Simulator (time, state, faults) on one port, and
// publishes simulated time, ground truth and the sensors on the data channel
// (topics in simulator/service/channel_publisher.h).

#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <sstream>
#include <string>

#include "behaviorlib/clock.h"
#include "behaviorlib/server_kit/flags.h"
#include "behaviorlib/server_kit/server_runtime.h"
#include "simulator/sensors/sensor_config.h"
#include "simulator/service/simulator_process.h"

int main(int argc, char** argv) {
  using behaviorlib::server::fatal;
  using behaviorlib::server::FlagSet;
  using behaviorlib::server::ServerRuntime;
  namespace sim = behaviorlib::sim;
  ServerRuntime::blockShutdownSignals();
  const std::string program = "simulator";

  std::string listen = "127.0.0.1:50070";
  std::string metrics_listen = "127.0.0.1:0";
  std::string port_file;
  std::string channel;
  std::string vehicles = "drone1";
  std::string world_arg;
  std::string worlds_dir = BEHAVIORLIB_WORLDS_DIR;
  std::string time_scale_arg = "1";
  bool lock_step = false;
  double quantum_ms = 10.0;
  int min_followers = 0;
  double follower_timeout_s = 5.0;
  double idle_time_scale = 20.0;
  bool fault_injection = false;
  std::string clock_publish = "line";
  bool gate_topics = true;
  std::string sensor_config_path;
  std::string seed_arg = "1";
  FlagSet flags(
      "quadrotor simulator: FlightController + Simulator services, state and time on "
      "the data channel");
  flags.add("listen", &listen, "gRPC address host:port (port 0 picks a free port)");
  flags.add("metrics-listen", &metrics_listen, "Prometheus /metrics address (empty disables)");
  flags.add("port-file", &port_file, "write the bound ports here (grpc_port=, metrics_port=)");
  flags.add("channel", &channel, "data channel broker address; empty: publish nothing");
  flags.add("world", &world_arg,
            "world file, or the name of a shipped world (empty_field, rooms, aircraft); empty: "
            "an empty field");
  flags.add("worlds-dir", &worlds_dir, "where the shipped worlds are");
  flags.add("vehicles", &vehicles,
            "comma-separated robot ids for a world without start poses; vehicle i starts "
            "landed at x = 2 i m");
  flags.add("time-scale", &time_scale_arg,
            "simulated seconds per wall second (0.1..1000), or 'max': the deterministic mode, "
            "time advanced by quanta as fast as every follower (Simulator.FollowTime) keeps up");
  flags.add("lock-step", &lock_step, "advance time only through Simulator.Step");
  flags.add("quantum-ms", &quantum_ms,
            "deterministic mode: simulated milliseconds per grant (1..100; at most the shortest "
            "behavior tick period)");
  flags.add("min-followers", &min_followers,
            "deterministic mode: time starts once this many followers joined (0..1000)");
  flags.add("follower-timeout-s", &follower_timeout_s,
            "deterministic mode: wall seconds a follower may take to catch up before time goes "
            "on without it (0.1..600)");
  flags.add("idle-time-scale", &idle_time_scale,
            "deterministic mode: while no follower is busy, simulated time runs at most this "
            "many times real time (1..1000; 0: no limit). Then only what is outside the "
            "barrier acts (the coordinator, tools, tests), in wall time: a safety action's "
            "lease renewals, a mission's next step");
  flags.add("clock-publish", &clock_publish,
            "free-running, how simulated time goes on the 'clock' topic: 'line' (its pace "
            "line when it changes and once a wall second; readers extrapolate) or "
            "'every-tick' (a sample every 5 ms of simulated time)");
  flags.add("gate-topics", &gate_topics,
            "publish a vehicle's topic only while the broker says someone wants it "
            "(DataChannel.WatchInterest); false: publish every sample");
  flags.add("enable-fault-injection", &fault_injection,
            "accept Simulator.InjectFailure (sensor, motor, battery and wind faults; see "
            "simulator.proto)");
  flags.add("sensor-config", &sensor_config_path,
            "YAML file of sensor rates, noise, lidar and camera settings (see "
            "simulator/sensors/README.md); empty: the defaults");
  flags.add("seed", &seed_arg,
            "seed of the sensor noise (a positive integer; Reset can change it)");
  int exit_code = 0;
  if (!flags.parse(argc, argv, &exit_code)) return exit_code;
  const bool deterministic = time_scale_arg == "max";
  double time_scale = 1.0;
  if (!deterministic) {
    char* end = nullptr;
    time_scale = std::strtod(time_scale_arg.c_str(), &end);
    if (time_scale_arg.empty() || *end != '\0' || !(time_scale >= 0.1 && time_scale <= 1000.0)) {
      fatal(program,
            "--time-scale must be within [0.1, 1000] or 'max', got '" + time_scale_arg + "'");
      return 2;
    }
  }
  if (!(quantum_ms >= 1.0 && quantum_ms <= 100.0) || min_followers < 0 || min_followers > 1000 ||
      !(follower_timeout_s >= 0.1 && follower_timeout_s <= 600.0) ||
      !(idle_time_scale == 0.0 || (idle_time_scale >= 1.0 && idle_time_scale <= 1000.0))) {
    fatal(program,
          "--quantum-ms must be within [1, 100], --min-followers within [0, 1000], "
          "--follower-timeout-s within [0.1, 600], --idle-time-scale 0 or within [1, 1000]");
    return 2;
  }

  if (clock_publish != "line" && clock_publish != "every-tick") {
    fatal(program, "--clock-publish must be 'line' or 'every-tick', not '" + clock_publish + "'");
    return 2;
  }
  uint64_t seed = 0;
  {
    char* end = nullptr;
    seed = std::strtoull(seed_arg.c_str(), &end, 10);
    if (seed_arg.empty() || *end != '\0' || seed == 0 || seed_arg[0] == '-') {
      fatal(program, "--seed must be a positive integer, got '" + seed_arg + "'");
      return 2;
    }
  }
  sim::SensorConfig sensor_config;
  if (!sensor_config_path.empty()) {
    absl::StatusOr<sim::SensorConfig> loaded = sim::loadSensorConfig(sensor_config_path);
    if (!loaded.ok()) {
      fatal(program, "--sensor-config: " + std::string(loaded.status().message()));
      return 2;
    }
    sensor_config = std::move(*loaded);
  }

  sim::SimulatorOptions options;
  options.listen = listen;
  options.metrics_listen = metrics_listen;
  options.channel = channel;
  options.world = world_arg;
  options.worlds_dir = worlds_dir;
  options.vehicles.clear();
  std::istringstream ids(vehicles);
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
  options.fault_injection = fault_injection;
  options.clock_every_tick = clock_publish == "every-tick";
  options.gate_topics = gate_topics;
  options.sensor_config = std::move(sensor_config);
  options.seed = seed;

  auto simulator = sim::SimulatorProcess::start(std::move(options));
  if (!simulator.ok()) {
    fatal(program, std::string(simulator.status().message()));
    return simulator.status().code() == absl::StatusCode::kInvalidArgument ? 2 : 1;
  }
  std::string error;
  if (!(*simulator)->writePortFile(port_file, &error)) return fatal(program, error);
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
