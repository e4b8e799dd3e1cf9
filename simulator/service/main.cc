// simulator: the quadrotor simulation service. Serves FlightController (the
// platform interface) and Simulator (time, state, faults) on one port, and
// publishes simulated time, ground truth and the sensors on the data channel
// (topics in simulator/service/channel_publisher.h).

#include <google/protobuf/util/time_util.h>

#include <cstdio>
#include <cstdlib>
#include <sstream>
#include <thread>

#include "behaviorlib/channel/channel_client.h"
#include "behaviorlib/server_kit/flags.h"
#include "behaviorlib/server_kit/server_runtime.h"
#include "behaviorlib/v1/platform.grpc.pb.h"
#include "behaviorlib/v1/simulator.grpc.pb.h"
#include "simulator/faults/fault_injector.h"
#include "simulator/service/channel_publisher.h"
#include "simulator/service/flight_controller_service.h"
#include "simulator/service/sensor_publisher.h"
#include "simulator/service/simulator_metrics.h"
#include "simulator/service/simulator_service.h"
#include "simulator/service/vehicle_models.h"

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
  double min_followers_arg = 0;  // FlagSet has no integers
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
  flags.add("min-followers", &min_followers_arg,
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
  const int min_followers = static_cast<int>(min_followers_arg);
  if (!(quantum_ms >= 1.0 && quantum_ms <= 100.0) || !(min_followers_arg >= 0.0) ||
      min_followers_arg > 1000.0 || min_followers != min_followers_arg ||
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

  sim::Simulation simulation(sim::SimulationOptions{});
  sim::TimeControl time;
  time.time_scale.store(time_scale);
  // The deterministic mode steps in lock-step itself, under time grants.
  time.lock_step.store(lock_step || deterministic);
  time.deterministic.store(deterministic);

  ServerRuntime runtime;
  std::string error;
  if (!runtime.startMetrics(metrics_listen, &error)) return fatal(program, error);
  sim::SimulatorMetrics metrics(runtime.registry(), simulation, time);

  // Publishers first: loading the world restarts the sensors.
  std::unique_ptr<behaviorlib::channel::ChannelClient> client;
  std::unique_ptr<behaviorlib::channel::ChannelClient> sensor_client;
  std::unique_ptr<sim::ChannelPublisher> publisher;
  std::unique_ptr<sim::SensorPublisher> sensors;
  if (!channel.empty()) {
    client = std::make_unique<behaviorlib::channel::ChannelClient>(channel);
    sim::PublishRates rates;
    rates.clock_every_tick = clock_publish == "every-tick";
    // Deterministic, the followers take their time from the grants; the
    // clock topic is for everyone else (the coordinator, tools).
    if (deterministic) rates.clock_hz = 20.0;
    publisher = std::make_unique<sim::ChannelPublisher>(*client, simulation, time, rates);
    // A stream of their own, so that images never delay the clock (free
    // running; deterministic, the grants wait for both, and one stream is
    // synced with one round trip).
    if (!deterministic) {
      sensor_client = std::make_unique<behaviorlib::channel::ChannelClient>(channel);
    }
    sensors =
        std::make_unique<sim::SensorPublisher>(sensor_client ? *sensor_client : *client, simulation,
                                               time, sensor_config, metrics.frameTimer());
  }
  // The vehicles' topics go to the broker only while someone wants them
  // (subscribers, or a recent GetLatest): an idle stack publishes almost
  // nothing. The clock is never gated.
  std::unique_ptr<behaviorlib::channel::InterestWatch> interest;
  if (client && gate_topics) {
    client->gatePublishing("robots/");
    if (sensor_client) sensor_client->gatePublishing("robots/");
    interest = client->watchInterest("robots/", [&publisher, &sensors] {
      if (publisher) publisher->interestChanged();
      if (sensors) sensors->interestChanged();
    });
    publisher->setInterest(interest.get());
    sensors->setInterest(interest.get());
  }
  sim::FaultInjector faults(simulation, sensors ? &sensors->sensors() : nullptr);

  sim::WorldControl worlds;
  worlds.worlds_dir = worlds_dir;
  std::istringstream ids(vehicles);
  for (std::string id; std::getline(ids, id, ',');) {
    if (!id.empty()) worlds.fallback_ids.push_back(id);
  }
  if (worlds.fallback_ids.empty()) {
    fatal(program, "--vehicles names no vehicle");
    return 2;
  }
  // Reset restarts the sensors and forgets the faults (the vehicles are new,
  // the wind calm).
  worlds.on_reset = [&sensors, &faults](const std::shared_ptr<const sim::World>& world,
                                        uint64_t world_seed) {
    if (sensors) sensors->reset(world, world_seed);
    faults.reset();
  };
  if (absl::Status s = sim::loadWorldInto(worlds, world_arg, seed, simulation); !s.ok()) {
    fatal(program, "--world: " + std::string(s.message()));
    return 2;
  }
  std::string robot_ids;
  for (const auto& id : simulation.robotIds()) robot_ids += (robot_ids.empty() ? "" : ",") + id;

  sim::FlightControllerService flight_controller(simulation);
  sim::SimulatorService simulator(simulation, time, worlds, fault_injection ? &faults : nullptr);
  sim::TimeGrants grants(std::chrono::duration_cast<std::chrono::nanoseconds>(
      std::chrono::duration<double>(follower_timeout_s)));
  if (deterministic) simulator.setTimeGrants(&grants);
  grpc::ServerBuilder builder;
  builder.RegisterService(&flight_controller);
  builder.RegisterService(&simulator);
  if (!runtime.startServer(builder, listen,
                           {behaviorlib::v1::FlightController::service_full_name(),
                            behaviorlib::v1::Simulator::service_full_name()},
                           &error)) {
    return fatal(program, error);
  }
  if (!runtime.writePortFile(port_file, &error)) return fatal(program, error);
  // Stopped before the publishers go (below).
  metrics.start({.sensors = sensors.get(), .state = publisher.get(), .faults = &faults});

  // The stepping thread: real time scaled; in lock-step, Step drives time;
  // in the deterministic mode, quanta granted to the followers.
  std::atomic<bool> stop{false};
  const auto quantum = std::chrono::duration_cast<sim::SimDuration>(
      std::chrono::duration<double, std::milli>(quantum_ms));
  std::thread stepper([&] {
    if (!deterministic) {
      simulation.runRealTime(time.time_scale, time.lock_step, stop);
      return;
    }
    grants.waitForFollowers(min_followers, stop);
    const auto idle_period = std::chrono::duration_cast<std::chrono::steady_clock::duration>(
        quantum / (idle_time_scale > 0.0 ? idle_time_scale : 1.0));
    auto idle_next = std::chrono::steady_clock::now();
    while (!stop.load()) {
      simulation.advance(quantum);
      behaviorlib::v1::FollowTimeResponse grant;
      if (publisher) {
        // What the quantum published reaches the broker before its grant,
        // and the grant names how far each topic got (the data barrier).
        publisher->waitDrained(std::chrono::seconds(1));
        sensors->waitDrained(std::chrono::seconds(1));
        client->sync().IgnoreError();  // a broker away: the followers see stale data
        for (const auto& [topic, seq] : client->acceptedSeqs()) {
          (*grant.mutable_topic_seqs())[topic] = seq;
        }
        *grant.mutable_clock() = publisher->lockStepClock(simulation.now());
      } else {
        *grant.mutable_clock()->mutable_time() =
            google::protobuf::util::TimeUtil::NanosecondsToTimestamp(
                std::chrono::duration_cast<std::chrono::nanoseconds>(simulation.now()).count());
      }
      grants.grantAndWait(grant, stop);
      if (idle_time_scale > 0.0 && !grants.anyBusy()) {
        // Nobody in the barrier is busy: pace at --idle-time-scale, sleeping
        // once a few milliseconds are owed (fewer wake-ups than a sleep per
        // quantum).
        const auto now = std::chrono::steady_clock::now();
        if (idle_next < now - std::chrono::milliseconds(50)) idle_next = now;  // was busy
        idle_next += idle_period;
        if (idle_next - now >= std::chrono::milliseconds(2))
          std::this_thread::sleep_until(idle_next);
      }
    }
  });
  if (deterministic) {
    std::fprintf(stderr,
                 "%s: vehicles [%s], gRPC on port %d, metrics on port %d, deterministic (time "
                 "scale max, quanta of %g ms, waiting for %d followers)\n",
                 program.c_str(), robot_ids.c_str(), runtime.grpcPort(), runtime.metricsPort(),
                 quantum_ms, min_followers);
  } else {
    std::fprintf(stderr,
                 "%s: vehicles [%s], gRPC on port %d, metrics on port %d, time scale %g%s\n",
                 program.c_str(), robot_ids.c_str(), runtime.grpcPort(), runtime.metricsPort(),
                 time_scale, lock_step ? " (lock-step)" : "");
  }

  ServerRuntime::waitForShutdownSignal();
  std::fprintf(stderr, "%s: shutting down\n", program.c_str());
  flight_controller.shutdown();
  simulator.shutdown();
  stop = true;
  grants.shutdown();  // ends the FollowTime streams and the stepper's wait
  runtime.shutdown(std::chrono::seconds(2));
  stepper.join();
  metrics.stop();
  if (sensors) {
    const auto& s = sensors->sensors();
    std::fprintf(stderr, "%s: sensor frames dropped (worker busy): lidar %llu, camera %llu\n",
                 program.c_str(),
                 static_cast<unsigned long long>(s.droppedCount(sim::SensorKind::kLidar)),
                 static_cast<unsigned long long>(s.droppedCount(sim::SensorKind::kCamera)));
  }
  if (interest) {
    publisher->setInterest(nullptr);
    sensors->setInterest(nullptr);
    interest.reset();  // no more interestChanged calls
  }
  sensors.reset();
  publisher.reset();
  return 0;
}
