#include "simulator/service/simulator_process.h"

#include <google/protobuf/util/time_util.h>
#include <grpcpp/grpcpp.h>

#include <algorithm>
#include <atomic>
#include <cstdio>
#include <thread>

#include "absl/status/status.h"
#include "absl/strings/str_join.h"
#include "behaviorlib/errors/status_details.h"
#include "behaviorlib/server_kit/server_runtime.h"
#include "behaviorlib/v1/platform.grpc.pb.h"
#include "behaviorlib/v1/simulator.grpc.pb.h"
#include "simulator/faults/fault_injector.h"
#include "simulator/service/channel_publisher.h"
#include "simulator/service/channel_routes.h"
#include "simulator/service/flight_controller_service.h"
#include "simulator/service/sensor_publisher.h"
#include "simulator/service/simulator_metrics.h"
#include "simulator/service/simulator_service.h"

namespace behaviorlib::sim {

// Declared in construction order: destroyed in reverse, after shutdown().
struct SimulatorProcess::Parts {
  explicit Parts(SimulatorOptions o) : options(std::move(o)), simulation(SimulationOptions{}) {}

  const SimulatorOptions options;
  Simulation simulation;
  TimeControl time;
  server_kit::ServerRuntime runtime;
  std::unique_ptr<SimulatorMetrics> metrics;
  std::unique_ptr<ChannelRoutes> client;
  std::unique_ptr<ChannelRoutes> sensor_client;
  std::unique_ptr<ChannelPublisher> publisher;
  std::unique_ptr<SensorPublisher> sensors;
  std::unique_ptr<FaultInjector> faults;
  WorldControl worlds;
  SetpointBarrier setpoint_barrier;  // the deterministic mode's
  std::unique_ptr<FlightControllerService> flight_controller;
  std::unique_ptr<SimulatorService> simulator;
  std::unique_ptr<TimeGrants> grants;
  std::atomic<bool> stop{false};
  std::thread stepper;
  bool stopped = false;

  // The stepping thread: real time scaled; in lock-step, Step drives time;
  // in the deterministic mode, quanta granted to the followers.
  void step() {
    if (!options.deterministic) {
      simulation.runRealTime(time.time_scale, time.lock_step, stop);
      return;
    }
    grants->waitForFollowers(options.min_followers, stop);
    const auto quantum = std::chrono::duration_cast<SimDuration>(options.quantum);
    const double idle_scale = options.idle_time_scale;
    const auto idle_period = std::chrono::duration_cast<std::chrono::steady_clock::duration>(
        quantum / (idle_scale > 0.0 ? idle_scale : 1.0));
    auto idle_next = std::chrono::steady_clock::now();
    while (!stop.load()) {
      simulation.advance(quantum);
      v1::FollowTimeResponse grant;
      if (publisher) {
        // What the quantum published reaches the broker before its grant,
        // and the grant names how far each topic got (the data barrier).
        // Published here, in one round trip for the sync (the sensors share
        // the publisher's streams in this mode); a broker away: the
        // followers see stale data.
        sensors->flush(false).IgnoreError();
        publisher->flush(true).IgnoreError();
        *grant.mutable_clock() = publisher->lockStepClock(simulation.now());
        // Each broker numbers its topics: a follower waits for its own's.
        grants->grantAndWait(grant, client->acceptedSeqsByDomain(), stop);
      } else {
        *grant.mutable_clock()->mutable_time() =
            google::protobuf::util::TimeUtil::NanosecondsToTimestamp(
                std::chrono::duration_cast<std::chrono::nanoseconds>(simulation.now()).count());
        grants->grantAndWait(grant, stop);
      }
      if (idle_scale > 0.0 && !grants->anyBusy()) {
        // Nobody in the barrier is busy: pace at the idle time scale,
        // sleeping once a few milliseconds are owed (fewer wake-ups than a
        // sleep per quantum).
        const auto now = std::chrono::steady_clock::now();
        if (idle_next < now - std::chrono::milliseconds(50)) idle_next = now;  // was busy
        idle_next += idle_period;
        if (idle_next - now >= std::chrono::milliseconds(2)) {
          std::this_thread::sleep_until(idle_next);
        }
      }
    }
  }
};

absl::Status SimulatorOptions::validate() const {
  absl::Status status;
  std::vector<std::string> problems;
  const auto refuse = [&](const char* field, const std::string& problem) {
    if (status.ok()) status = absl::InvalidArgumentError("");
    status = errors::withFieldViolation(status, field, problem);
    problems.push_back(problem);
  };
  if (!deterministic && !(time_scale >= 0.1 && time_scale <= 1000.0)) {
    refuse("time_scale", "--time-scale must be within [0.1, 1000] or 'max'");
  }
  const double quantum_ms = std::chrono::duration<double, std::milli>(quantum).count();
  if (!(quantum_ms >= 1.0 && quantum_ms <= 100.0)) {
    refuse("quantum", "--quantum-ms must be within [1, 100]");
  }
  if (min_followers < 0 || min_followers > 1000) {
    refuse("min_followers", "--min-followers must be within [0, 1000]");
  }
  const double timeout_s = std::chrono::duration<double>(follower_timeout).count();
  if (!(timeout_s >= 0.1 && timeout_s <= 600.0)) {
    refuse("follower_timeout", "--follower-timeout-s must be within [0.1, 600]");
  }
  if (!(idle_time_scale == 0.0 || (idle_time_scale >= 1.0 && idle_time_scale <= 1000.0))) {
    refuse("idle_time_scale", "--idle-time-scale must be 0 or within [1, 1000]");
  }
  if (seed == 0) refuse("seed", "--seed must be a positive integer");
  if (vehicles.empty()) refuse("vehicles", "--vehicles names no vehicle");
  if (!vehicle_channels.empty() && channel.empty()) {
    refuse("vehicle_channels", "--vehicle-channels needs --channel");
  }
  for (const auto& [robot, address] : vehicle_channels) {
    if (robot.empty() || address.empty()) {
      refuse("vehicle_channels", "--vehicle-channels: each entry is ROBOT=HOST:PORT");
    }
  }
  if (status.ok()) return status;
  return errors::rewrap(status, absl::StrJoin(problems, "; "));
}

absl::StatusOr<std::unique_ptr<SimulatorProcess>> SimulatorProcess::start(
    SimulatorOptions options) {
  if (absl::Status valid = options.validate(); !valid.ok()) return valid;
  auto p = std::make_unique<Parts>(std::move(options));
  const SimulatorOptions& o = p->options;
  p->time.time_scale.store(o.time_scale);
  // The deterministic mode steps in lock-step itself, under time grants.
  p->time.lock_step.store(o.lock_step || o.deterministic);
  p->time.deterministic.store(o.deterministic);

  std::string error;
  if (!p->runtime.startMetrics(o.metrics_listen, &error)) return absl::UnavailableError(error);
  p->metrics = std::make_unique<SimulatorMetrics>(p->runtime.registry(), p->simulation, p->time);

  // Publishers first: loading the world restarts the sensors.
  if (!o.channel.empty()) {
    p->client = std::make_unique<ChannelRoutes>(o.channel, o.vehicle_channels);
    PublishRates rates;
    rates.clock_every_tick = o.clock_every_tick;
    // Deterministic, the followers take their time from the grants; the
    // clock topic is for everyone else (the coordinator, tools).
    if (o.deterministic) rates.clock_hz = 20.0;
    p->publisher = std::make_unique<ChannelPublisher>(*p->client, p->simulation, p->time, rates);
    // A stream of their own, so that images never delay the clock (free
    // running; deterministic, the grants wait for both, and one stream is
    // synced with one round trip).
    if (!o.deterministic) {
      p->sensor_client = std::make_unique<ChannelRoutes>(o.channel, o.vehicle_channels);
    }
    p->sensors = std::make_unique<SensorPublisher>(
        p->sensor_client ? *p->sensor_client : *p->client, p->simulation, p->time, o.sensor_config,
        p->metrics->frameTimer());
  }
  // The vehicles' topics go to the broker only while someone wants them
  // (subscribers, or a recent GetLatest): an idle stack publishes almost
  // nothing. The clock is never gated.
  if (p->client && o.gate_topics) {
    p->client->gatePublishing("robots/");
    if (p->sensor_client) p->sensor_client->gatePublishing("robots/");
    Parts* parts = p.get();
    p->client->watchInterest("robots/", [parts] {
      if (parts->publisher) parts->publisher->interestChanged();
      if (parts->sensors) parts->sensors->interestChanged();
    });
    p->publisher->setInterest(p->client.get());
    p->sensors->setInterest(p->client.get());
  }
  p->faults =
      std::make_unique<FaultInjector>(p->simulation, p->sensors ? &p->sensors->sensors() : nullptr);

  p->worlds.worlds_dir = o.worlds_dir;
  p->worlds.fallback_ids = o.vehicles;
  // Reset restarts the sensors and forgets the faults (the vehicles are new,
  // the wind calm).
  Parts* parts = p.get();
  p->worlds.on_reset = [parts](const std::shared_ptr<const world::World>& world,
                               uint64_t world_seed) {
    if (parts->sensors) parts->sensors->reset(world, world_seed);
    parts->faults->reset();
  };
  if (absl::Status s =
          loadWorldInto(p->worlds, o.world, o.seed, WorldSource::kConfiguration, p->simulation);
      !s.ok()) {
    return absl::InvalidArgumentError("--world: " + std::string(s.message()));
  }
  const std::vector<std::string> ids = p->simulation.robotIds();
  for (const auto& [robot, address] : o.vehicle_channels) {
    if (std::find(ids.begin(), ids.end(), robot) == ids.end()) {
      return absl::InvalidArgumentError("--vehicle-channels: '" + robot +
                                        "' is not a vehicle of the world");
    }
  }

  p->flight_controller = std::make_unique<FlightControllerService>(p->simulation);
  p->simulator = std::make_unique<SimulatorService>(p->simulation, p->time, p->worlds,
                                                    o.fault_injection ? p->faults.get() : nullptr);
  p->grants = std::make_unique<TimeGrants>(o.follower_timeout);
  if (o.deterministic) {
    p->simulator->setTimeGrants(p->grants.get());
    // The followers' setpoints are applied before the next step.
    p->flight_controller->setSetpointBarrier(&p->setpoint_barrier);
    p->grants->setSetpointBarrier(&p->setpoint_barrier);
  }
  if (p->client) {
    ChannelRoutes* routes = p->client.get();
    p->grants->setDomainOf([routes](const std::string& robot) { return routes->domainOf(robot); });
  }
  grpc::ServerBuilder builder;
  builder.RegisterService(p->flight_controller.get());
  builder.RegisterService(p->simulator.get());
  if (!p->runtime.startServer(
          builder, o.listen,
          {v1::FlightController::service_full_name(), v1::Simulator::service_full_name()},
          &error)) {
    return absl::UnavailableError(error);
  }
  // Stopped before the publishers go (shutdown()).
  p->metrics->start(
      {.sensors = p->sensors.get(), .state = p->publisher.get(), .faults = p->faults.get()});
  p->stepper = std::thread([parts] { parts->step(); });
  return std::unique_ptr<SimulatorProcess>(new SimulatorProcess(std::move(p)));
}

SimulatorProcess::SimulatorProcess(std::unique_ptr<Parts> parts) : parts_(std::move(parts)) {}

SimulatorProcess::~SimulatorProcess() { shutdown(); }

int SimulatorProcess::grpcPort() const { return parts_->runtime.grpcPort(); }
int SimulatorProcess::metricsPort() const { return parts_->runtime.metricsPort(); }
std::vector<std::string> SimulatorProcess::robotIds() const {
  return parts_->simulation.robotIds();
}

bool SimulatorProcess::writePortFile(const std::string& path, std::string* error) const {
  return parts_->runtime.writePortFile(path, error);
}

void SimulatorProcess::shutdown() {
  Parts& p = *parts_;
  if (p.stopped) return;
  p.stopped = true;
  p.flight_controller->shutdown();
  p.simulator->shutdown();
  p.stop = true;
  p.grants->shutdown();  // ends the FollowTime streams and the stepper's wait
  p.runtime.shutdown(std::chrono::seconds(2));
  p.stepper.join();
  p.metrics->stop();
  if (p.options.deterministic) {
    std::fprintf(stderr,
                 "simulator: steps that waited for a reported setpoint: %llu (gave up: %llu)\n",
                 static_cast<unsigned long long>(p.setpoint_barrier.waitCount()),
                 static_cast<unsigned long long>(p.setpoint_barrier.timeoutCount()));
  }
  if (p.sensors) {
    const auto& s = p.sensors->sensors();
    std::fprintf(stderr,
                 "simulator: sensor frames dropped (worker busy): lidar %llu, camera %llu\n",
                 static_cast<unsigned long long>(s.droppedCount(SensorKind::kLidar)),
                 static_cast<unsigned long long>(s.droppedCount(SensorKind::kCamera)));
  }
  if (p.client && p.options.gate_topics) {
    p.publisher->setInterest(nullptr);
    p.sensors->setInterest(nullptr);
    p.client->stopWatching();  // no more interestChanged calls
  }
  p.sensors.reset();
  p.publisher.reset();
}

}  // namespace behaviorlib::sim
