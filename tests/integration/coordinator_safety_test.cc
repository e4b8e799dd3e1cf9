// The coordinator's safety rules and actions (issue 4, section 7) with the
// real processes on free loopback ports: the channel broker, the simulator
// (3x, fixed seed, fault injection on), basic_quadrotor_behaviors,
// quadrotor_motion_with_pid_control (both registering with the coordinator)
// and the coordinator with the shipped catalog, the simulator as drone1's
// flight controller and the broker for the pose estimates.
//
// What each test asserts is observed outside the coordinator: the flight
// state and lease holder from the simulator's FlightController.WatchFlightState,
// the vehicle from Simulator.WatchState, the mission from GetMission, the
// behaviors' ends from the coordinator's WatchEvents. Waits are bounded; time
// spans of the flight are simulated time (the state's stamps).

#include <gtest/gtest.h>
#include <signal.h>
#include <sys/wait.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <functional>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include "behaviorlib/v1/platform.grpc.pb.h"
#include "behaviorlib/v1/simulator.grpc.pb.h"
#include "coordinator_test_support.h"
#include "support/deterministic.h"
#include "support/run_command.h"
#include "support/server_process.h"

namespace coordinator_test {
namespace {

constexpr char kRobot[] = "drone1";
constexpr char kSeed[] = "7";
/// The coordinator's --grace-period-s (its default).
constexpr double kGraceS = 1.0;
/// The coordinator's --hover-before-land-s.
constexpr double kHoverBeforeLandS = 1.0;
/// The coordinator's --critical-battery: above the behaviors' own limits (0.2
/// to 0.3 in the systems' config.yaml), so that only the coordinator reacts.
constexpr double kCriticalBattery = 0.5;
/// Who holds the lease while the coordinator's safety action commands.
constexpr char kSafetyHolder[] = "drone1/coordinator-safety";
/// Bound on a landing from 1.5 m, wall time (about 3 s of simulated time at
/// the platform's landing speed, plus the hover before it).
constexpr milliseconds kLandBound = seconds(15);
/// Bound on a flight sample or an event that must follow what a test did,
/// wall time: far above any latency, so that only its absence fails, however
/// busy the machine. What a test measures is printed, and bounded only where
/// a wrong design would be slower by the systems' call deadline (3 s).
constexpr milliseconds kMustFollow = seconds(15);

double wallSeconds(SteadyClock::time_point from, SteadyClock::time_point to) {
  return std::chrono::duration<double>(to - from).count();
}

/// Simulated seconds from one flight status to another (their stamps): the
/// vehicle's time, which the coordinator's hover before landing counts
/// (--clock sim), and which runs slower than the host's when the simulator
/// waits for a starved system.
double simSeconds(const v1::FlightStatus& from, const v1::FlightStatus& to) {
  const auto& a = from.header().stamp();
  const auto& b = to.header().stamp();
  return static_cast<double>(b.seconds() - a.seconds()) + (b.nanos() - a.nanos()) * 1e-9;
}

// A mission of drone1: take off to 1.5 m and fly 10 m east and back at
// 1 m/s (long enough for what each test provokes), then land; LAND on abort.
std::string missionText(const std::string& name, const std::string& geofence = "") {
  return "name: " + name +
         "\n"
         "robot: drone1\n"
         "recurrent:\n"
         "  - behavior: SELF_LOCALIZE_WITH_GROUND_TRUTH\n" +
         (geofence.empty() ? "" : "geofence: " + geofence + "\n") +
         "safety:\n"
         "  - behavior: LAND\n"
         "steps:\n"
         "  - name: settle\n"
         "    behavior: WAIT\n"
         "    parameters: {duration_s: 1.0}\n"
         "  - name: take_off\n"
         "    behavior: TAKE_OFF\n"
         "    parameters: {altitude_m: 1.5}\n"
         "    on:\n"
         "      REFUSED: {retry: 2}\n"
         "  - name: fly\n"
         "    behavior: FOLLOW_PATH\n"
         "    parameters:\n"
         "      path_m:\n"
         "        - {x: 10.0, y: 0.0, z: 1.5}\n"
         "        - {x: 0.0, y: 0.0, z: 1.5}\n"
         "      speed_m_s: 1.0\n"
         "  - name: land\n"
         "    behavior: LAND\n";
}

double stampSeconds(const google::protobuf::Timestamp& t) {
  return static_cast<double>(t.seconds()) + 1e-9 * t.nanos();
}

std::string stateName(v1::FlightState state) { return v1::FlightState_Name(state); }

/// drone1's FlightStatus as the simulator's FlightController streams it (the
/// current one, then every change), each with its wall arrival time.
class FlightRecorder {
 public:
  struct Sample {
    SteadyClock::time_point at;
    v1::FlightStatus status;
  };

  explicit FlightRecorder(const std::string& simulator)
      : stub_(v1::FlightController::NewStub(
            grpc::CreateChannel(simulator, grpc::InsecureChannelCredentials()))) {
    context_.set_deadline(std::chrono::system_clock::now() + seconds(90));
    v1::WatchFlightStateRequest request;
    request.set_robot_id(kRobot);
    reader_ = stub_->WatchFlightState(&context_, request);
    thread_ = std::thread([this] {
      v1::WatchFlightStateResponse message;
      while (reader_->Read(&message)) {
        std::lock_guard lock(mutex_);
        samples_.push_back({SteadyClock::now(), message.status()});
        cv_.notify_all();
      }
      reader_->Finish();
    });
  }
  ~FlightRecorder() {
    context_.TryCancel();
    thread_.join();
  }

  size_t size() const {
    std::lock_guard lock(mutex_);
    return samples_.size();
  }
  std::optional<v1::FlightStatus> latest() const {
    std::lock_guard lock(mutex_);
    if (samples_.empty()) return std::nullopt;
    return samples_.back().status;
  }
  std::vector<Sample> since(size_t index) const {
    std::lock_guard lock(mutex_);
    if (index >= samples_.size()) return {};
    return {samples_.begin() + static_cast<std::ptrdiff_t>(index), samples_.end()};
  }
  /// Index of the first sample at or after `from` that matches, waiting up
  /// to `timeout`.
  std::optional<size_t> waitFor(size_t from,
                                const std::function<bool(const v1::FlightStatus&)>& predicate,
                                milliseconds timeout) const {
    std::unique_lock lock(mutex_);
    std::optional<size_t> found;
    cv_.wait_for(lock, timeout, [&] {
      for (size_t i = from; i < samples_.size(); ++i) {
        if (predicate(samples_[i].status)) {
          found = i;
          return true;
        }
      }
      return false;
    });
    return found;
  }
  Sample at(size_t index) const {
    std::lock_guard lock(mutex_);
    return samples_.at(index);
  }
  /// The states of the samples from `from`, for failure messages.
  std::string trace(size_t from = 0) const {
    std::string out;
    for (const auto& s : since(from)) {
      out += stateName(s.status.state()) + "[" + s.status.lease_holder() +
             (s.status.failsafe_active() ? ", failsafe" : "") + "] ";
    }
    return out;
  }

 private:
  std::unique_ptr<v1::FlightController::Stub> stub_;
  grpc::ClientContext context_;
  std::unique_ptr<grpc::ClientReader<v1::WatchFlightStateResponse>> reader_;
  std::thread thread_;
  mutable std::mutex mutex_;
  mutable std::condition_variable cv_;
  std::vector<Sample> samples_;
};

/// drone1's simulated ground truth (Simulator.WatchState at 50 Hz of
/// simulated time): the latest state and the largest x reached.
class VehicleRecorder {
 public:
  explicit VehicleRecorder(const std::string& simulator)
      : stub_(v1::Simulator::NewStub(
            grpc::CreateChannel(simulator, grpc::InsecureChannelCredentials()))) {
    context_.set_deadline(std::chrono::system_clock::now() + seconds(90));
    v1::WatchStateRequest request;
    request.add_robot_ids(kRobot);
    request.set_rate_hz(50);
    reader_ = stub_->WatchState(&context_, request);
    thread_ = std::thread([this] {
      v1::WatchStateResponse message;
      while (reader_->Read(&message)) {
        std::lock_guard lock(mutex_);
        latest_ = message.state();
        max_x_ = std::max(max_x_, message.state().pose().position_m().x());
      }
      reader_->Finish();
    });
  }
  ~VehicleRecorder() {
    context_.TryCancel();
    thread_.join();
  }

  std::optional<v1::VehicleState> latest() const {
    std::lock_guard lock(mutex_);
    return latest_;
  }
  double maxX() const {
    std::lock_guard lock(mutex_);
    return max_x_;
  }
  void resetMaxX() {
    std::lock_guard lock(mutex_);
    max_x_ = latest_ ? latest_->pose().position_m().x() : -1e9;
  }
  double simSeconds() const {
    auto s = latest();
    return s ? stampSeconds(s->header().stamp()) : 0.0;
  }
  /// Waits until `span_s` of simulated time has passed (at most 30 s wall).
  bool sleepSim(double span_s) const {
    const double from = simSeconds();
    return waitUntil([&] { return simSeconds() >= from + span_s; }, seconds(30));
  }

 private:
  std::unique_ptr<v1::Simulator::Stub> stub_;
  grpc::ClientContext context_;
  std::unique_ptr<grpc::ClientReader<v1::WatchStateResponse>> reader_;
  std::thread thread_;
  mutable std::mutex mutex_;
  std::optional<v1::VehicleState> latest_;
  double max_x_ = -1e9;
};

using support::run;

// Runs `command` with a shell, its stderr going to the test's; its exit
// code. Its stdout in `output`; its last line parsed as JSON into `message`
// (behaviorctl prints one JSON object per line).
int runJson(const std::string& command, google::protobuf::Message* message, std::string* output) {
  FILE* pipe = popen(command.c_str(), "r");
  if (!pipe) return -1;
  char buffer[4096];
  size_t n;
  while ((n = fread(buffer, 1, sizeof(buffer), pipe)) > 0) output->append(buffer, n);
  const int status = pclose(pipe);
  std::string last = *output;
  while (!last.empty() && last.back() == '\n') last.pop_back();
  if (const auto newline = last.rfind('\n'); newline != std::string::npos) {
    last = last.substr(newline + 1);
  }
  google::protobuf::util::JsonParseOptions options;
  options.ignore_unknown_fields = false;
  message->Clear();
  const auto parsed = google::protobuf::util::JsonStringToMessage(last, message, options);
  EXPECT_TRUE(parsed.ok()) << command << " printed: " << *output << "\n" << parsed.ToString();
  return WIFEXITED(status) ? WEXITSTATUS(status) : -1;
}

class CoordinatorSafetyTest : public ::testing::Test {
 protected:
  void SetUp() override {
    ASSERT_TRUE(broker_.start()) << broker_.error();
    simulator_ = std::make_unique<support::ServerProcess>(
        BEHAVIORLIB_SIMULATOR_PATH,
        // A frozen busy system holds time for 0.25 s of wall time only (the
        // default 5 s): in the hung-controller test the lease (1 s of
        // simulated time) then expires well before the coordinator's
        // watchdog (kGraceS of wall time) notices the frozen system.
        support::deterministicSimulatorArgs(
            {"--channel", broker_.address(), "--vehicles", kRobot, "--seed", kSeed,
             "--enable-fault-injection", "--follower-timeout-s", "0.25"},
            1));
    ASSERT_TRUE(simulator_->start()) << simulator_->error();
    std::vector<std::string> coordinator_args = {"--catalog",
                                                 BEHAVIORLIB_CATALOG_PATH,
                                                 "--flight-controller",
                                                 std::string(kRobot) + "=" + simulator_->address(),
                                                 "--channel",
                                                 broker_.address(),
                                                 "--grace-period-s",
                                                 std::to_string(kGraceS),
                                                 "--critical-battery",
                                                 std::to_string(kCriticalBattery),
                                                 "--hover-before-land-s",
                                                 std::to_string(kHoverBeforeLandS),
                                                 "--clock",
                                                 "sim"};
    for (const auto& arg : extraCoordinatorArgs()) coordinator_args.push_back(arg);
    coordinator_ =
        std::make_unique<support::ServerProcess>(BEHAVIORLIB_COORDINATOR_PATH, coordinator_args);
    ASSERT_TRUE(coordinator_->start()) << coordinator_->error();
    client_ = std::make_unique<CoordinatorClient>(coordinator_->address());
    stub_ = v1::Coordinator::NewStub(
        grpc::CreateChannel(coordinator_->address(), grpc::InsecureChannelCredentials()));
    flight_ = std::make_unique<FlightRecorder>(simulator_->address());
    vehicle_ = std::make_unique<VehicleRecorder>(simulator_->address());
    // Every event of drone1 from the start.
    events_ = std::make_unique<FleetWatcher>(coordinator_->address(),
                                             FleetWatcher::request(0, "", {kRobot}));
    ASSERT_TRUE(events_->start());

    basic_ = startSystem(BEHAVIORLIB_BASIC_QUADROTOR_BEHAVIORS_PATH, BEHAVIORLIB_BASIC_CONFIG_PATH);
    pid_ = startSystem(BEHAVIORLIB_PID_SYSTEM_PATH, BEHAVIORLIB_PID_CONFIG_PATH);
    ASSERT_TRUE(basic_ && pid_);
    ASSERT_TRUE(waitUntil(
        [&] {
          auto systems = client_->listSystems(kRobot);
          int up = 0;
          for (const auto& s : systems.response.systems()) up += s.state() == v1::SYSTEM_STATE_UP;
          return up == 2;
        },
        seconds(15)))
        << client_->listSystems(kRobot).response.ShortDebugString();
    ASSERT_TRUE(waitUntil([&] { return flight_->latest().has_value(); }, kMustFollow));
    ASSERT_EQ(flight_->latest()->state(), v1::FLIGHT_STATE_LANDED);
  }

  /// Flags added to the coordinator's (fixtures of other configurations).
  virtual std::vector<std::string> extraCoordinatorArgs() const { return {}; }

  void TearDown() override {
    events_.reset();
    if (pid_ && pid_->running()) {
      ::kill(pid_->pid(), SIGCONT);  // a test may have stopped it
      pid_->kill();
    }
    if (basic_ && basic_->running()) basic_->kill();
    if (coordinator_ && coordinator_->running()) {
      EXPECT_EQ(coordinator_->terminate(), 0) << "the coordinator stops cleanly";
    }
    flight_.reset();
    vehicle_.reset();
  }

  std::unique_ptr<support::ServerProcess> startSystem(const std::string& binary,
                                                      const std::string& config) {
    auto system = std::make_unique<support::ServerProcess>(
        binary,
        support::followTimeArgs({"--robot-id", kRobot, "--channel", broker_.address(), "--clock",
                                 "sim", "--flight-controller", simulator_->address(), "--config",
                                 config, "--coordinator", coordinator_->address()},
                                simulator_->address()));
    if (!system->start()) {
      ADD_FAILURE() << binary << ": " << system->error();
      return nullptr;
    }
    return system;
  }

  Reply<v1::SafetyActionResponse> emergencyLand(const std::string& robot,
                                                const std::string& reason = "") {
    v1::SafetyActionRequest request;
    request.set_robot_id(robot);
    request.set_reason(reason);
    return unary(*stub_, &v1::Coordinator::Stub::EmergencyLand, request);
  }
  Reply<v1::SafetyActionResponse> kill(const std::string& robot, bool confirm) {
    v1::SafetyActionRequest request;
    request.set_robot_id(robot);
    request.set_confirm(confirm);
    return unary(*stub_, &v1::Coordinator::Stub::Kill, request);
  }

  /// The coordinator's /metrics page once `ready` holds on it, or the last
  /// page read after 10 s (wall). A counter moves just after the state a
  /// test waited for (the mission's end is published, then counted).
  std::string coordinatorMetricsWhen(const std::function<bool(const std::string&)>& ready) {
    std::string text;
    const auto until = SteadyClock::now() + seconds(10);
    for (;;) {
      text = support::httpGet(coordinator_->metricsPort(), "/metrics");
      if (ready(text) || SteadyClock::now() > until) return text;
      std::this_thread::sleep_for(milliseconds(20));
    }
  }
  /// Expects the mission counters of one mission of kRobot that ended with
  /// `outcome` (its cause is not fixed: a step may end on its own while the
  /// vehicle is stood down), and one safety action `action` by `trigger`.
  void expectCounted(const std::string& outcome, const std::string& action,
                     const std::string& trigger) {
    const support::MetricLabels robot = {{"robot", kRobot}};
    const support::MetricLabels ended = {{"robot", kRobot}, {"outcome", outcome}};
    const std::string text = coordinatorMetricsWhen([&](const std::string& t) {
      return metricSum(t, "behaviorlib_coordinator_missions_finished_total", ended) >= 1;
    });
    EXPECT_EQ(metricSum(text, "behaviorlib_coordinator_missions_started_total", robot), 1) << text;
    EXPECT_EQ(metricSum(text, "behaviorlib_coordinator_missions_finished_total", robot), 1) << text;
    EXPECT_EQ(metricSum(text, "behaviorlib_coordinator_missions_finished_total", ended), 1) << text;
    EXPECT_EQ(metricSum(text, "behaviorlib_coordinator_safety_actions_total", robot), 1) << text;
    EXPECT_EQ(metricValue(text, "behaviorlib_coordinator_safety_actions_total",
                          {{"robot", kRobot}, {"action", action}, {"trigger", trigger}}),
              1.0)
        << text;
  }

  std::string startMission(const std::string& text) {
    v1::StartMissionRequest request;
    request.set_text(text);
    auto reply = unary(*stub_, &v1::Coordinator::Stub::StartMission, request);
    EXPECT_TRUE(reply.status.ok()) << describe(reply.status);
    return reply.response.status().mission_id();
  }
  v1::MissionStatus mission(const std::string& id) {
    v1::GetMissionRequest request;
    request.set_mission_id(id);
    auto reply = unary(*stub_, &v1::Coordinator::Stub::GetMission, request);
    EXPECT_TRUE(reply.status.ok()) << describe(reply.status);
    return reply.response.status();
  }
  static bool ended(const v1::MissionStatus& m) { return m.has_end_time(); }
  /// The mission once ended (fails the test if it does not end in time).
  v1::MissionStatus missionEnded(const std::string& id, milliseconds timeout = seconds(20)) {
    v1::MissionStatus status;
    EXPECT_TRUE(waitUntil(
        [&] {
          status = mission(id);
          return ended(status);
        },
        timeout))
        << status.ShortDebugString();
    return status;
  }
  /// The record of the mission's step `name` (its latest attempt).
  static std::optional<v1::MissionStepRecord> step(const v1::MissionStatus& m,
                                                   const std::string& name) {
    for (int i = m.steps_size() - 1; i >= 0; --i) {
      if (m.steps(i).name() == name) return m.steps(i);
    }
    return std::nullopt;
  }

  /// Starts the mission and waits until FOLLOW_PATH flies it east (the
  /// vehicle FLYING and past x = 0.5 m); FOLLOW_PATH's activation id.
  std::string flyMission(const std::string& text, std::string* mission_id) {
    *mission_id = startMission(text);
    if (mission_id->empty()) return "";
    std::string follow;
    const bool flying = waitUntil(
        [&] {
          auto m = mission(*mission_id);
          auto fly = step(m, "fly");
          if (ended(m) || !fly || fly->state() != v1::MISSION_STEP_STATE_RUNNING) return false;
          follow = fly->activation_id();
          auto status = flight_->latest();
          auto vehicle = vehicle_->latest();
          return !follow.empty() && status && status->state() == v1::FLIGHT_STATE_FLYING &&
                 vehicle && vehicle->pose().position_m().x() > 0.5;
        },
        seconds(25));
    EXPECT_TRUE(flying) << mission(*mission_id).ShortDebugString()
                        << "\nflight: " << flight_->trace();
    return flying ? follow : "";
  }

  /// Reads every event that arrives within `timeout` into seen_ until
  /// `predicate` holds for one of them (seen before or now).
  std::optional<v1::BehaviorEvent> waitEvent(
      const std::function<bool(const v1::BehaviorEvent&)>& predicate,
      milliseconds timeout = seconds(10)) {
    const auto deadline = SteadyClock::now() + timeout;
    for (;;) {
      for (const auto& e : seen_) {
        if (predicate(e)) return e;
      }
      const auto left = std::max(
          milliseconds(0), std::chrono::duration_cast<milliseconds>(deadline - SteadyClock::now()));
      auto event = events_->nextEvent(left);  // with 0: only what is queued
      if (!event) return std::nullopt;
      if (event->has_behavior_event()) seen_.push_back(event->behavior_event());
    }
  }
  std::optional<v1::BehaviorEvent> finished(const std::string& activation_id,
                                            milliseconds timeout = seconds(10)) {
    return waitEvent(
        [&](const v1::BehaviorEvent& e) {
          return e.activation_id() == activation_id && e.has_finished();
        },
        timeout);
  }
  /// The activation id of `behavior`'s latest activated event seen so far.
  std::string activationOf(const std::string& behavior) {
    (void)waitEvent([](const v1::BehaviorEvent&) { return false; }, milliseconds(100));
    for (auto it = seen_.rbegin(); it != seen_.rend(); ++it) {
      if (it->behavior() == behavior && it->has_activated()) return it->activation_id();
    }
    return "";
  }
  std::string seenText() const {
    std::string out;
    for (const auto& e : seen_) {
      out += e.behavior() + (e.has_activated() ? " activated" : "") +
             (e.has_finished() ? " finished " + v1::TerminationCause_Name(e.finished().cause()) +
                                     " (" + e.finished().message() + ")"
                               : "") +
             "\n";
    }
    return out;
  }

  /// Waits from flight sample `from` for `state`; its index.
  std::optional<size_t> waitState(size_t from, v1::FlightState state,
                                  milliseconds timeout = kLandBound) {
    return flight_->waitFor(
        from, [&](const v1::FlightStatus& s) { return s.state() == state; }, timeout);
  }
  /// Asserts the vehicle is on the ground, landed, in one piece.
  void expectOnTheGround() {
    auto vehicle = vehicle_->latest();
    ASSERT_TRUE(vehicle);
    EXPECT_FALSE(vehicle->crashed());
    EXPECT_LT(vehicle->pose().position_m().z(), 0.15) << vehicle->ShortDebugString();
  }

  support::ServerProcess broker_{BEHAVIORLIB_CHANNEL_BROKER_PATH, {}};
  std::unique_ptr<support::ServerProcess> simulator_;
  std::unique_ptr<support::ServerProcess> coordinator_;
  std::unique_ptr<support::ServerProcess> basic_;
  std::unique_ptr<support::ServerProcess> pid_;
  std::unique_ptr<CoordinatorClient> client_;
  std::unique_ptr<v1::Coordinator::Stub> stub_;
  std::unique_ptr<FlightRecorder> flight_;
  std::unique_ptr<VehicleRecorder> vehicle_;
  std::unique_ptr<FleetWatcher> events_;
  std::vector<v1::BehaviorEvent> seen_;
};

TEST_F(CoordinatorSafetyTest, EmergencyLandAbortsTheMissionLandsAndInterruptsTheCommanders) {
  std::string id;
  const std::string follow = flyMission(missionText("emergency"), &id);
  ASSERT_FALSE(follow.empty());
  const std::string controller = activationOf("QUADROTOR_PID_MOTION_CONTROL");
  ASSERT_FALSE(controller.empty()) << seenText();

  // Refusals first; none of them touches the vehicle.
  auto unconfirmed = kill(kRobot, false);
  EXPECT_EQ(unconfirmed.status.error_code(), grpc::StatusCode::INVALID_ARGUMENT)
      << describe(unconfirmed.status);
  EXPECT_NE(unconfirmed.status.error_message().find("confirm"), std::string::npos)
      << unconfirmed.status.error_message();
  for (auto reply : {emergencyLand("ghost"), kill("ghost", true)}) {
    EXPECT_EQ(reply.status.error_code(), grpc::StatusCode::NOT_FOUND) << describe(reply.status);
    EXPECT_NE(reply.status.error_message().find("ghost"), std::string::npos);
    EXPECT_NE(reply.status.error_message().find("--flight-controller"), std::string::npos);
  }
  const double x_before = vehicle_->latest()->pose().position_m().x();
  ASSERT_TRUE(vehicle_->sleepSim(1.0));
  EXPECT_EQ(flight_->latest()->state(), v1::FLIGHT_STATE_FLYING) << flight_->trace();
  EXPECT_GT(vehicle_->latest()->pose().position_m().x(), x_before + 0.5) << "still following";
  EXPECT_EQ(mission(id).state(), v1::MISSION_STATE_RUNNING);
  for (const auto& activation : {follow, controller}) {
    EXPECT_FALSE(finished(activation, milliseconds(0))) << seenText();
  }

  const size_t mark = flight_->size();
  const auto requested_at = SteadyClock::now();
  auto landed = emergencyLand(kRobot, "operator saw smoke");
  ASSERT_TRUE(landed.status.ok()) << describe(landed.status);
  EXPECT_NE(landed.response.message().find("EMERGENCY_LAND"), std::string::npos)
      << landed.response.message();
  EXPECT_NE(landed.response.message().find(id), std::string::npos)
      << "names the aborted mission: " << landed.response.message();
  std::printf("EmergencyLand: %s\n", landed.response.message().c_str());

  // The platform's emergency descent (EMERGENCY), then on the ground.
  auto emergency = waitState(mark, v1::FLIGHT_STATE_EMERGENCY, kMustFollow);
  ASSERT_TRUE(emergency) << flight_->trace(mark);
  // The stand-down before it (mission, behaviors) has a budget of 0.5 s.
  const double descending_after_s =
      std::chrono::duration<double>(flight_->at(*emergency).at - requested_at).count();
  std::printf("EmergencyLand: descending %.3f s (wall) after the request\n", descending_after_s);
  // Not held by the stand-down's calls (their deadline is 3 s).
  EXPECT_LT(descending_after_s, 2.5);
  auto down = waitState(*emergency, v1::FLIGHT_STATE_LANDED);
  ASSERT_TRUE(down) << flight_->trace(mark);
  expectOnTheGround();

  const v1::MissionStatus ended = missionEnded(id);
  EXPECT_EQ(ended.state(), v1::MISSION_STATE_ABORTED) << ended.ShortDebugString();
  EXPECT_NE(ended.message().find("emergency land"), std::string::npos) << ended.message();
  EXPECT_NE(ended.message().find("operator saw smoke"), std::string::npos) << ended.message();
  // The vehicle was landed by the action, not by the mission's LAND.
  EXPECT_FALSE(waitEvent([](const v1::BehaviorEvent& e) { return e.behavior() == "LAND"; },
                         milliseconds(300)))
      << seenText();

  // The behaviors that commanded the vehicle were deactivated.
  for (const auto& activation : {follow, controller}) {
    auto end = finished(activation);
    ASSERT_TRUE(end) << activation << "\n" << seenText();
    EXPECT_EQ(end->finished().cause(), v1::TERMINATION_CAUSE_INTERRUPTED)
        << end->ShortDebugString() << "\n"
        << seenText();
  }
  // Counted: the refused Kill is no action.
  expectCounted("aborted", "emergency_land", "operator");
}

TEST_F(CoordinatorSafetyTest, KillThroughBehaviorctlNeedsConfirmThenStopsTheMotors) {
  // Hovering at 1.5 m (TAKE_OFF through the coordinator: its plan activates
  // the self-localization first).
  auto take_off = client_->activate(kRobot, "TAKE_OFF", R"({"altitude_m": 1.5})");
  ASSERT_TRUE(take_off.status.ok()) << describe(take_off.status);
  auto took_off = finished(take_off.response.activation().activation_id(), seconds(20));
  ASSERT_TRUE(took_off) << seenText();
  ASSERT_EQ(took_off->finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED)
      << took_off->ShortDebugString();
  // TAKE_OFF leaves the vehicle hovering (after a HOVER of its own when it
  // ended on a setpoint, which may reach this stream after its end).
  ASSERT_TRUE(waitUntil([&] { return flight_->latest()->state() == v1::FLIGHT_STATE_HOVERING; },
                        kMustFollow))
      << flight_->trace();

  const std::string ctl = std::string(BEHAVIORLIB_BEHAVIORCTL_PATH) + " --coordinator " +
                          coordinator_->address() + " --robot ";
  std::string output;
  EXPECT_EQ(run(ctl + kRobot + " kill", &output), 1) << output;
  EXPECT_NE(output.find("confirm"), std::string::npos) << output;
  output.clear();
  EXPECT_EQ(run(ctl + "ghost emergency-land", &output), 1) << output;
  EXPECT_NE(output.find("ghost"), std::string::npos) << output;
  ASSERT_TRUE(vehicle_->sleepSim(1.0));
  EXPECT_EQ(flight_->latest()->state(), v1::FLIGHT_STATE_HOVERING) << flight_->trace();
  EXPECT_GT(vehicle_->latest()->pose().position_m().z(), 1.2);

  const size_t mark = flight_->size();
  output.clear();
  ASSERT_EQ(run(ctl + kRobot + " kill --confirm 'test of the kill switch'", &output), 0) << output;
  EXPECT_NE(output.find("KILL"), std::string::npos) << output;
  ASSERT_TRUE(waitState(mark, v1::FLIGHT_STATE_EMERGENCY, kMustFollow)) << flight_->trace(mark);
  // Motors off: they spin down within a fraction of a second and the
  // vehicle falls.
  ASSERT_TRUE(vehicle_->sleepSim(0.3));
  auto falling = vehicle_->latest();
  ASSERT_TRUE(falling);
  for (double motor : falling->motor_speed_ratios()) EXPECT_LT(motor, 0.05) << "motors off";
  auto down = flight_->waitFor(
      mark,
      [](const v1::FlightStatus& s) {
        return s.state() == v1::FLIGHT_STATE_LANDED || s.state() == v1::FLIGHT_STATE_CRASHED;
      },
      kLandBound);
  ASSERT_TRUE(down) << flight_->trace(mark);
  EXPECT_LT(vehicle_->latest()->pose().position_m().z(), 0.15);
}

TEST_F(CoordinatorSafetyTest, KilledMotionControllerIsReportedThenTheVehicleHoversAndLands) {
  std::string id;
  const std::string follow = flyMission(missionText("controller_failure"), &id);
  ASSERT_FALSE(follow.empty());
  const std::string controller = activationOf("QUADROTOR_PID_MOTION_CONTROL");
  ASSERT_FALSE(controller.empty()) << seenText();

  const size_t mark = flight_->size();
  const auto killed_at = SteadyClock::now();
  pid_->kill();  // SIGKILL, during FOLLOW_PATH

  // The coordinator's subscribers get PROCESS_FAILURE for both behaviors of
  // the dead process, once its grace period has passed.
  for (const auto& activation : {controller, follow}) {
    auto end = finished(activation, kMustFollow);
    ASSERT_TRUE(end) << activation << "\n" << seenText();
    EXPECT_EQ(end->finished().cause(), v1::TERMINATION_CAUSE_PROCESS_FAILURE)
        << end->ShortDebugString();
  }
  const double reported_s = std::chrono::duration<double>(SteadyClock::now() - killed_at).count();
  EXPECT_LT(reported_s, kGraceS + 2.5) << "PROCESS_FAILURE reported after the grace period";

  // The coordinator takes the vehicle: hover, then land, under its lease.
  auto hover = flight_->waitFor(
      mark,
      [](const v1::FlightStatus& s) {
        return s.state() == v1::FLIGHT_STATE_HOVERING && s.lease_holder() == kSafetyHolder;
      },
      kMustFollow);
  ASSERT_TRUE(hover) << flight_->trace(mark);
  auto landing = waitState(*hover, v1::FLIGHT_STATE_LANDING);
  ASSERT_TRUE(landing) << flight_->trace(mark);
  EXPECT_EQ(flight_->at(*landing).status.lease_holder(), kSafetyHolder) << flight_->trace(mark);
  // The hover lasts the vehicle's time: its simulated seconds are bounded.
  const double hovered_s = simSeconds(flight_->at(*hover).status, flight_->at(*landing).status);
  EXPECT_GE(hovered_s, 0.8 * kHoverBeforeLandS) << flight_->trace(mark);
  ASSERT_TRUE(waitState(*landing, v1::FLIGHT_STATE_LANDED)) << flight_->trace(mark);
  const double landed_s = std::chrono::duration<double>(SteadyClock::now() - killed_at).count();
  EXPECT_LT(landed_s, 10.0) << "landed within the bound after the kill";
  expectOnTheGround();

  const v1::MissionStatus ended = missionEnded(id);
  EXPECT_EQ(ended.state(), v1::MISSION_STATE_ABORTED) << ended.ShortDebugString();
  EXPECT_NE(ended.message().find("motion controller"), std::string::npos) << ended.message();
  std::printf(
      "kill -9 of the PID system: PROCESS_FAILURE after %.2f s, LANDED after %.2f s "
      "(wall), after a hover of %.2f simulated s; mission: %s\n",
      reported_s, landed_s, hovered_s, ended.message().c_str());
}

TEST_F(CoordinatorSafetyTest, CriticalBatteryLandsTheVehicleAndAbortsTheMission) {
  std::string id;
  const std::string follow = flyMission(missionText("battery"), &id);
  ASSERT_FALSE(follow.empty());
  const double before = flight_->latest()->battery_ratio();
  ASSERT_GT(before, kCriticalBattery + 0.3);

  // A failing cell: the charge drops below the coordinator's threshold, but
  // stays above the behaviors' own limits.
  auto sim = v1::Simulator::NewStub(
      grpc::CreateChannel(simulator_->address(), grpc::InsecureChannelCredentials()));
  v1::InjectFailureRequest drop;
  drop.set_robot_id(kRobot);
  drop.set_component(v1::FAILURE_COMPONENT_BATTERY);
  drop.set_type(v1::FAILURE_TYPE_DEGRADED);
  drop.set_intensity(before - kCriticalBattery + 0.1);
  const size_t mark = flight_->size();
  auto injected = unary(*sim, &v1::Simulator::Stub::InjectFailure, drop);
  ASSERT_TRUE(injected.status.ok()) << describe(injected.status);

  auto low = flight_->waitFor(
      mark, [](const v1::FlightStatus& s) { return s.battery_ratio() < kCriticalBattery; },
      kMustFollow);
  ASSERT_TRUE(low) << flight_->trace(mark);
  EXPECT_GT(flight_->at(*low).status.battery_ratio(), 0.3);
  // Landed by the coordinator (its lease), straight away: no hover first.
  auto landing = waitState(*low, v1::FLIGHT_STATE_LANDING, kMustFollow);
  ASSERT_TRUE(landing) << flight_->trace(mark);
  EXPECT_EQ(flight_->at(*landing).status.lease_holder(), kSafetyHolder) << flight_->trace(mark);
  for (size_t i = *low; i < *landing; ++i) {
    EXPECT_NE(flight_->at(i).status.state(), v1::FLIGHT_STATE_HOVERING) << flight_->trace(mark);
  }
  ASSERT_TRUE(waitState(*landing, v1::FLIGHT_STATE_LANDED)) << flight_->trace(mark);
  expectOnTheGround();

  const v1::MissionStatus ended = missionEnded(id);
  EXPECT_EQ(ended.state(), v1::MISSION_STATE_ABORTED) << ended.ShortDebugString();
  EXPECT_NE(ended.message().find("battery"), std::string::npos) << ended.message();
  auto end = finished(follow);
  ASSERT_TRUE(end) << seenText();
  EXPECT_NE(end->finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED);
  expectCounted("aborted", "land", "battery");
}

TEST_F(CoordinatorSafetyTest, LeavingTheMissionGeofenceAbortsItAndItsSafetyStepLands) {
  constexpr double kFenceX = 3.0;
  std::string id;
  const std::string follow =
      flyMission(missionText("geofence", "{min_m: [-2, -2, -1], max_m: [3, 2, 4]}"), &id);
  ASSERT_FALSE(follow.empty());
  const size_t mark = flight_->size();

  const v1::MissionStatus ended = missionEnded(id, seconds(25));
  EXPECT_EQ(ended.state(), v1::MISSION_STATE_ABORTED) << ended.ShortDebugString();
  EXPECT_NE(ended.message().find("geofence"), std::string::npos) << ended.message();
  // FOLLOW_PATH went on to x = 10 m: it was stopped.
  auto stopped = finished(follow);
  ASSERT_TRUE(stopped) << seenText();
  EXPECT_NE(stopped->finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED);

  // The coordinator held the vehicle (hover: FOLLOW_PATH alone keeps it
  // FLYING), then the mission's safety step LAND landed it (under LAND's
  // lease, not the coordinator's).
  auto hover = waitState(mark, v1::FLIGHT_STATE_HOVERING, kMustFollow);
  ASSERT_TRUE(hover) << flight_->trace(mark);
  auto land = waitEvent(
      [](const v1::BehaviorEvent& e) { return e.behavior() == "LAND" && e.has_activated(); });
  ASSERT_TRUE(land) << seenText() << "mission: " << ended.message();
  auto landed = finished(land->activation_id(), kLandBound);
  ASSERT_TRUE(landed) << seenText();
  EXPECT_EQ(landed->finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED)
      << landed->ShortDebugString();
  auto landing = waitState(mark, v1::FLIGHT_STATE_LANDING, kMustFollow);
  ASSERT_TRUE(landing) << flight_->trace(mark);
  EXPECT_NE(flight_->at(*landing).status.lease_holder(), kSafetyHolder) << flight_->trace(mark);
  ASSERT_TRUE(waitState(*landing, v1::FLIGHT_STATE_LANDED, kMustFollow)) << flight_->trace(mark);
  expectOnTheGround();
  const double overshoot = vehicle_->maxX() - kFenceX;
  std::printf("geofence at x = %.1f m: the vehicle went %.2f m past it; mission: %s\n", kFenceX,
              overshoot, ended.message().c_str());
  // Reacting takes a pose estimate through the broker, a policy poll (0.1 s)
  // and two calls to the platform, at 1 m/s and 3x; then the vehicle brakes.
  EXPECT_LT(overshoot, 3.0) << "held near the fence, far from the path's end at x = 10 m";
}

// Seconds of wall time between two flight samples.

// The motion controller hangs (SIGSTOP of the PID system during
// FOLLOW_PATH): it stops renewing its lease, the platform's lease failsafe
// engages (HOVERING, failsafe_active, no holder) and the coordinator's rule
// takes the vehicle: it hovers under the coordinator's lease, then lands
// under it, while the controller is still frozen (the stand-down's calls to
// it cannot be answered: the landing does not wait for them) and before the
// platform's own failsafe landing. The mission is aborted with the rule as
// its reason; once the system runs again its behaviors end.
TEST_F(CoordinatorSafetyTest, AHungControllerLosesItsLeaseAndTheFailsafeRuleHoversThenLands) {
  std::string id;
  const std::string follow = flyMission(missionText("lease_lost"), &id);
  ASSERT_FALSE(follow.empty());
  const std::string controller = activationOf("QUADROTOR_PID_MOTION_CONTROL");
  ASSERT_FALSE(controller.empty()) << seenText();
  EXPECT_EQ(flight_->latest()->lease_holder(),
            std::string(kRobot) + "/QUADROTOR_PID_MOTION_CONTROL")
      << flight_->trace();

  const size_t mark = flight_->size();
  const auto frozen_at = SteadyClock::now();
  ASSERT_TRUE(pid_->freeze()) << pid_->error();

  // The platform: the lease expired (1 s of simulated time, once the
  // simulator stopped waiting for the frozen system: 0.25 s of wall time),
  // failsafe hover.
  auto failsafe = flight_->waitFor(
      mark, [](const v1::FlightStatus& s) { return s.failsafe_active(); }, kMustFollow);
  ASSERT_TRUE(failsafe) << flight_->trace(mark);
  const FlightRecorder::Sample engaged = flight_->at(*failsafe);
  EXPECT_EQ(engaged.status.state(), v1::FLIGHT_STATE_HOVERING) << flight_->trace(mark);
  EXPECT_TRUE(engaged.status.lease_holder().empty()) << flight_->trace(mark);
  // The coordinator's rule: hover under its own lease (the failsafe ends)...
  auto hover = flight_->waitFor(
      *failsafe,
      [](const v1::FlightStatus& s) {
        return s.state() == v1::FLIGHT_STATE_HOVERING && s.lease_holder() == kSafetyHolder;
      },
      kMustFollow);
  ASSERT_TRUE(hover) << flight_->trace(mark);
  const double reacted_s = wallSeconds(engaged.at, flight_->at(*hover).at);
  EXPECT_LT(reacted_s, 2.5) << flight_->trace(mark);
  // ...then land, still under its lease.
  auto landing = waitState(*hover, v1::FLIGHT_STATE_LANDING);
  ASSERT_TRUE(landing) << flight_->trace(mark);
  // A hover of the vehicle's time, which does not wait for the frozen
  // system: bounded below in simulated time, above in wall time.
  const double hovered_s = simSeconds(flight_->at(*hover).status, flight_->at(*landing).status);
  EXPECT_GE(hovered_s, 0.8 * kHoverBeforeLandS) << flight_->trace(mark);
  const double hovered_wall_s = wallSeconds(flight_->at(*hover).at, flight_->at(*landing).at);
  EXPECT_LT(hovered_wall_s, kHoverBeforeLandS + 1.5)
      << "the landing did not wait for the frozen system: " << flight_->trace(mark);
  auto landed = waitState(*landing, v1::FLIGHT_STATE_LANDED);
  ASSERT_TRUE(landed) << flight_->trace(mark);
  for (size_t i = *hover; i < *landed; ++i) {
    const auto& s = flight_->at(i).status;
    EXPECT_EQ(s.lease_holder(), kSafetyHolder)
        << "the coordinator kept the vehicle to the ground: " << flight_->trace(mark);
    EXPECT_FALSE(s.failsafe_active()) << flight_->trace(mark);
  }
  const double landed_s = wallSeconds(frozen_at, SteadyClock::now());
  EXPECT_LT(landed_s, 8.0) << flight_->trace(mark);
  expectOnTheGround();

  // The system runs again: the mission (whose runner waited for the frozen
  // system) ends ABORTED by the failsafe rule, FOLLOW_PATH and the
  // controller end (not by their goal).
  ASSERT_EQ(::kill(pid_->pid(), SIGCONT), 0);
  const v1::MissionStatus ended = missionEnded(id, seconds(15));
  EXPECT_EQ(ended.state(), v1::MISSION_STATE_ABORTED) << ended.ShortDebugString();
  EXPECT_NE(ended.message().find("lease failsafe"), std::string::npos) << ended.message();
  EXPECT_EQ(ended.message().find("motion controller failed"), std::string::npos)
      << "the failsafe rule, not the controller-failure rule: " << ended.message();
  for (const auto& activation : {follow, controller}) {
    auto end = finished(activation, seconds(12));
    ASSERT_TRUE(end) << activation << "\n" << seenText();
    EXPECT_NE(end->finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED)
        << end->ShortDebugString();
  }
  EXPECT_FALSE(waitEvent([](const v1::BehaviorEvent& e) { return e.behavior() == "LAND"; },
                         milliseconds(200)))
      << "landed by the rule, not by the mission's safety step: " << seenText();
  EXPECT_EQ(flight_->latest()->state(), v1::FLIGHT_STATE_LANDED) << flight_->trace(mark);
  std::printf(
      "SIGSTOP of the PID system: lease failsafe, coordinator hover after %.2f s, landing after "
      "%.2f s of hover (%.2f simulated), LANDED %.2f s after the freeze (wall); mission: %s\n",
      wallSeconds(frozen_at, flight_->at(*hover).at), hovered_wall_s, hovered_s, landed_s,
      ended.message().c_str());
}

// behaviorctl's situation, mission run --detach, mission status, deactivate
// and emergency-land, each run as a subprocess against the coordinator.
TEST_F(CoordinatorSafetyTest, BehaviorctlSituationMissionStatusDeactivateAndEmergencyLand) {
  const std::string ctl = std::string(BEHAVIORLIB_BEHAVIORCTL_PATH) + " --coordinator " +
                          coordinator_->address() + " --robot " + kRobot;
  std::string output;

  // On the ground LAND is infeasible; the answer says why (exit 0: an
  // answer, not an error).
  v1::CheckFleetBehaviorSituationResponse situation;
  ASSERT_EQ(runJson(ctl + " situation LAND", &situation, &output), 0) << output;
  EXPECT_EQ(situation.robot_id(), kRobot);
  EXPECT_EQ(situation.system(), "basic_quadrotor_behaviors");
  EXPECT_FALSE(situation.situation().feasible()) << output;
  ASSERT_FALSE(situation.situation().reasons().empty()) << output;
  std::printf("behaviorctl situation LAND (landed): %s", output.c_str());

  const std::string file = (std::filesystem::temp_directory_path() /
                            ("behaviorctl_mission_" + std::to_string(::getpid()) + ".yaml"))
                               .string();
  std::ofstream(file) << "name: held\n"
                         "robot: drone1\n"
                         "recurrent:\n"
                         "  - behavior: SELF_LOCALIZE_WITH_GROUND_TRUTH\n"
                         "safety:\n"
                         "  - behavior: LAND\n"
                         "steps:\n"
                         "  - name: settle\n"
                         "    behavior: WAIT\n"
                         "    parameters: {duration_s: 1.0}\n"
                         "  - name: take_off\n"
                         "    behavior: TAKE_OFF\n"
                         "    parameters: {altitude_m: 1.5}\n"
                         "    on: {REFUSED: {retry: 2}}\n"
                         "  - name: hold\n"
                         "    behavior: WAIT\n"
                         "    parameters: {duration_s: 600}\n"
                         "    on: {INTERRUPTED: continue}\n"
                         "  - name: hold_on\n"
                         "    behavior: WAIT\n"
                         "    parameters: {duration_s: 600}\n";
  v1::MissionStatus status;
  output.clear();
  const int started =
      runJson(ctl + " mission run " + file + " --detach --mission-id ctl-1", &status, &output);
  std::filesystem::remove(file);
  ASSERT_EQ(started, 0) << output;
  EXPECT_EQ(status.mission_id(), "ctl-1") << output;
  EXPECT_EQ(status.name(), "held") << output;
  EXPECT_EQ(status.state(), v1::MISSION_STATE_RUNNING) << output;

  // Hovering, holding in step 'hold'.
  std::string hold_id;
  ASSERT_TRUE(waitUntil(
      [&] {
        auto hold = step(mission("ctl-1"), "hold");
        auto flight = flight_->latest();
        if (!hold || hold->activation_id().empty() || !flight) return false;
        hold_id = hold->activation_id();
        return flight->state() == v1::FLIGHT_STATE_HOVERING;
      },
      seconds(25)))
      << mission("ctl-1").ShortDebugString() << "\n"
      << flight_->trace();

  output.clear();
  ASSERT_EQ(runJson(ctl + " mission status ctl-1", &status, &output), 0) << output;
  EXPECT_EQ(status.mission_id(), "ctl-1");
  EXPECT_EQ(status.state(), v1::MISSION_STATE_RUNNING) << output;
  ASSERT_EQ(status.steps_size(), 3) << output;
  const std::vector<std::string> names = {"settle", "take_off", "hold"};
  for (int i = 0; i < 3; ++i) EXPECT_EQ(status.steps(i).name(), names[static_cast<size_t>(i)]);
  EXPECT_EQ(status.steps(1).cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED) << output;
  EXPECT_EQ(status.steps(2).state(), v1::MISSION_STEP_STATE_RUNNING) << output;
  EXPECT_EQ(status.steps(2).activation_id(), hold_id) << output;

  // In the air LAND is feasible.
  output.clear();
  ASSERT_EQ(runJson(ctl + " situation LAND", &situation, &output), 0) << output;
  EXPECT_TRUE(situation.situation().feasible()) << output;
  EXPECT_GT(situation.situation().performance_ratio(), 0.0) << output;

  // deactivate: the mission's WAIT ends INTERRUPTED, the mission takes its
  // branch (continue) to the next step.
  v1::DeactivateFleetBehaviorResponse deactivated;
  output.clear();
  ASSERT_EQ(runJson(ctl + " deactivate WAIT", &deactivated, &output), 0) << output;
  EXPECT_EQ(deactivated.robot_id(), kRobot);
  EXPECT_EQ(deactivated.system(), "basic_quadrotor_behaviors");
  EXPECT_EQ(deactivated.result().activation_id(), hold_id) << output;
  EXPECT_EQ(deactivated.result().cause(), v1::TERMINATION_CAUSE_INTERRUPTED) << output;
  EXPECT_FALSE(deactivated.result().already_finished()) << output;
  auto interrupted = finished(hold_id, kMustFollow);
  ASSERT_TRUE(interrupted) << seenText();
  EXPECT_EQ(interrupted->finished().cause(), v1::TERMINATION_CAUSE_INTERRUPTED);
  ASSERT_TRUE(waitUntil(
      [&] {
        auto next = step(mission("ctl-1"), "hold_on");
        return next && !next->activation_id().empty();
      },
      kMustFollow))
      << mission("ctl-1").ShortDebugString();
  output.clear();
  ASSERT_EQ(runJson(ctl + " mission status ctl-1", &status, &output), 0) << output;
  ASSERT_EQ(status.steps_size(), 4) << output;
  EXPECT_EQ(status.steps(2).state(), v1::MISSION_STEP_STATE_FINISHED) << output;
  EXPECT_EQ(status.steps(2).cause(), v1::TERMINATION_CAUSE_INTERRUPTED) << output;
  EXPECT_EQ(status.steps(3).name(), "hold_on") << output;
  EXPECT_EQ(status.steps(3).state(), v1::MISSION_STEP_STATE_RUNNING) << output;
  EXPECT_EQ(status.state(), v1::MISSION_STATE_RUNNING) << output;

  // emergency-land: exit 0, says what it did; the vehicle comes down.
  const size_t mark = flight_->size();
  v1::SafetyActionResponse landed;
  output.clear();
  ASSERT_EQ(runJson(ctl + " emergency-land 'operator test with behaviorctl'", &landed, &output), 0)
      << output;
  std::printf("behaviorctl emergency-land: %s", output.c_str());
  EXPECT_NE(landed.message().find("EMERGENCY_LAND"), std::string::npos) << output;
  EXPECT_NE(landed.message().find("ctl-1"), std::string::npos) << "names the mission: " << output;
  auto emergency = waitState(mark, v1::FLIGHT_STATE_EMERGENCY, kMustFollow);
  ASSERT_TRUE(emergency) << flight_->trace(mark);
  ASSERT_TRUE(waitState(*emergency, v1::FLIGHT_STATE_LANDED)) << flight_->trace(mark);
  expectOnTheGround();
  (void)missionEnded("ctl-1");
  output.clear();
  ASSERT_EQ(runJson(ctl + " mission status ctl-1", &status, &output), 0) << output;
  EXPECT_EQ(status.state(), v1::MISSION_STATE_ABORTED) << output;
  EXPECT_NE(status.message().find("emergency land: operator test with behaviorctl"),
            std::string::npos)
      << output;
  EXPECT_TRUE(status.has_end_time()) << output;
}

// The coordinator's configured geofence (--geofence), for a mission that has
// none of its own.
class CoordinatorConfiguredGeofenceTest : public CoordinatorSafetyTest {
 protected:
  std::vector<std::string> extraCoordinatorArgs() const override {
    return {"--geofence", "-2,-2,-1,3,2,4"};
  }
};

TEST_F(CoordinatorConfiguredGeofenceTest, LeavingTheConfiguredGeofenceHoversAndAbortsTheMission) {
  constexpr double kFenceX = 3.0;
  std::string id;
  const std::string follow = flyMission(missionText("configured_fence"), &id);
  ASSERT_FALSE(follow.empty());
  const size_t mark = flight_->size();

  const v1::MissionStatus ended = missionEnded(id, seconds(25));
  EXPECT_EQ(ended.state(), v1::MISSION_STATE_ABORTED) << ended.ShortDebugString();
  EXPECT_NE(ended.message().find("left the configured geofence"), std::string::npos)
      << ended.message();
  auto stopped = finished(follow);
  ASSERT_TRUE(stopped) << seenText();
  EXPECT_NE(stopped->finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED);

  // Held by the coordinator (it took the lease and hovered; the status
  // stream sends the newest status only, so that short hold may not show:
  // the overshoot below says the vehicle stopped near the fence, FOLLOW_PATH
  // alone flies on to x = 10 m), then landed by the mission's safety step.
  auto land = waitEvent(
      [](const v1::BehaviorEvent& e) { return e.behavior() == "LAND" && e.has_activated(); });
  ASSERT_TRUE(land) << seenText() << "mission: " << ended.message();
  auto landed = finished(land->activation_id(), kLandBound);
  ASSERT_TRUE(landed) << seenText();
  EXPECT_EQ(landed->finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED)
      << landed->ShortDebugString();
  auto landing = waitState(mark, v1::FLIGHT_STATE_LANDING, kMustFollow);
  ASSERT_TRUE(landing) << flight_->trace(mark);
  EXPECT_NE(flight_->at(*landing).status.lease_holder(), kSafetyHolder) << flight_->trace(mark);
  ASSERT_TRUE(waitState(*landing, v1::FLIGHT_STATE_LANDED, kMustFollow)) << flight_->trace(mark);
  expectOnTheGround();
  const double overshoot = vehicle_->maxX() - kFenceX;
  std::printf("configured geofence at x = %.1f m: %.2f m past it; mission: %s\n", kFenceX,
              overshoot, ended.message().c_str());
  EXPECT_LT(overshoot, 3.0) << "held near the fence, far from the path's end at x = 10 m";
}

}  // namespace
}  // namespace coordinator_test
