#pragma once

// The simulator as a class: the simulation, its publishers on the data
// channel, the FlightController and Simulator services and the stepping
// thread, wired together and serving on one port. main() parses the flags
// into SimulatorOptions and runs one until a shutdown signal; a test builds
// one in-process.

#include <chrono>
#include <cstdint>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "simulator/sensors/sensor_config.h"

namespace behaviorlib::sim {

/// A simulator's settings: the command line, parsed and checked.
struct SimulatorOptions {
  /// gRPC address host:port (port 0 picks a free port).
  std::string listen = "127.0.0.1:50070";
  /// Prometheus /metrics address (empty: none).
  std::string metrics_listen = "127.0.0.1:0";
  /// Data channel broker; empty: publish nothing.
  std::string channel;
  /// A broker of its own per vehicle (robot id -> host:port): that vehicle's
  /// topics, and the clock, go there instead (a fleet across hosts,
  /// decision 39).
  std::map<std::string, std::string> vehicle_channels;
  /// World file or shipped world name; empty: an empty field.
  std::string world;
  /// Where the shipped worlds are.
  std::string worlds_dir;
  /// Robot ids for a world without start poses (vehicle i at x = 2 i m).
  std::vector<std::string> vehicles = {"drone1"};
  /// The deterministic mode (--time-scale max): time advanced by quanta
  /// granted to the followers.
  bool deterministic = false;
  /// Free running: simulated seconds per wall second.
  double time_scale = 1.0;
  /// Time advances only through Simulator.Step.
  bool lock_step = false;
  /// Deterministic: simulated time per grant.
  std::chrono::nanoseconds quantum = std::chrono::milliseconds(10);
  /// Deterministic: followers to wait for before time starts.
  int min_followers = 0;
  /// Deterministic: wall time a follower may take to catch up.
  std::chrono::nanoseconds follower_timeout = std::chrono::seconds(5);
  /// Deterministic: pace while no follower is busy (0: none).
  double idle_time_scale = 20.0;
  /// Accept Simulator.InjectFailure.
  bool fault_injection = false;
  /// Free running: a clock sample every tick instead of the pace line.
  bool clock_every_tick = false;
  /// Publish a vehicle's topics only while someone wants them.
  bool gate_topics = true;
  SensorConfig sensor_config;
  /// Seed of the sensor noise (positive).
  uint64_t seed = 1;

  /// Every setting within its range, each problem named by its flag:
  /// INVALID_ARGUMENT with a google.rpc.BadRequest field violation per
  /// setting (time_scale, quantum, min_followers, follower_timeout,
  /// idle_time_scale, seed, vehicles, vehicle_channels). start() checks it.
  absl::Status validate() const;
};

class SimulatorProcess {
 public:
  /// Loads the world (INVALID_ARGUMENT naming it when it cannot), binds the
  /// ports (UNAVAILABLE when it cannot), serves and starts the time.
  static absl::StatusOr<std::unique_ptr<SimulatorProcess>> start(SimulatorOptions options);
  /// shutdown(), if not done yet.
  ~SimulatorProcess();
  SimulatorProcess(const SimulatorProcess&) = delete;
  SimulatorProcess& operator=(const SimulatorProcess&) = delete;

  int grpcPort() const;
  int metricsPort() const;
  /// The simulated vehicles' robot ids.
  std::vector<std::string> robotIds() const;
  /// Writes grpc_port= and metrics_port= lines to `path`.
  bool writePortFile(const std::string& path, std::string* error) const;

  /// Ends the services' streams and the time grants, stops the server and
  /// the stepping thread, then the metrics and the publishers.
  void shutdown();

 private:
  struct Parts;
  explicit SimulatorProcess(std::unique_ptr<Parts> parts);
  std::unique_ptr<Parts> parts_;
};

}  // namespace behaviorlib::sim
