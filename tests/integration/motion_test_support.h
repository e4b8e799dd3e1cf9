#pragma once

// What the motion-system integration tests share: the real processes (the
// channel broker, the simulator at 5x with a fixed seed, basic_quadrotor_behaviors
// for SELF_LOCALIZE_WITH_GROUND_TRUTH / TAKE_OFF / LAND, and the motion
// systems under test) on free loopback ports; a client per behavior system
// (generic lifecycle calls, the event stream, waits on one activation's end);
// and the simulator's ground truth (Simulator.WatchState) recorded in the
// background, to measure tracking on the truth rather than on the estimate.

#include <google/protobuf/struct.pb.h>
#include <google/protobuf/util/json_util.h>
#include <google/protobuf/util/time_util.h>
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>

#include <Eigen/Core>
#include <algorithm>
#include <chrono>
#include <cmath>
#include <condition_variable>
#include <cstdio>
#include <deque>
#include <fstream>
#include <memory>
#include <mutex>
#include <optional>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "behaviorlib/v1/behavior.grpc.pb.h"
#include "behaviorlib/v1/platform.grpc.pb.h"
#include "behaviorlib/v1/simulator.grpc.pb.h"
#include "support/deterministic.h"
#include "support/server_process.h"

namespace motion_test {

namespace v1 = behaviorlib::v1;
using google::protobuf::util::TimeUtil;
using std::chrono::milliseconds;
using std::chrono::seconds;
using WallClock = std::chrono::steady_clock;

inline constexpr char kRobot[] = "drone1";
/// Fixed seed of every random process in the simulator.
inline constexpr char kSeed[] = "7";

inline std::unique_ptr<grpc::ClientContext> deadline(milliseconds timeout = seconds(5)) {
  auto context = std::make_unique<grpc::ClientContext>();
  context->set_deadline(std::chrono::system_clock::now() + timeout);
  return context;
}

inline std::string describe(const grpc::Status& s) {
  return std::to_string(static_cast<int>(s.error_code())) + " " + s.error_message();
}

inline double stampSeconds(const google::protobuf::Timestamp& t) {
  return static_cast<double>(TimeUtil::TimestampToNanoseconds(t)) * 1e-9;
}

inline double degrees(double rad) { return rad * 180.0 / M_PI; }

inline double wrap(double rad) { return std::remainder(rad, 2.0 * M_PI); }

inline double yawOf(const v1::Quaternion& q) {
  return std::atan2(2.0 * (q.w() * q.z() + q.x() * q.y()),
                    1.0 - 2.0 * (q.y() * q.y() + q.z() * q.z()));
}

/// One behavior-system process seen through its generic BehaviorSystem
/// service, with its event stream read on a thread.
class SystemClient {
 public:
  explicit SystemClient(const std::string& address)
      : stub_(v1::BehaviorSystem::NewStub(
            grpc::CreateChannel(address, grpc::InsecureChannelCredentials()))) {
    context_.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(120));
    reader_ = stub_->WatchEvents(&context_, v1::WatchEventsRequest());
    thread_ = std::thread([this] {
      v1::WatchEventsResponse message;
      while (reader_->Read(&message)) {
        if (!message.has_event()) continue;
        std::lock_guard lock(mutex_);
        events_.push_back(message.event());
        cv_.notify_all();
      }
      reader_->Finish();
    });
  }
  ~SystemClient() {
    context_.TryCancel();
    thread_.join();
  }

  /// Activates through the generic API; retried while the system has no
  /// simulated time yet.
  grpc::Status activate(const std::string& behavior, const std::string& json,
                        v1::ActivateResponse* response) {
    google::protobuf::Struct parameters;
    EXPECT_TRUE(google::protobuf::util::JsonStringToMessage(json, &parameters).ok()) << json;
    return activate(behavior, parameters, response);
  }
  /// Activates with parameters built in code (a Struct can carry what JSON
  /// cannot, e.g. NaN); retried while the system has no simulated time yet,
  /// and while its flight-state stream still shows the lease of a commander
  /// that just finished (the coordinator's planner retries such lagging
  /// situations too; a commander still active keeps being refused).
  grpc::Status activate(const std::string& behavior, const google::protobuf::Struct& parameters,
                        v1::ActivateResponse* response) {
    v1::ActivateBehaviorRequest request;
    request.set_behavior(behavior);
    *request.mutable_parameters() = parameters;
    grpc::Status status;
    for (int attempt = 0; attempt < 100; ++attempt) {
      status = stub_->ActivateBehavior(deadline().get(), request, response);
      const std::string& message = status.error_message();
      if (status.ok() || (message.find("no time yet") == std::string::npos &&
                          message.find("only one commander at a time") == std::string::npos)) {
        break;
      }
      std::this_thread::sleep_for(milliseconds(20));
    }
    return status;
  }
  /// Activates and expects success; the activation id.
  std::string start(const std::string& behavior, const std::string& json) {
    v1::ActivateResponse response;
    const grpc::Status status = activate(behavior, json, &response);
    EXPECT_TRUE(status.ok()) << behavior << ": " << describe(status);
    return response.activation_id();
  }
  /// ModifyBehavior with the parameters in `json` (fields left out keep their values).
  grpc::Status modify(const std::string& behavior, const std::string& json) {
    v1::ModifyBehaviorRequest request;
    request.set_behavior(behavior);
    EXPECT_TRUE(
        google::protobuf::util::JsonStringToMessage(json, request.mutable_parameters()).ok())
        << json;
    v1::ModifyResponse response;
    return stub_->ModifyBehavior(deadline().get(), request, &response);
  }
  grpc::Status deactivate(const std::string& behavior) {
    v1::DeactivateBehaviorRequest request;
    request.set_behavior(behavior);
    v1::DeactivateResponse response;
    return stub_->DeactivateBehavior(deadline().get(), request, &response);
  }
  v1::CheckSituationResponse checkSituation(const std::string& behavior) {
    v1::CheckBehaviorSituationRequest request;
    request.set_behavior(behavior);
    v1::CheckSituationResponse response;
    const grpc::Status status = stub_->CheckBehaviorSituation(deadline().get(), request, &response);
    EXPECT_TRUE(status.ok()) << describe(status);
    return response;
  }
  /// The activated event of `activation_id`, if seen.
  std::optional<v1::BehaviorEvent> activated(const std::string& activation_id) {
    std::lock_guard lock(mutex_);
    for (const auto& e : events_) {
      if (e.activation_id() == activation_id && e.has_activated()) return e;
    }
    return std::nullopt;
  }
  /// The finished event of `activation_id`, or nullopt after `timeout` (wall).
  std::optional<v1::BehaviorEvent> finished(const std::string& activation_id,
                                            milliseconds timeout = seconds(20)) {
    std::unique_lock lock(mutex_);
    std::optional<v1::BehaviorEvent> found;
    cv_.wait_for(lock, timeout, [&] {
      for (const auto& e : events_) {
        if (e.activation_id() == activation_id && e.has_finished()) {
          found = e;
          return true;
        }
      }
      return false;
    });
    return found;
  }

 private:
  std::unique_ptr<v1::BehaviorSystem::Stub> stub_;
  grpc::ClientContext context_;
  std::unique_ptr<grpc::ClientReader<v1::WatchEventsResponse>> reader_;
  std::thread thread_;
  std::mutex mutex_;
  std::condition_variable cv_;
  std::deque<v1::BehaviorEvent> events_;
};

/// One ground-truth sample.
struct TruthSample {
  double t_s;
  Eigen::Vector3d position_m;
  double yaw_rad;
  v1::FlightState state;
};

/// The simulator's ground truth of kRobot (Simulator.WatchState at 100 Hz of
/// simulated time), recorded on a thread.
class TruthRecorder {
 public:
  explicit TruthRecorder(const std::string& simulator)
      : stub_(v1::Simulator::NewStub(
            grpc::CreateChannel(simulator, grpc::InsecureChannelCredentials()))) {
    v1::WatchStateRequest request;
    request.add_robot_ids(kRobot);
    request.set_rate_hz(100);
    reader_ = stub_->WatchState(&context_, request);
    thread_ = std::thread([this] {
      v1::WatchStateResponse message;
      while (reader_->Read(&message)) {
        const auto& s = message.state();
        const auto& p = s.pose().position_m();
        std::lock_guard lock(mutex_);
        samples_.push_back({stampSeconds(s.header().stamp()),
                            {p.x(), p.y(), p.z()},
                            yawOf(s.pose().orientation()),
                            s.flight_state()});
      }
      reader_->Finish();
    });
  }
  ~TruthRecorder() {
    context_.TryCancel();
    thread_.join();
  }
  /// Samples stamped within [from_s, to_s] of simulated time.
  std::vector<TruthSample> between(double from_s, double to_s) {
    std::lock_guard lock(mutex_);
    std::vector<TruthSample> out;
    for (const auto& s : samples_) {
      if (s.t_s >= from_s && s.t_s <= to_s) out.push_back(s);
    }
    return out;
  }
  std::optional<TruthSample> latest() {
    std::lock_guard lock(mutex_);
    if (samples_.empty()) return std::nullopt;
    return samples_.back();
  }

 private:
  std::unique_ptr<v1::Simulator::Stub> stub_;
  grpc::ClientContext context_;
  std::unique_ptr<grpc::ClientReader<v1::WatchStateResponse>> reader_;
  std::thread thread_;
  std::mutex mutex_;
  std::vector<TruthSample> samples_;
};

/// Waits (at most `timeout` of wall time) until the simulator's time reached
/// `min_s` (its ground truth's stamps): in the deterministic mode, time starts
/// once the first behavior system joined, and a behavior activated before
/// then finds no sensor data.
inline bool waitForSimulatedTime(const std::string& simulator, double min_s,
                                 milliseconds timeout = seconds(10)) {
  auto stub =
      v1::Simulator::NewStub(grpc::CreateChannel(simulator, grpc::InsecureChannelCredentials()));
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + timeout);
  v1::WatchStateRequest request;
  request.add_robot_ids(kRobot);
  request.set_rate_hz(100);
  auto reader = stub->WatchState(&context, request);
  v1::WatchStateResponse message;
  bool reached = false;
  while (!reached && reader->Read(&message)) {
    reached = stampSeconds(message.state().header().stamp()) >= min_s;
  }
  context.TryCancel();
  reader->Finish();
  return reached;
}

/// Distance from `p` to the polyline through `points`.
inline double crossTrack(const Eigen::Vector3d& p, const std::vector<Eigen::Vector3d>& points) {
  double best = (p - points.front()).norm();
  for (size_t i = 1; i < points.size(); ++i) {
    const Eigen::Vector3d d = points[i] - points[i - 1];
    const double length = d.norm();
    if (length < 1e-9) continue;
    const double along = std::clamp((p - points[i - 1]).dot(d / length), 0.0, length);
    best = std::min(best, (p - (points[i - 1] + d / length * along)).norm());
  }
  return best;
}

/// JSON of a path parameter: {"path_m": [{"x":..,"y":..,"z":..}, ...], ...}.
inline std::string pathJson(const std::vector<Eigen::Vector3d>& points,
                            const std::string& extra = "") {
  std::ostringstream out;
  out << "{\"path_m\": [";
  for (size_t i = 0; i < points.size(); ++i) {
    out << (i ? ", " : "") << "{\"x\": " << points[i].x() << ", \"y\": " << points[i].y()
        << ", \"z\": " << points[i].z() << "}";
  }
  out << "]" << (extra.empty() ? "" : ", " + extra) << "}";
  return out.str();
}

/// Flies kRobot through the simulator's FlightController itself (a lease, a
/// take-off, velocity setpoints): for the tests of estimators, whose flight
/// must not depend on the estimate under test.
class Pilot {
 public:
  explicit Pilot(const std::string& simulator)
      : flight_(v1::FlightController::NewStub(
            grpc::CreateChannel(simulator, grpc::InsecureChannelCredentials()))) {}

  /// A 10 s lease, the take-off, and the wait until HOVERING (20 s at most).
  void takeOff(double altitude_m) {
    v1::AcquireLeaseRequest lease;
    lease.set_robot_id(kRobot);
    lease.set_holder("test pilot");
    *lease.mutable_ttl() = TimeUtil::SecondsToDuration(10);
    v1::AcquireLeaseResponse leased;
    ASSERT_TRUE(flight_->AcquireLease(deadline().get(), lease, &leased).ok());
    lease_id_ = leased.lease_id();
    v1::ExecuteFlightActionRequest action;
    action.set_robot_id(kRobot);
    action.set_lease_id(lease_id_);
    action.set_action(v1::FLIGHT_ACTION_TAKE_OFF);
    action.set_takeoff_altitude_m(altitude_m);
    v1::ExecuteFlightActionResponse done;
    ASSERT_TRUE(flight_->ExecuteFlightAction(deadline().get(), action, &done).ok());
    v1::WatchFlightStateRequest watch;
    watch.set_robot_id(kRobot);
    auto context = deadline(seconds(20));
    auto reader = flight_->WatchFlightState(context.get(), watch);
    v1::WatchFlightStateResponse state;
    bool hovering = false;
    while (!hovering && reader->Read(&state))
      hovering = state.status().state() == v1::FLIGHT_STATE_HOVERING;
    context->TryCancel();
    reader->Finish();
    ASSERT_TRUE(hovering);
  }

  /// A velocity setpoint (world frame, m/s; no yaw rate), which also renews
  /// the lease.
  void setVelocity(double vx, double vy, double vz = 0.0) {
    v1::SetpointRequest setpoint;
    setpoint.set_robot_id(kRobot);
    setpoint.set_lease_id(lease_id_);
    auto* v = setpoint.mutable_velocity_yaw_rate()->mutable_velocity_m_s();
    v->set_x(vx);
    v->set_y(vy);
    v->set_z(vz);
    v1::SendSetpointResponse response;
    ASSERT_TRUE(flight_->SendSetpoint(deadline().get(), setpoint, &response).ok());
  }

 private:
  std::unique_ptr<v1::FlightController::Stub> flight_;
  std::string lease_id_;
};

/// The broker, the simulator (the deterministic mode, fixed seed) and
/// basic_quadrotor_behaviors for localization, take-off and landing.
class FlightStack {
 public:
  /// `world` chooses the simulator's world and vehicles (its one vehicle
  /// in the open field by default).
  bool start(std::string* error, const std::vector<std::string>& world = {"--vehicles", kRobot}) {
    if (!broker_.start()) return *error = "broker: " + broker_.error(), false;
    std::vector<std::string> args = {"--channel", broker_.address(), "--seed", kSeed};
    args.insert(args.end(), world.begin(), world.end());
    simulator_ = std::make_unique<support::ServerProcess>(
        BEHAVIORLIB_SIMULATOR_PATH, support::deterministicSimulatorArgs(args, 1));
    if (!simulator_->start()) return *error = "simulator: " + simulator_->error(), false;
    basic_ = startSystem(BEHAVIORLIB_BASIC_QUADROTOR_BEHAVIORS_PATH, BEHAVIORLIB_BASIC_CONFIG_PATH,
                         error);
    if (!basic_) return false;
    if (!waitForSimulatedTime(simulator_->address(), 0.1)) {
      return *error = "simulated time did not start", false;
    }
    basic_client_ = std::make_unique<SystemClient>(basic_->address());
    truth_ = std::make_unique<TruthRecorder>(simulator_->address());
    flight_ = v1::FlightController::NewStub(
        grpc::CreateChannel(simulator_->address(), grpc::InsecureChannelCredentials()));
    return true;
  }

  /// Starts a behavior system on this stack (--clock sim following the time
  /// grants, --channel, --flight-controller, --config, then `extra`).
  std::unique_ptr<support::ServerProcess> startSystem(const std::string& binary,
                                                      const std::string& config, std::string* error,
                                                      const std::vector<std::string>& extra = {}) {
    std::vector<std::string> args = {
        "--robot-id", kRobot, "--channel",           broker_.address(),
        "--clock",    "sim",  "--flight-controller", simulator_->address(),
        "--config",   config};
    args.insert(args.end(), extra.begin(), extra.end());
    auto system = std::make_unique<support::ServerProcess>(
        binary, support::followTimeArgs(args, simulator_->address()));
    if (!system->start()) {
      *error = binary + ": " + system->error();
      return nullptr;
    }
    return system;
  }

  /// Kills the processes (SIGKILL: an orderly exit is checked where it matters).
  void stop() {
    truth_.reset();
    basic_client_.reset();
    if (basic_ && basic_->running()) basic_->kill();
  }

  /// SELF_LOCALIZE_WITH_GROUND_TRUTH, then TAKE_OFF to `altitude_m`
  /// (GOAL_ACHIEVED expected).
  void localizeAndTakeOff(double altitude_m) {
    localization_ = basic_client_->start("SELF_LOCALIZE_WITH_GROUND_TRUTH", "{}");
    ASSERT_FALSE(localization_.empty());
    // The first estimate takes a few samples to reach the channel.
    ASSERT_TRUE(
        waitFor([&] { return basic_client_->checkSituation("TAKE_OFF").feasible(); }, seconds(5)))
        << basic_client_->checkSituation("TAKE_OFF").ShortDebugString();
    const std::string take_off =
        basic_client_->start("TAKE_OFF", "{\"altitude_m\": " + std::to_string(altitude_m) + "}");
    ASSERT_FALSE(take_off.empty());
    const auto finished = basic_client_->finished(take_off);
    ASSERT_TRUE(finished) << "TAKE_OFF did not finish";
    ASSERT_EQ(finished->finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED)
        << finished->ShortDebugString();
  }

  /// LAND (GOAL_ACHIEVED expected) and the platform LANDED.
  void land() {
    const std::string land = basic_client_->start("LAND", "{}");
    ASSERT_FALSE(land.empty()) << "localization: "
                               << basic_client_->finished(localization_, milliseconds(0))
                                      .value_or(v1::BehaviorEvent())
                                      .ShortDebugString();
    const auto finished = basic_client_->finished(land, seconds(30));
    ASSERT_TRUE(finished) << "LAND did not finish";
    EXPECT_EQ(finished->finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED)
        << finished->ShortDebugString();
    EXPECT_EQ(flightStatus().state(), v1::FLIGHT_STATE_LANDED);
  }

  /// kRobot's flight status as the simulator reports it.
  v1::FlightStatus flightStatus() {
    auto context = deadline();
    v1::WatchFlightStateRequest request;
    request.set_robot_id(kRobot);
    auto reader = flight_->WatchFlightState(context.get(), request);
    v1::WatchFlightStateResponse message;
    EXPECT_TRUE(reader->Read(&message));
    context->TryCancel();
    reader->Finish();
    return message.status();
  }

  /// Waits (wall time, bounded) until `condition` holds; returns it.
  template <class F>
  static bool waitFor(F condition, milliseconds timeout = seconds(10)) {
    const auto until = WallClock::now() + timeout;
    while (!condition()) {
      if (WallClock::now() > until) return false;
      std::this_thread::sleep_for(milliseconds(10));
    }
    return true;
  }

  /// Waits until `seconds` of simulated time have passed (on the ground
  /// truth's stamps; at most 30 s of wall time).
  void sleepSim(double seconds) {
    const auto start = truth_->latest();
    const double from = start ? start->t_s : 0.0;
    waitFor(
        [&] {
          const auto now = truth_->latest();
          return now && now->t_s >= from + seconds;
        },
        std::chrono::seconds(30));
  }

  SystemClient& basic() { return *basic_client_; }
  TruthRecorder& truth() { return *truth_; }
  support::ServerProcess& broker() { return broker_; }
  support::ServerProcess& simulator() { return *simulator_; }
  support::ServerProcess& basicProcess() { return *basic_; }
  const std::string& localization() const { return localization_; }

 private:
  support::ServerProcess broker_{BEHAVIORLIB_CHANNEL_BROKER_PATH, {}};
  std::unique_ptr<support::ServerProcess> simulator_;
  std::unique_ptr<support::ServerProcess> basic_;
  std::unique_ptr<SystemClient> basic_client_;
  std::unique_ptr<TruthRecorder> truth_;
  std::unique_ptr<v1::FlightController::Stub> flight_;
  std::string localization_;
};

/// Ground-truth tracking of one activation: RMS and maximum cross-track error
/// to the polyline `points` over the samples between its activated and
/// finished events.
struct Tracking {
  double rms_m = 0.0;
  double max_m = 0.0;
  size_t samples = 0;
  double duration_s = 0.0;
};

inline Tracking tracking(TruthRecorder& truth, const v1::BehaviorEvent& activated,
                         const v1::BehaviorEvent& finished,
                         const std::vector<Eigen::Vector3d>& points) {
  Tracking out;
  const double from = stampSeconds(activated.time()), to = stampSeconds(finished.time());
  out.duration_s = to - from;
  double sum = 0.0;
  for (const auto& s : truth.between(from, to)) {
    const double e = crossTrack(s.position_m, points);
    sum += e * e;
    out.max_m = std::max(out.max_m, e);
    ++out.samples;
  }
  if (out.samples > 0) out.rms_m = std::sqrt(sum / static_cast<double>(out.samples));
  return out;
}

/// {"path_m": [{"x": .., "y": .., "z": ..}, ...]} as a Struct built in code
/// (coordinates may be NaN, which JSON cannot carry).
inline google::protobuf::Struct pathStruct(const std::vector<Eigen::Vector3d>& points) {
  google::protobuf::Struct parameters;
  auto* list = (*parameters.mutable_fields())["path_m"].mutable_list_value();
  for (const Eigen::Vector3d& p : points) {
    auto* fields = list->add_values()->mutable_struct_value()->mutable_fields();
    (*fields)["x"].set_number_value(p.x());
    (*fields)["y"].set_number_value(p.y());
    (*fields)["z"].set_number_value(p.z());
  }
  return parameters;
}

/// Writes `text` to a temporary file and returns its path (a test-specific
/// --config).
inline std::string writeTempFile(const std::string& name, const std::string& text) {
  const std::string path = ::testing::TempDir() + name;
  std::ofstream(path) << text;
  return path;
}

/// The contents of a file.
inline std::string readFile(const std::string& path) {
  std::ifstream in(path);
  std::stringstream text;
  text << in.rdbuf();
  return text.str();
}

}  // namespace motion_test
