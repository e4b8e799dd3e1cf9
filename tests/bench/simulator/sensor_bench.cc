// sim_sensors_bench: how fast the simulator runs with its sensors on. The
// simulator binary and the channel broker run as real processes; one vehicle
// at 1 kHz physics with every sensor at its default rate (IMU 200 Hz, GPS
// 10 Hz, barometer 25 Hz, linear speed 30 Hz, battery 2 Hz, 2-D lidar 360
// beams at 10 Hz, camera 640x480 at 15 Hz), in the shipped `rooms` world
// (a copy with drone1 as its only vehicle).
//
// Per configuration (camera subscribed by this process, or not; and for
// reference the simulator without a channel, so without sensors) it measures:
//   lock-step     Simulator.Step of 1 s at a time, as fast as it answers: the
//                 physics waits for every lidar scan and camera frame
//   free-running  SetTimeScale 10 (does everything keep up?) and 1000 (the
//                 maximum: the pace the simulator reaches by itself); frames
//                 a worker cannot make in time are dropped and counted
// and reads from the simulator's own /metrics: the mean wall time of a
// physics step, of a lidar scan and of a camera frame (render + JPEG), the
// frames dropped, the samples published per sensor.
//
//   sim_sensors_bench                  # about 1.5 min, markdown table
//   sim_sensors_bench --smoke          # a few seconds: fails on errors only
//   sim_sensors_bench --sim-s 20 --window-s 5 --world empty_field
//
// Exit code 1 when something is broken (a process does not start or exit
// cleanly, a call fails, no sample or frame comes); timings never fail it.

#include <google/protobuf/util/time_util.h>
#include <grpcpp/grpcpp.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <map>
#include <optional>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "behaviorlib/channel/channel_client.h"
#include "behaviorlib/v1/simulator.grpc.pb.h"
#include "behaviorlib/v1/types.pb.h"
#include "support/server_process.h"

namespace behaviorlib::bench {
namespace {

namespace v1 = behaviorlib::v1;
using google::protobuf::util::TimeUtil;
using std::chrono::milliseconds;
using std::chrono::seconds;
using Labels = std::map<std::string, std::string>;

struct Options {
  bool smoke = false;
  int sim_s = 20;         ///< simulated seconds per lock-step run
  double window_s = 5.0;  ///< wall seconds per free-running run
  std::string world = "rooms";
};

/// One series of a Prometheus text exposition (nullopt when absent).
std::optional<double> value(const std::string& text, const std::string& name,
                            const Labels& labels = {}) {
  std::istringstream lines(text);
  for (std::string line; std::getline(lines, line);) {
    if (line.empty() || line[0] == '#') continue;
    const std::size_t end_of_name = line.find_first_of("{ ");
    if (end_of_name == std::string::npos || line.substr(0, end_of_name) != name) continue;
    Labels found;
    std::size_t rest = end_of_name;
    if (line[end_of_name] == '{') {
      const std::size_t close = line.find('}', end_of_name);
      std::istringstream pairs(line.substr(end_of_name + 1, close - end_of_name - 1));
      for (std::string pair; std::getline(pairs, pair, ',');) {
        const std::size_t eq = pair.find('=');
        found[pair.substr(0, eq)] = pair.substr(eq + 2, pair.size() - eq - 3);
      }
      rest = close + 1;
    }
    bool match = true;
    for (const auto& [key, wanted] : labels) {
      auto it = found.find(key);
      match = match && it != found.end() && it->second == wanted;
    }
    if (match) return std::stod(line.substr(rest));
  }
  return std::nullopt;
}

std::unique_ptr<grpc::ClientContext> context(seconds timeout = seconds(120)) {
  auto ctx = std::make_unique<grpc::ClientContext>();
  ctx->set_deadline(std::chrono::system_clock::now() + timeout);
  return ctx;
}

/// What one run measured.
struct Row {
  std::string configuration;
  std::string mode;
  double sim_s = 0, wall_s = 0;
  double step_us = NAN, lidar_ms = NAN, camera_ms = NAN;
  double lidar_frames = 0, camera_frames = 0, lidar_dropped = 0, camera_dropped = 0;
  double imu_samples = 0, gps_samples = 0;
  double rtf = 0;  ///< simulated seconds per wall second
};

/// Differences of the simulator's metrics between two scrapes.
class Scrape {
 public:
  explicit Scrape(int port) : port_(port) { text_ = support::httpGet(port_, "/metrics"); }
  bool ok() const { return !text_.empty(); }
  double get(const std::string& name, const Labels& labels = {}) const {
    return value(text_, name, labels).value_or(0.0);
  }

 private:
  int port_;
  std::string text_;
};

class Bench {
 public:
  explicit Bench(Options options) : options_(std::move(options)) {}

  /// The shipped world `name` with drone1 as its only vehicle (a copy in
  /// /tmp); "" when it cannot be read.
  std::string singleVehicleWorld(const std::string& name) {
    std::ifstream in(std::string(BEHAVIORLIB_WORLDS_DIR) + "/" + name + ".yaml");
    std::stringstream text;
    text << in.rdbuf();
    std::string world = text.str();
    const std::size_t poses = world.find("\nstart_poses:");
    if (!in || poses == std::string::npos) return "";
    world = world.substr(0, poses) +
            "\nstart_poses:\n  - robot_id: drone1\n    position_m: [2.0, 2.0, 0.0]\n";
    const std::string path =
        "/tmp/sim_sensors_bench_" + std::to_string(::getpid()) + "_" + name + ".yaml";
    std::ofstream(path) << world;
    return path;
  }

  int run() {
    world_path_ = singleVehicleWorld(options_.world);
    if (world_path_.empty()) return fail("cannot read the shipped world " + options_.world);
    const int code = runAll();
    std::remove(world_path_.c_str());
    return code;
  }

  int runAll() {
    support::ServerProcess broker(BEHAVIORLIB_CHANNEL_BROKER_PATH, {});
    if (!broker.start()) return fail("channel broker: " + broker.error());
    std::vector<Row> rows;
    // With sensors: camera subscribed (rendered) and not.
    for (bool camera : {true, false}) {
      support::ServerProcess simulator(
          BEHAVIORLIB_SIMULATOR_PATH,
          {"--channel", broker.address(), "--world", world_path_, "--lock-step"});
      if (!simulator.start()) return fail("simulator: " + simulator.error());
      const std::string name =
          camera ? "all sensors, camera subscribed" : "all sensors, camera not subscribed";
      if (!measure(simulator, broker.address(), name, camera, &rows)) return 1;
      if (int code = simulator.terminate(); code != 0) {
        return fail("simulator exit " + std::to_string(code));
      }
    }
    // Reference: no channel, so no sensors and nothing published.
    {
      support::ServerProcess simulator(BEHAVIORLIB_SIMULATOR_PATH,
                                       {"--world", world_path_, "--lock-step"});
      if (!simulator.start()) return fail("simulator: " + simulator.error());
      if (!measure(simulator, "", "no channel (dynamics, no sensors)", false, &rows)) return 1;
      if (int code = simulator.terminate(); code != 0) {
        return fail("simulator exit " + std::to_string(code));
      }
    }
    if (int code = broker.terminate(); code != 0)
      return fail("broker exit " + std::to_string(code));
    print(rows);
    return 0;
  }

 private:
  int fail(const std::string& what) {
    std::fprintf(stderr, "sim_sensors_bench: %s\n", what.c_str());
    return 1;
  }

  bool setScale(v1::Simulator::Stub& sim, bool lock_step, double scale) {
    v1::SetTimeScaleRequest request;
    request.set_lock_step(lock_step);
    request.set_time_scale(scale);
    v1::SetTimeScaleResponse response;
    const grpc::Status s = sim.SetTimeScale(context().get(), request, &response);
    if (!s.ok()) fail("SetTimeScale: " + s.error_message());
    return s.ok();
  }

  bool step(v1::Simulator::Stub& sim, int ms) {
    v1::StepRequest request;
    *request.mutable_duration() = TimeUtil::MillisecondsToDuration(ms);
    v1::StepResponse response;
    const grpc::Status s = sim.Step(context().get(), request, &response);
    if (!s.ok()) fail("Step: " + s.error_message());
    return s.ok();
  }

  /// Fills `row` from the metrics that changed between `a` and `b`.
  static void fromMetrics(const Scrape& a, const Scrape& b, Row* row) {
    auto delta = [&](const std::string& name, const Labels& labels = {}) {
      return b.get(name, labels) - a.get(name, labels);
    };
    const double steps = delta("behaviorlib_simulator_step_seconds_count");
    if (steps > 0) row->step_us = 1e6 * delta("behaviorlib_simulator_step_seconds_sum") / steps;
    const Labels lidar = {{"sensor", "lidar"}}, camera = {{"sensor", "camera"}};
    row->lidar_frames = delta("behaviorlib_simulator_sensor_frame_seconds_count", lidar);
    row->camera_frames = delta("behaviorlib_simulator_sensor_frame_seconds_count", camera);
    if (row->lidar_frames > 0) {
      row->lidar_ms =
          1e3 * delta("behaviorlib_simulator_sensor_frame_seconds_sum", lidar) / row->lidar_frames;
    }
    if (row->camera_frames > 0) {
      row->camera_ms = 1e3 * delta("behaviorlib_simulator_sensor_frame_seconds_sum", camera) /
                       row->camera_frames;
    }
    const Labels busy_lidar = {{"sensor", "lidar"}, {"reason", "worker_busy"}};
    const Labels busy_camera = {{"sensor", "camera"}, {"reason", "worker_busy"}};
    row->lidar_dropped = delta("behaviorlib_simulator_sensor_samples_dropped_total", busy_lidar);
    row->camera_dropped = delta("behaviorlib_simulator_sensor_samples_dropped_total", busy_camera);
    row->imu_samples = delta("behaviorlib_simulator_sensor_samples_total", {{"sensor", "imu"}});
    row->gps_samples = delta("behaviorlib_simulator_sensor_samples_total", {{"sensor", "gps"}});
  }

  bool measure(support::ServerProcess& simulator, const std::string& broker,
               const std::string& name, bool camera, std::vector<Row>* rows) {
    auto sim = v1::Simulator::NewStub(
        grpc::CreateChannel(simulator.address(), grpc::InsecureChannelCredentials()));
    std::unique_ptr<channel::ChannelClient> client;
    std::unique_ptr<channel::Subscription> subscription;
    std::atomic<uint64_t> images{0};
    if (camera) {
      client = std::make_unique<channel::ChannelClient>(broker);
      subscription =
          client->subscribe("robots/drone1/camera/image", {.mode = v1::DELIVERY_MODE_LATEST},
                            [&images](const v1::SubscribeResponse&) { images.fetch_add(1); });
      if (!subscription->waitConnected(seconds(10))) return fail("camera subscription") == 0;
      // The simulator asks the broker for subscribers every 0.5 s.
      std::this_thread::sleep_for(milliseconds(1200));
    }
    const int port = simulator.metricsPort();
    const bool sensors = !broker.empty();

    // Lock-step: Step 1 s at a time.
    if (!step(*sim, 1000)) return false;             // warm-up (and the first camera poll)
    std::this_thread::sleep_for(milliseconds(400));  // the collector runs every 250 ms
    Row locked{name, "lock-step"};
    {
      const Scrape before(port);
      const auto start = std::chrono::steady_clock::now();
      for (int i = 0; i < options_.sim_s; ++i) {
        if (!step(*sim, 1000)) return false;
      }
      locked.wall_s =
          std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
      std::this_thread::sleep_for(milliseconds(400));  // the collector runs every 250 ms
      const Scrape after(port);
      if (!before.ok() || !after.ok()) return fail("GET /metrics failed") == 0;
      locked.sim_s = options_.sim_s;
      locked.rtf = locked.sim_s / locked.wall_s;
      fromMetrics(before, after, &locked);
    }
    // Free-running: at the target's 10x (does everything keep up?) and at
    // the highest time scale (how fast can it go?).
    std::vector<Row> free_rows;
    for (double scale : {10.0, 1000.0}) {
      char mode[64];
      std::snprintf(mode, sizeof mode, "free-running, time scale %g", scale);
      Row free{name, mode};
      if (!setScale(*sim, false, scale)) return false;
      std::this_thread::sleep_for(milliseconds(500));
      const Scrape before(port);
      const auto start = std::chrono::steady_clock::now();
      std::this_thread::sleep_for(std::chrono::duration<double>(options_.window_s));
      const Scrape after(port);
      free.wall_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
      if (!setScale(*sim, true, 1)) return false;
      free.sim_s = after.get("behaviorlib_simulator_time_seconds") -
                   before.get("behaviorlib_simulator_time_seconds");
      // The simulator's own figure since the scale was set (the scraped
      // times are up to one collector period old).
      free.rtf = after.get("behaviorlib_simulator_real_time_factor");
      fromMetrics(before, after, &free);
      if (free.sim_s <= 0) return fail(name + ": simulated time did not advance") == 0;
      free_rows.push_back(free);
    }
    if (sensors && (locked.imu_samples < 100 * options_.sim_s || locked.lidar_frames < 1)) {
      return fail(name + ": the sensors published nothing") == 0;
    }
    if (camera && (locked.camera_frames < 1 || images.load() == 0)) {
      return fail(name + ": no camera frame reached the subscriber") == 0;
    }
    rows->push_back(locked);
    rows->insert(rows->end(), free_rows.begin(), free_rows.end());
    return true;
  }

  void print(const std::vector<Row>& rows) {
    std::printf(
        "| configuration | mode | simulated s | wall s | real-time factor | physics step, mean "
        "(us) | lidar scan, mean (ms) | camera frame, mean (ms) | lidar / camera frames made | "
        "dropped (worker busy) | IMU samples per simulated s |\n");
    std::printf("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n");
    auto ms = [](double v) {
      char buffer[32];
      if (std::isnan(v)) return std::string("—");
      std::snprintf(buffer, sizeof buffer, "%.2f", v);
      return std::string(buffer);
    };
    for (const Row& r : rows) {
      std::printf(
          "| %s | %s | %.1f | %.2f | **%.1fx** | %.2f | %s | %s | %.0f / %.0f | %.0f / %.0f | %.0f "
          "|\n",
          r.configuration.c_str(), r.mode.c_str(), r.sim_s, r.wall_s, r.rtf, r.step_us,
          ms(r.lidar_ms).c_str(), ms(r.camera_ms).c_str(), r.lidar_frames, r.camera_frames,
          r.lidar_dropped, r.camera_dropped, r.sim_s > 0 ? r.imu_samples / r.sim_s : 0.0);
    }
  }

  Options options_;
  std::string world_path_;
};

}  // namespace
}  // namespace behaviorlib::bench

int main(int argc, char** argv) {
  behaviorlib::bench::Options options;
  for (int i = 1; i < argc; ++i) {
    const std::string arg = argv[i];
    auto next = [&]() -> std::string {
      if (i + 1 >= argc) {
        std::fprintf(stderr, "sim_sensors_bench: %s needs a value\n", arg.c_str());
        std::exit(2);
      }
      return argv[++i];
    };
    if (arg == "--smoke") {
      options.smoke = true;
      options.sim_s = 2;
      options.window_s = 1.0;
    } else if (arg == "--sim-s") {
      options.sim_s = std::max(1, std::atoi(next().c_str()));
    } else if (arg == "--window-s") {
      options.window_s = std::atof(next().c_str());
    } else if (arg == "--world") {
      options.world = next();
    } else {
      std::fprintf(stderr,
                   "usage: sim_sensors_bench [--smoke] [--sim-s N] [--window-s S] [--world W]\n");
      return 2;
    }
  }
  return behaviorlib::bench::Bench(options).run();
}
