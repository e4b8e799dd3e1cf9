// closed_loop_bench: the loop every mission depends on. The simulator
// publishes the vehicle's ground-truth pose (100 Hz of simulated time) on the
// data channel; this process (another process, as a controller is) receives
// each sample and answers it with a position setpoint to the simulator's
// FlightController, as a 100 Hz controller does.
//
// Per time scale it reports, in wall time on this host (the broker stamps the
// sample's arrival, CLOCK_REALTIME is shared by the processes):
//   deliver  broker receipt -> the subscriber's callback
//   loop     broker receipt -> the setpoint acknowledged by the FlightController
// and whether the controller saw every state sample: samples the broker
// replaced before delivery (latest-only subscription) plus gaps in the
// samples' simulated stamps (the simulator's own publisher falling behind).
// The highest scale with no missed sample is the one the end-to-end tests may
// use for a 100 Hz controller. The simulator runs with its defaults: every
// sensor publishing at its default rate (nobody subscribes to the camera, so
// it does not render), as in a mission.
//
//   closed_loop_bench                 # full sweep (about 30 s), markdown table
//   closed_loop_bench --smoke         # one short scale: fails on errors only
//   closed_loop_bench --scales 1,10,50 --window-s 3
//
// Exit code 1 when something is broken (a server does not start, no sample
// arrives, a setpoint is refused); timings never fail the run.

#include <google/protobuf/util/time_util.h>
#include <grpcpp/grpcpp.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <mutex>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "behaviorlib/channel/channel_client.h"
#include "behaviorlib/v1/platform.grpc.pb.h"
#include "behaviorlib/v1/simulator.grpc.pb.h"
#include "behaviorlib/v1/types.pb.h"
#include "support/server_process.h"

namespace behaviorlib::bench {
namespace {

using google::protobuf::util::TimeUtil;
using std::chrono::milliseconds;
using std::chrono::seconds;

constexpr const char* kRobot = "drone1";
constexpr double kStatePeriodS = 0.01;  // ground truth at 100 Hz simulated

struct Options {
  bool smoke = false;
  std::vector<double> scales = {1, 2, 5, 10, 20, 50, 100, 200};
  double window_s = 2.0;
};

double percentile(std::vector<double> v, double p) {
  if (v.empty()) return NAN;
  std::sort(v.begin(), v.end());
  const size_t i = std::min(v.size() - 1, static_cast<size_t>(p * static_cast<double>(v.size())));
  return v[i];
}

double wallNowUs() {
  return std::chrono::duration<double, std::micro>(
             std::chrono::system_clock::now().time_since_epoch())
      .count();
}

std::unique_ptr<grpc::ClientContext> context(std::chrono::milliseconds timeout = seconds(5)) {
  auto ctx = std::make_unique<grpc::ClientContext>();
  ctx->set_deadline(std::chrono::system_clock::now() + timeout);
  return ctx;
}

struct ScaleResult {
  double scale = 0;
  double achieved_scale = 0;
  uint64_t samples = 0;
  uint64_t replaced = 0;    // latest-only: the broker replaced it before delivery
  uint64_t stamp_gaps = 0;  // simulated stamps further apart than one period
  uint64_t refused = 0;
  std::vector<double> deliver_us, loop_us;
};

class Bench {
 public:
  explicit Bench(Options options) : options_(std::move(options)) {}

  int run() {
    support::ServerProcess broker(BEHAVIORLIB_CHANNEL_BROKER_PATH, {});
    if (!broker.start()) return fail("channel broker: " + broker.error());
    support::ServerProcess simulator(
        BEHAVIORLIB_SIMULATOR_PATH,
        {"--channel", broker.address(), "--vehicles", kRobot, "--time-scale", "1"});
    if (!simulator.start()) return fail("simulator: " + simulator.error());
    auto channel = grpc::CreateChannel(simulator.address(), grpc::InsecureChannelCredentials());
    flight_ = v1::FlightController::NewStub(channel);
    sim_ = v1::Simulator::NewStub(channel);
    client_ = std::make_unique<channel::ChannelClient>(broker.address());

    if (!takeOff() || !startController()) return 1;
    std::vector<ScaleResult> results;
    for (double scale : options_.scales) {
      ScaleResult r;
      if (!measure(scale, &r)) return 1;
      results.push_back(std::move(r));
    }
    print(results);
    subscription_.reset();
    if (int code = simulator.terminate(); code != 0)
      return fail("simulator exit " + std::to_string(code));
    if (int code = broker.terminate(); code != 0)
      return fail("broker exit " + std::to_string(code));
    return 0;
  }

 private:
  int fail(const std::string& what) {
    std::fprintf(stderr, "closed_loop_bench: %s\n", what.c_str());
    return 1;
  }

  bool setScale(double scale) {
    v1::SetTimeScaleRequest request;
    request.set_time_scale(scale);
    v1::SetTimeScaleResponse response;
    auto status = sim_->SetTimeScale(context().get(), request, &response);
    if (!status.ok()) fail("SetTimeScale: " + status.error_message());
    return status.ok();
  }

  bool takeOff() {
    if (!setScale(10)) return false;
    v1::AcquireLeaseRequest lease_request;
    lease_request.set_robot_id(kRobot);
    lease_request.set_holder("closed_loop_bench");
    *lease_request.mutable_ttl() = TimeUtil::SecondsToDuration(10);
    v1::AcquireLeaseResponse lease;
    if (auto s = flight_->AcquireLease(context().get(), lease_request, &lease); !s.ok()) {
      return fail("AcquireLease: " + s.error_message()) == 0;
    }
    lease_id_ = lease.lease_id();
    v1::ExecuteFlightActionRequest action;
    action.set_robot_id(kRobot);
    action.set_lease_id(lease_id_);
    action.set_action(v1::FLIGHT_ACTION_TAKE_OFF);
    action.set_takeoff_altitude_m(2.0);
    v1::ExecuteFlightActionResponse reply;
    if (auto s = flight_->ExecuteFlightAction(context().get(), action, &reply); !s.ok()) {
      return fail("TAKE_OFF: " + s.error_message()) == 0;
    }
    // Wait for HOVERING through the platform's own state stream.
    v1::WatchFlightStateRequest watch;
    watch.set_robot_id(kRobot);
    auto ctx = context(seconds(20));
    auto reader = flight_->WatchFlightState(ctx.get(), watch);
    v1::WatchFlightStateResponse state;
    while (reader->Read(&state)) {
      if (state.status().state() == v1::FLIGHT_STATE_HOVERING) {
        ctx->TryCancel();
        reader->Finish();
        return true;
      }
    }
    return fail("the vehicle did not reach HOVERING after TAKE_OFF") == 0;
  }

  // Answers every delivered sample with a setpoint (always: a pause would
  // let the lease lapse) and records it while a window is open.
  bool startController() {
    channel::SubscribeOptions options;
    options.mode = v1::DELIVERY_MODE_LATEST;
    subscription_ =
        client_->subscribe(std::string("robots/") + kRobot + "/ground_truth/pose", options,
                           [this](const v1::SubscribeResponse& response) { onSample(response); });
    if (!subscription_->waitConnected(seconds(5))) return fail("subscription did not connect") == 0;
    return true;
  }

  void onSample(const v1::SubscribeResponse& response) {
    const double received_us = wallNowUs();
    v1::PoseStamped pose;
    if (!response.sample().UnpackTo(&pose)) return;
    v1::SetpointRequest setpoint;
    setpoint.set_robot_id(kRobot);
    {
      std::lock_guard lock(mutex_);
      setpoint.set_lease_id(lease_id_);
    }
    setpoint.mutable_position_yaw()->mutable_position_m()->set_z(2.0);
    v1::SendSetpointResponse reply;
    const grpc::Status status = flight_->SendSetpoint(context().get(), setpoint, &reply);
    const double acked_us = wallNowUs();
    const double broker_us =
        static_cast<double>(TimeUtil::TimestampToMicroseconds(response.receive_time()));
    const double stamp_s =
        static_cast<double>(TimeUtil::TimestampToNanoseconds(pose.header().stamp())) * 1e-9;
    std::lock_guard lock(mutex_);
    if (!status.ok()) last_error_ = status.error_message();
    if (window_ == nullptr) return;
    ScaleResult& r = *window_;
    if (!status.ok()) ++r.refused;
    if (r.samples == 0) {
      first_stamp_s_ = stamp_s;
      first_wall_us_ = received_us;
      dropped_at_start_ = response.dropped_count();
    } else if (stamp_s - last_stamp_s_ > 1.5 * kStatePeriodS) {
      r.stamp_gaps +=
          static_cast<uint64_t>(std::lround((stamp_s - last_stamp_s_) / kStatePeriodS)) - 1;
    }
    r.replaced = response.dropped_count() - dropped_at_start_;
    last_stamp_s_ = stamp_s;
    last_wall_us_ = received_us;
    ++r.samples;
    r.deliver_us.push_back(received_us - broker_us);
    r.loop_us.push_back(acked_us - broker_us);
  }

  // A fresh lease before each window: at a scale the simulator cannot
  // sustain, setpoints come too late for the lease and it lapses (counted as
  // refused setpoints in that window).
  bool renewLease() {
    v1::AcquireLeaseRequest request;
    request.set_robot_id(kRobot);
    request.set_holder("closed_loop_bench");
    request.set_preempt(true);
    *request.mutable_ttl() = TimeUtil::SecondsToDuration(10);
    v1::AcquireLeaseResponse lease;
    if (auto s = flight_->AcquireLease(context().get(), request, &lease); !s.ok()) {
      return fail("AcquireLease: " + s.error_message()) == 0;
    }
    std::lock_guard lock(mutex_);
    lease_id_ = lease.lease_id();
    return true;
  }

  // One window at `scale`.
  bool measure(double scale, ScaleResult* r) {
    if (!setScale(scale) || !renewLease()) return false;
    r->scale = scale;
    std::this_thread::sleep_for(milliseconds(300));  // let the pacing settle
    {
      std::lock_guard lock(mutex_);
      window_ = r;
    }
    std::this_thread::sleep_for(std::chrono::duration<double>(options_.window_s));
    std::lock_guard lock(mutex_);
    window_ = nullptr;
    if (r->samples < 2)
      return fail("no state samples arrived at scale " + std::to_string(scale)) == 0;
    // A replaced sample also leaves a gap in the stamps: count it once.
    r->stamp_gaps = r->stamp_gaps > r->replaced ? r->stamp_gaps - r->replaced : 0;
    r->achieved_scale =
        (last_stamp_s_ - first_stamp_s_) / ((last_wall_us_ - first_wall_us_) * 1e-6);
    return true;
  }

  void print(const std::vector<ScaleResult>& results) {
    std::printf(
        "| time scale | achieved | state rate (wall Hz) | samples | missed (replaced + "
        "publisher gaps + refused) | setpoints refused | deliver p50 / p99 (us) | loop p50 / p99 "
        "(us) |\n");
    std::printf("|---:|---:|---:|---:|---:|---:|---:|---:|\n");
    double best = 0;
    bool none_missed_so_far = true;
    for (const auto& r : results) {
      const uint64_t missed = r.replaced + r.stamp_gaps + r.refused;
      std::printf(
          "| %g | %.1f | %.0f | %llu | %llu (%llu + %llu) | %llu | %.0f / %.0f | %.0f / %.0f |\n",
          r.scale, r.achieved_scale, r.achieved_scale / kStatePeriodS,
          static_cast<unsigned long long>(r.samples), static_cast<unsigned long long>(missed),
          static_cast<unsigned long long>(r.replaced),
          static_cast<unsigned long long>(r.stamp_gaps), static_cast<unsigned long long>(r.refused),
          percentile(r.deliver_us, 0.5), percentile(r.deliver_us, 0.99), percentile(r.loop_us, 0.5),
          percentile(r.loop_us, 0.99));
      none_missed_so_far = none_missed_so_far && missed == 0;
      if (none_missed_so_far) best = r.scale;
    }
    std::printf("\nhighest time scale with every state sample seen by a 100 Hz controller: %g\n",
                best);
  }

  Options options_;
  std::unique_ptr<v1::FlightController::Stub> flight_;
  std::unique_ptr<v1::Simulator::Stub> sim_;
  std::unique_ptr<channel::ChannelClient> client_;
  std::unique_ptr<channel::Subscription> subscription_;
  std::string lease_id_;

  std::mutex mutex_;
  ScaleResult* window_ = nullptr;  // the open window, if any
  std::string last_error_;
  double first_stamp_s_ = 0, last_stamp_s_ = 0, first_wall_us_ = 0, last_wall_us_ = 0;
  uint64_t dropped_at_start_ = 0;
};

}  // namespace
}  // namespace behaviorlib::bench

int main(int argc, char** argv) {
  behaviorlib::bench::Options options;
  for (int i = 1; i < argc; ++i) {
    const std::string arg = argv[i];
    auto value = [&]() -> std::string {
      if (i + 1 >= argc) {
        std::fprintf(stderr, "closed_loop_bench: %s needs a value\n", arg.c_str());
        std::exit(2);
      }
      return argv[++i];
    };
    if (arg == "--smoke") {
      options.smoke = true;
      options.scales = {10};
      options.window_s = 0.5;
    } else if (arg == "--scales") {
      options.scales.clear();
      std::istringstream in(value());
      for (std::string s; std::getline(in, s, ',');) options.scales.push_back(std::atof(s.c_str()));
    } else if (arg == "--window-s") {
      options.window_s = std::atof(value().c_str());
    } else {
      std::fprintf(stderr,
                   "usage: closed_loop_bench [--smoke] [--scales 1,10,...] [--window-s S]\n");
      return 2;
    }
  }
  return behaviorlib::bench::Bench(options).run();
}
