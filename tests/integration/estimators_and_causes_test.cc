// The position estimators of basic_quadrotor_behaviors
// (ESTIMATE_POSITION_WITH_SENSOR, ESTIMATE_POSITION_WITH_LINEAR_SPEED) and
// the termination causes provoked by the environment (wind, a battery drop,
// a sensor fault), against the real simulator: the channel broker, the
// simulator at 5x with a fixed seed and --enable-fault-injection,
// basic_quadrotor_behaviors and (for FOLLOW_PATH / KEEP_HOVERING) the PID
// system, each a real process on free loopback ports. Faults go through
// Simulator.InjectFailure; estimates are compared with the ground truth on
// the data channel, stamp by stamp. Every time is simulated time.

#include <cstdlib>
#include <map>

#include "behaviorlib/channel/channel_client.h"
#include "behaviorlib/v1/types.pb.h"
#include "motion_test_support.h"
#include "support/deterministic.h"

namespace motion_test {
namespace {

// Bounds on the estimators' error against the ground truth, from the errors
// measured over repeated runs (printed by the tests; docs in
// services/basic_quadrotor_behaviors/README.md) with a margin of 1.5 to 2x:
// - ESTIMATE_POSITION_WITH_SENSOR with the simulator's default GPS (0.5 m
//   horizontal, 1 m vertical noise), barometer and IMU, 3 s after its start,
//   over a take-off, a 3 m triangle and hovers: RMS 0.22-0.23 m, max
//   0.48-0.53 m over 9 runs, two of them side by side;
// - ESTIMATE_POSITION_WITH_LINEAR_SPEED from the last ground-truth estimate
//   over two moves of about 3 m: max 0.03-0.045 m over 9 runs.
constexpr double kSensorRmsBoundM = 0.35;
constexpr double kSensorMaxBoundM = 0.8;
constexpr double kLinearSpeedMaxBoundM = 0.08;

/// Positions published on a topic, by stamp (ns of simulated time).
class Track {
 public:
  Track(behaviorlib::channel::ChannelClient& channel, const std::string& topic) {
    subscription_ = channel.subscribeTyped<v1::PoseStamped>(
        topic, {.mode = v1::DELIVERY_MODE_QUEUE, .queue_size = 5000},
        [this](const v1::PoseStamped& pose) {
          const auto& p = pose.pose().position_m();
          std::lock_guard lock(mutex_);
          points_[TimeUtil::TimestampToNanoseconds(pose.header().stamp())] = {p.x(), p.y(), p.z()};
        });
  }
  bool waitConnected() { return subscription_->waitConnected(seconds(5)); }
  std::map<int64_t, Eigen::Vector3d> points() const {
    std::lock_guard lock(mutex_);
    return points_;
  }
  std::optional<std::pair<int64_t, Eigen::Vector3d>> latest() const {
    std::lock_guard lock(mutex_);
    if (points_.empty()) return std::nullopt;
    return *points_.rbegin();
  }
  void stop() { subscription_.reset(); }

 private:
  mutable std::mutex mutex_;
  std::map<int64_t, Eigen::Vector3d> points_;
  std::unique_ptr<behaviorlib::channel::Subscription> subscription_;
};

/// Errors of `estimate` against `truth` (interpolated between its samples at
/// the estimate's stamps), for the estimates stamped within [from_ns, to_ns].
struct Errors {
  double rms_m = 0.0;
  double max_m = 0.0;
  /// RMS of the horizontal and of the vertical error.
  double horizontal_rms_m = 0.0;
  double vertical_rms_m = 0.0;
  int count = 0;
};

Errors errorsAgainst(const Track& truth, const Track& estimate, int64_t from_ns, int64_t to_ns) {
  const auto t = truth.points();
  Errors out;
  double sum = 0.0, horizontal = 0.0, vertical = 0.0;
  for (const auto& [stamp, p] : estimate.points()) {
    if (stamp < from_ns || stamp > to_ns) continue;
    auto hi = t.lower_bound(stamp);
    if (hi == t.end() || hi == t.begin()) continue;
    auto lo = std::prev(hi);
    if (hi->first - lo->first > 50'000'000) continue;
    const double w =
        static_cast<double>(stamp - lo->first) / static_cast<double>(hi->first - lo->first);
    const Eigen::Vector3d d = p - ((1 - w) * lo->second + w * hi->second);
    const double e = d.norm();
    sum += e * e;
    horizontal += d.head<2>().squaredNorm();
    vertical += d.z() * d.z();
    out.max_m = std::max(out.max_m, e);
    ++out.count;
  }
  if (out.count > 0) {
    out.rms_m = std::sqrt(sum / out.count);
    out.horizontal_rms_m = std::sqrt(horizontal / out.count);
    out.vertical_rms_m = std::sqrt(vertical / out.count);
  }
  return out;
}

/// The broker, the simulator (5x, fixed seed, fault injection) and
/// basic_quadrotor_behaviors; the test's own FlightController lease for
/// flying without a localization-dependent behavior.
class CausesStack {
 public:
  bool start(std::string* error) {
    if (!broker_.start()) return *error = "broker: " + broker_.error(), false;
    simulator_ = std::make_unique<support::ServerProcess>(
        BEHAVIORLIB_SIMULATOR_PATH,
        support::deterministicSimulatorArgs({"--channel", broker_.address(), "--vehicles", kRobot,
                                             "--seed", kSeed, "--enable-fault-injection"},
                                            1));
    if (!simulator_->start()) return *error = "simulator: " + simulator_->error(), false;
    basic_ = startSystem(BEHAVIORLIB_BASIC_QUADROTOR_BEHAVIORS_PATH, BEHAVIORLIB_BASIC_CONFIG_PATH,
                         error);
    if (!basic_) return false;
    if (!waitForSimulatedTime(simulator_->address(), 0.1)) {
      return *error = "simulated time did not start", false;
    }
    basic_client_ = std::make_unique<SystemClient>(basic_->address());
    auto channel = grpc::CreateChannel(simulator_->address(), grpc::InsecureChannelCredentials());
    flight_ = v1::FlightController::NewStub(channel);
    sim_ = v1::Simulator::NewStub(channel);
    channel_ = std::make_unique<behaviorlib::channel::ChannelClient>(broker_.address());
    truth_ =
        std::make_unique<Track>(*channel_, std::string("robots/") + kRobot + "/ground_truth/pose");
    if (!truth_->waitConnected()) return *error = "no ground-truth subscription", false;
    return true;
  }

  std::unique_ptr<support::ServerProcess> startSystem(const std::string& binary,
                                                      const std::string& config,
                                                      std::string* error) {
    auto system = std::make_unique<support::ServerProcess>(
        binary, support::followTimeArgs(
                    {"--robot-id", kRobot, "--channel", broker_.address(), "--clock", "sim",
                     "--flight-controller", simulator_->address(), "--config", config},
                    simulator_->address()));
    if (!system->start()) {
      *error = binary + ": " + system->error();
      return nullptr;
    }
    return system;
  }

  void stop() {
    truth_.reset();
    basic_client_.reset();
    if (basic_ && basic_->running()) basic_->kill();
  }

  v1::InjectFailureRequest failure(v1::FailureComponent component, v1::FailureType type) {
    v1::InjectFailureRequest r;
    r.set_robot_id(kRobot);
    r.set_component(component);
    r.set_type(type);
    return r;
  }
  void inject(const v1::InjectFailureRequest& request) {
    v1::InjectFailureResponse response;
    const grpc::Status s = sim_->InjectFailure(deadline().get(), request, &response);
    ASSERT_TRUE(s.ok()) << request.ShortDebugString() << ": " << describe(s);
  }

  /// Takes off to `altitude_m` through the FlightController under the
  /// test's lease and waits until the platform reports HOVERING.
  void takeOff(double altitude_m) {
    v1::AcquireLeaseRequest lease;
    lease.set_robot_id(kRobot);
    lease.set_holder("estimators_and_causes_test");
    *lease.mutable_ttl() = TimeUtil::SecondsToDuration(10);
    v1::AcquireLeaseResponse leased;
    const grpc::Status s = flight_->AcquireLease(deadline().get(), lease, &leased);
    ASSERT_TRUE(s.ok()) << describe(s);
    lease_id_ = leased.lease_id();
    v1::ExecuteFlightActionRequest action;
    action.set_robot_id(kRobot);
    action.set_lease_id(lease_id_);
    action.set_action(v1::FLIGHT_ACTION_TAKE_OFF);
    action.set_takeoff_altitude_m(altitude_m);
    v1::ExecuteFlightActionResponse done;
    ASSERT_TRUE(flight_->ExecuteFlightAction(deadline().get(), action, &done).ok());
    ASSERT_TRUE(FlightStack::waitFor(
        [&] {
          renew();
          return flightStatus().state() == v1::FLIGHT_STATE_HOVERING;
        },
        seconds(20)))
        << "not HOVERING after the take-off";
  }

  /// Flies to `target` with position setpoints (renewing the lease) until
  /// the ground truth is within 5 cm of it, at most `max_s` of simulated
  /// time.
  void flyTo(const Eigen::Vector3d& target, double max_s) {
    v1::SetpointRequest setpoint;
    setpoint.set_robot_id(kRobot);
    setpoint.set_lease_id(lease_id_);
    auto* p = setpoint.mutable_position_yaw()->mutable_position_m();
    p->set_x(target.x());
    p->set_y(target.y());
    p->set_z(target.z());
    const double from = simNow();
    bool reached = false;
    while (!reached && simNow() < from + max_s) {
      v1::SendSetpointResponse response;
      const grpc::Status s = flight_->SendSetpoint(deadline().get(), setpoint, &response);
      ASSERT_TRUE(s.ok()) << describe(s);
      std::this_thread::sleep_for(milliseconds(20));
      reached = (truePosition() - target).norm() < 0.05;
    }
    EXPECT_TRUE(reached) << "did not reach the target";
  }

  /// Gives the lease up: the platform hovers where it is.
  void releaseLease() {
    v1::ReleaseLeaseRequest release;
    release.set_robot_id(kRobot);
    release.set_lease_id(lease_id_);
    v1::ReleaseLeaseResponse released;
    EXPECT_TRUE(flight_->ReleaseLease(deadline().get(), release, &released).ok());
    lease_id_.clear();
  }

  void renew() {
    if (lease_id_.empty()) return;
    v1::RenewLeaseRequest request;
    request.set_robot_id(kRobot);
    request.set_lease_id(lease_id_);
    v1::RenewLeaseResponse response;
    (void)flight_->RenewLease(deadline().get(), request, &response);
  }

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

  /// Simulated time of the latest ground-truth sample, seconds.
  double simNow() const {
    const auto latest = truth_->latest();
    return latest ? static_cast<double>(latest->first) * 1e-9 : 0.0;
  }
  Eigen::Vector3d truePosition() const {
    const auto latest = truth_->latest();
    return latest ? latest->second : Eigen::Vector3d::Zero();
  }
  /// Waits until `s` of simulated time have passed (renewing the lease).
  void sleepSim(double s) {
    const double until = simNow() + s;
    FlightStack::waitFor(
        [&] {
          renew();
          return simNow() >= until;
        },
        seconds(30));
  }

  SystemClient& basic() { return *basic_client_; }
  Track& truth() { return *truth_; }
  behaviorlib::channel::ChannelClient& channel() { return *channel_; }

 private:
  support::ServerProcess broker_{BEHAVIORLIB_CHANNEL_BROKER_PATH, {}};
  std::unique_ptr<support::ServerProcess> simulator_;
  std::unique_ptr<support::ServerProcess> basic_;
  std::unique_ptr<SystemClient> basic_client_;
  std::unique_ptr<v1::FlightController::Stub> flight_;
  std::unique_ptr<v1::Simulator::Stub> sim_;
  std::unique_ptr<behaviorlib::channel::ChannelClient> channel_;
  std::unique_ptr<Track> truth_;
  std::string lease_id_;
};

const std::string kEstimateTopic = std::string("robots/") + kRobot + "/self_localization/pose";

class EstimatorsTest : public ::testing::Test {
 protected:
  void SetUp() override {
    std::string error;
    ASSERT_TRUE(stack_.start(&error)) << error;
  }
  void TearDown() override { stack_.stop(); }

  /// The finished event of `activation_id` (fails the test without one).
  v1::BehaviorEvent finished(const std::string& activation_id, milliseconds timeout = seconds(20)) {
    auto event = stack_.basic().finished(activation_id, timeout);
    EXPECT_TRUE(event) << activation_id << " did not finish";
    return event.value_or(v1::BehaviorEvent());
  }

  /// Activates `behavior` with `json` once its situation allows it (the
  /// sensors it needs are publishing).
  std::string startWhenFeasible(const std::string& behavior, const std::string& json) {
    EXPECT_TRUE(FlightStack::waitFor([&] {
      return stack_.basic().checkSituation(behavior).feasible();
    })) << stack_.basic().checkSituation(behavior).ShortDebugString();
    return stack_.basic().start(behavior, json);
  }

  /// Activates `behavior` with `json`, injects `fault` once it publishes,
  /// and returns its finished event.
  v1::BehaviorEvent finishedAfterFault(const std::string& behavior, const std::string& json,
                                       const v1::InjectFailureRequest& fault) {
    Track estimate(stack_.channel(), kEstimateTopic);
    EXPECT_TRUE(estimate.waitConnected());
    const std::string id = startWhenFeasible(behavior, json);
    EXPECT_FALSE(id.empty());
    EXPECT_TRUE(FlightStack::waitFor([&] { return estimate.latest().has_value(); }))
        << behavior << " publishes no estimate";
    stack_.sleepSim(0.5);
    EXPECT_FALSE(stack_.basic().finished(id, milliseconds(0)))
        << "ended before the fault: "
        << stack_.basic().finished(id, milliseconds(0)).value().ShortDebugString();
    stack_.inject(fault);
    return finished(id);
  }

  CausesStack stack_;
};

TEST_F(EstimatorsTest, SensorEstimateFollowsTheGroundTruthAndSensorFaultsEndIt) {
  Track estimate(stack_.channel(), kEstimateTopic);
  ASSERT_TRUE(estimate.waitConnected());
  // Bad input: INVALID_ARGUMENT naming the parameter, nothing published.
  v1::ActivateResponse response;
  grpc::Status status = stack_.basic().activate("ESTIMATE_POSITION_WITH_SENSOR",
                                                "{\"max_innovation_m\": 0.1}", &response);
  EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << describe(status);
  EXPECT_NE(status.error_message().find("max_innovation_m"), std::string::npos) << describe(status);
  status =
      stack_.basic().activate("ESTIMATE_POSITION_WITH_SENSOR", "{\"max_rejected\": 2}", &response);
  EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << describe(status);
  EXPECT_NE(status.error_message().find("max_rejected"), std::string::npos) << describe(status);

  const std::string id = startWhenFeasible("ESTIMATE_POSITION_WITH_SENSOR", "{}");
  ASSERT_FALSE(id.empty());
  ASSERT_TRUE(FlightStack::waitFor([&] { return estimate.latest().has_value(); }))
      << "no estimate on " << kEstimateTopic;
  const int64_t first = estimate.latest()->first;
  // On the ground, a take-off to 2 m, a 3 m x 3 m triangle with a climb, and
  // a hover.
  stack_.sleepSim(3.0);
  ASSERT_NO_FATAL_FAILURE(stack_.takeOff(2.0));
  const Eigen::Vector3d start = stack_.truePosition();
  ASSERT_NO_FATAL_FAILURE(stack_.flyTo(start + Eigen::Vector3d(3.0, 0.0, 0.0), 15.0));
  ASSERT_NO_FATAL_FAILURE(stack_.flyTo(start + Eigen::Vector3d(3.0, 3.0, 1.0), 15.0));
  ASSERT_NO_FATAL_FAILURE(stack_.flyTo(start, 15.0));
  stack_.sleepSim(3.0);
  stack_.releaseLease();  // the platform hovers
  const int64_t last = estimate.latest()->first;
  ASSERT_FALSE(stack_.basic().finished(id, milliseconds(0)))
      << stack_.basic().finished(id, milliseconds(0)).value().ShortDebugString();
  const Errors e = errorsAgainst(stack_.truth(), estimate, first + 3'000'000'000, last);
  std::printf(
      "ESTIMATE_POSITION_WITH_SENSOR vs ground truth: RMS %.3f m (horizontal %.3f, vertical "
      "%.3f), max %.3f m over %d estimates (%.1f s)\n",
      e.rms_m, e.horizontal_rms_m, e.vertical_rms_m, e.max_m, e.count,
      static_cast<double>(last - first) * 1e-9);
  const double measured_s = static_cast<double>(last - first) * 1e-9 - 3.0;
  EXPECT_GT(e.count, 0.9 * 100 * measured_s) << "100 Hz of simulated time";
  EXPECT_LE(e.rms_m, kSensorRmsBoundM);
  EXPECT_LE(e.max_m, kSensorMaxBoundM);

  // The GPS freezes (the same fix again, new stamps): PROCESS_FAILURE.
  stack_.inject(stack_.failure(v1::FAILURE_COMPONENT_GPS, v1::FAILURE_TYPE_STUCK));
  auto event = finished(id);
  EXPECT_EQ(event.finished().cause(), v1::TERMINATION_CAUSE_PROCESS_FAILURE)
      << event.ShortDebugString();
  EXPECT_NE(event.finished().message().find("frozen"), std::string::npos)
      << event.finished().message();
  std::printf("GPS stuck: %s\n", event.finished().message().c_str());
  stack_.inject(stack_.failure(v1::FAILURE_COMPONENT_GPS, v1::FAILURE_TYPE_OK));

  // Situation before activation: the IMU is off.
  stack_.inject(stack_.failure(v1::FAILURE_COMPONENT_IMU, v1::FAILURE_TYPE_OFF));
  ASSERT_TRUE(FlightStack::waitFor([&] {
    return !stack_.basic().checkSituation("ESTIMATE_POSITION_WITH_SENSOR").feasible();
  })) << "a silent IMU makes the estimator infeasible";
  const auto situation = stack_.basic().checkSituation("ESTIMATE_POSITION_WITH_SENSOR");
  ASSERT_GT(situation.reasons_size(), 0);
  EXPECT_NE(situation.reasons(0).find("imu"), std::string::npos) << situation.ShortDebugString();
  stack_.inject(stack_.failure(v1::FAILURE_COMPONENT_IMU, v1::FAILURE_TYPE_OK));
  ASSERT_TRUE(FlightStack::waitFor(
      [&] { return stack_.basic().checkSituation("ESTIMATE_POSITION_WITH_SENSOR").feasible(); }));

  // The barometer stops: PROCESS_FAILURE naming it.
  event = finishedAfterFault("ESTIMATE_POSITION_WITH_SENSOR", "{}",
                             stack_.failure(v1::FAILURE_COMPONENT_BARO, v1::FAILURE_TYPE_OFF));
  EXPECT_EQ(event.finished().cause(), v1::TERMINATION_CAUSE_PROCESS_FAILURE)
      << event.ShortDebugString();
  EXPECT_NE(event.finished().message().find("baro"), std::string::npos)
      << event.finished().message();
  stack_.inject(stack_.failure(v1::FAILURE_COMPONENT_BARO, v1::FAILURE_TYPE_OK));

  // The fix jumps tens of metres (garbage): WRONG_PROGRESS, the innovation bound.
  event = finishedAfterFault("ESTIMATE_POSITION_WITH_SENSOR", "{}",
                             stack_.failure(v1::FAILURE_COMPONENT_GPS, v1::FAILURE_TYPE_GARBAGE));
  EXPECT_EQ(event.finished().cause(), v1::TERMINATION_CAUSE_WRONG_PROGRESS)
      << event.ShortDebugString();
  EXPECT_NE(event.finished().message().find("max_innovation_m"), std::string::npos)
      << event.finished().message();
  std::printf("GPS garbage: %s\n", event.finished().message().c_str());
}

TEST_F(EstimatorsTest, LinearSpeedDeadReckoningFollowsTheGroundTruthAndSensorFaultsEndIt) {
  // Bad input: INVALID_ARGUMENT naming the parameter.
  v1::ActivateResponse response;
  grpc::Status status = stack_.basic().activate("ESTIMATE_POSITION_WITH_LINEAR_SPEED",
                                                "{\"initial_x_m\": 1}", &response);
  EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << describe(status);
  EXPECT_NE(status.error_message().find("initial_y_m"), std::string::npos) << describe(status);
  status = stack_.basic().activate("ESTIMATE_POSITION_WITH_LINEAR_SPEED", "{\"max_drift_m\": -1}",
                                   &response);
  EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << describe(status);
  EXPECT_NE(status.error_message().find("max_drift_m"), std::string::npos) << describe(status);

  // Airborne on the ground truth, then dead reckoning from its last estimate.
  const std::string ground_truth = startWhenFeasible("SELF_LOCALIZE_WITH_GROUND_TRUTH", "{}");
  ASSERT_FALSE(ground_truth.empty());
  ASSERT_NO_FATAL_FAILURE(stack_.takeOff(1.5));
  stack_.sleepSim(1.0);
  ASSERT_TRUE(stack_.basic().deactivate("SELF_LOCALIZE_WITH_GROUND_TRUTH").ok());
  ASSERT_TRUE(stack_.basic().finished(ground_truth));
  Track estimate(stack_.channel(), kEstimateTopic);
  ASSERT_TRUE(estimate.waitConnected());
  const std::string id = startWhenFeasible("ESTIMATE_POSITION_WITH_LINEAR_SPEED", "{}");
  ASSERT_FALSE(id.empty());
  ASSERT_TRUE(FlightStack::waitFor([&] { return estimate.latest().has_value(); }));
  const int64_t first = estimate.latest()->first;
  const Eigen::Vector3d start = stack_.truePosition();
  ASSERT_NO_FATAL_FAILURE(stack_.flyTo(start + Eigen::Vector3d(-1.8, 2.4, 0.5), 15.0));
  ASSERT_NO_FATAL_FAILURE(stack_.flyTo(start + Eigen::Vector3d(1.0, 1.0, 0.0), 15.0));
  stack_.sleepSim(2.0);
  stack_.releaseLease();  // the platform hovers
  const int64_t last = estimate.latest()->first;
  ASSERT_FALSE(stack_.basic().finished(id, milliseconds(0)))
      << stack_.basic().finished(id, milliseconds(0)).value().ShortDebugString();
  const Errors e = errorsAgainst(stack_.truth(), estimate, first, last);
  const Eigen::Vector3d final_error = estimate.latest()->second - stack_.truePosition();
  std::printf(
      "ESTIMATE_POSITION_WITH_LINEAR_SPEED vs ground truth: RMS %.3f m, max %.3f m over %d "
      "estimates (%.1f s), final %.3f m\n",
      e.rms_m, e.max_m, e.count, static_cast<double>(last - first) * 1e-9, final_error.norm());
  EXPECT_GT(e.count, 0.9 * 30 * static_cast<double>(last - first) * 1e-9)
      << "30 Hz of simulated time";
  EXPECT_LE(e.max_m, kLinearSpeedMaxBoundM);

  // The speed sensor goes silent: PROCESS_FAILURE.
  stack_.inject(stack_.failure(v1::FAILURE_COMPONENT_LINEAR_SPEED, v1::FAILURE_TYPE_OFF));
  auto event = finished(id);
  EXPECT_EQ(event.finished().cause(), v1::TERMINATION_CAUSE_PROCESS_FAILURE)
      << event.ShortDebugString();
  EXPECT_NE(event.finished().message().find("silent"), std::string::npos)
      << event.finished().message();
  std::printf("linear speed off: %s\n", event.finished().message().c_str());
  stack_.inject(stack_.failure(v1::FAILURE_COMPONENT_LINEAR_SPEED, v1::FAILURE_TYPE_OK));
  ASSERT_TRUE(FlightStack::waitFor([&] {
    return stack_.basic().checkSituation("ESTIMATE_POSITION_WITH_LINEAR_SPEED").feasible();
  }));

  // From an explicit position; the speed sensor freezes: PROCESS_FAILURE.
  const Eigen::Vector3d here = stack_.truePosition();
  const std::string at = "{\"initial_x_m\": " + std::to_string(here.x()) +
                         ", \"initial_y_m\": " + std::to_string(here.y()) +
                         ", \"initial_z_m\": " + std::to_string(here.z());
  event = finishedAfterFault(
      "ESTIMATE_POSITION_WITH_LINEAR_SPEED", at + "}",
      stack_.failure(v1::FAILURE_COMPONENT_LINEAR_SPEED, v1::FAILURE_TYPE_STUCK));
  EXPECT_EQ(event.finished().cause(), v1::TERMINATION_CAUSE_PROCESS_FAILURE)
      << event.ShortDebugString();
  EXPECT_NE(event.finished().message().find("frozen"), std::string::npos)
      << event.finished().message();
  stack_.inject(stack_.failure(v1::FAILURE_COMPONENT_LINEAR_SPEED, v1::FAILURE_TYPE_OK));

  // A tight drift bound while hovering: WRONG_PROGRESS once the bound
  // (0.005 m/s while still) passes 5 cm, after about 10 s.
  const std::string tight =
      startWhenFeasible("ESTIMATE_POSITION_WITH_LINEAR_SPEED", at + ", \"max_drift_m\": 0.05}");
  ASSERT_FALSE(tight.empty());
  event = finished(tight, seconds(30));
  EXPECT_EQ(event.finished().cause(), v1::TERMINATION_CAUSE_WRONG_PROGRESS)
      << event.ShortDebugString();
  EXPECT_NE(event.finished().message().find("drift bound"), std::string::npos)
      << event.finished().message();
  const double active_s =
      static_cast<double>(TimeUtil::DurationToMilliseconds(event.finished().active_duration())) /
      1e3;
  EXPECT_GT(active_s, 5.0) << event.finished().message();
  EXPECT_LT(active_s, 15.0) << event.finished().message();

  // max_duration_s: TIME_OUT.
  const std::string timed =
      startWhenFeasible("ESTIMATE_POSITION_WITH_LINEAR_SPEED", at + ", \"max_duration_s\": 1}");
  ASSERT_FALSE(timed.empty());
  event = finished(timed);
  EXPECT_EQ(event.finished().cause(), v1::TERMINATION_CAUSE_TIME_OUT) << event.ShortDebugString();
}

// The causes provoked through the motion behaviors of the PID system, with
// the ground truth as the localization.
class CausesWithPidTest : public ::testing::Test {
 protected:
  void SetUp() override {
    std::string error;
    ASSERT_TRUE(stack_.start(&error)) << error;
    pid_ = stack_.startSystem(BEHAVIORLIB_PID_SYSTEM_PATH, BEHAVIORLIB_PID_CONFIG_PATH, &error);
    ASSERT_TRUE(pid_) << error;
    client_ = std::make_unique<SystemClient>(pid_->address());
  }
  void TearDown() override {
    client_.reset();
    if (pid_ && pid_->running()) pid_->kill();
    stack_.stop();
  }

  /// SELF_LOCALIZE_WITH_GROUND_TRUTH, take-off to `altitude_m` (TAKE_OFF
  /// behavior) and QUADROTOR_PID_MOTION_CONTROL.
  void flyWithPid(double altitude_m) {
    ASSERT_FALSE(stack_.basic().start("SELF_LOCALIZE_WITH_GROUND_TRUTH", "{}").empty());
    ASSERT_TRUE(FlightStack::waitFor(
        [&] { return stack_.basic().checkSituation("TAKE_OFF").feasible(); }, seconds(5)));
    const std::string take_off =
        stack_.basic().start("TAKE_OFF", "{\"altitude_m\": " + std::to_string(altitude_m) + "}");
    const auto done = stack_.basic().finished(take_off);
    ASSERT_TRUE(done);
    ASSERT_EQ(done->finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED)
        << done->ShortDebugString();
    // TAKE_OFF released the lease before it reported its end, but the PID
    // system learns it from the platform's status stream a moment later.
    ASSERT_TRUE(FlightStack::waitFor(
        [&] { return client_->checkSituation("QUADROTOR_PID_MOTION_CONTROL").feasible(); },
        seconds(5)))
        << client_->checkSituation("QUADROTOR_PID_MOTION_CONTROL").ShortDebugString();
    ASSERT_FALSE(client_->start("QUADROTOR_PID_MOTION_CONTROL", "{}").empty());
  }

  v1::BehaviorEvent finished(const std::string& activation_id, milliseconds timeout = seconds(20)) {
    auto event = client_->finished(activation_id, timeout);
    EXPECT_TRUE(event) << activation_id << " did not finish";
    return event.value_or(v1::BehaviorEvent());
  }

  CausesStack stack_;
  std::unique_ptr<support::ServerProcess> pid_;
  std::unique_ptr<SystemClient> client_;
};

TEST_F(CausesWithPidTest, WindPushingTheVehicleOffThePathIsWrongProgress) {
  ASSERT_NO_FATAL_FAILURE(flyWithPid(1.5));
  const Eigen::Vector3d start = stack_.truePosition();
  const std::string path = client_->start(
      "FOLLOW_PATH", pathJson({{start.x() + 8, start.y(), start.z()}}, "\"speed_m_s\": 1.0"));
  ASSERT_FALSE(path.empty());
  stack_.sleepSim(1.5);
  ASSERT_FALSE(client_->finished(path, milliseconds(0)))
      << client_->finished(path, milliseconds(0)).value().ShortDebugString();
  // 20 m/s from the south, across the path: its drag (about 21 N) exceeds
  // what the controller's 0.6 rad tilt limit can oppose (about 10 N).
  auto wind = stack_.failure(v1::FAILURE_COMPONENT_WIND, v1::FAILURE_TYPE_SET);
  wind.mutable_wind_velocity_m_s()->set_y(20.0);
  ASSERT_NO_FATAL_FAILURE(stack_.inject(wind));
  const double wind_at = stack_.simNow();
  const auto event = finished(path);
  std::printf("wind 20 m/s across the path: FOLLOW_PATH %s after %.2f s: %s\n",
              v1::TerminationCause_Name(event.finished().cause()).c_str(),
              stack_.simNow() - wind_at, event.finished().message().c_str());
  EXPECT_EQ(event.finished().cause(), v1::TERMINATION_CAUSE_WRONG_PROGRESS)
      << event.ShortDebugString();
  EXPECT_NE(event.finished().message().find("from the path"), std::string::npos)
      << event.finished().message();
  EXPECT_GT(stack_.truePosition().y() - start.y(), 0.8) << "pushed north, downwind";
  ASSERT_NO_FATAL_FAILURE(
      stack_.inject(stack_.failure(v1::FAILURE_COMPONENT_WIND, v1::FAILURE_TYPE_OK)));
}

/// The wind a situation's reason names ("wind of about 6.02 m/s ..."), or
/// -1 without one.
double windInReasons(const v1::CheckSituationResponse& situation) {
  for (const auto& reason : situation.reasons()) {
    const size_t at = reason.find("wind of about ");
    if (at != std::string::npos) return std::atof(reason.c_str() + at + 14);
  }
  return -1.0;
}

TEST_F(CausesWithPidTest, SteadyWindLowersThePerformanceEstimateAndCalmRestoresIt) {
  ASSERT_NO_FATAL_FAILURE(flyWithPid(1.5));
  const std::string hover =
      client_->start("KEEP_HOVERING_WITH_PID_CONTROL", "{\"max_drift_m\": 3}");
  ASSERT_FALSE(hover.empty());
  stack_.sleepSim(2.0);
  // Calm air, full battery: the estimate is 1 (no wind term below 2 m/s).
  const char* kHover = "KEEP_HOVERING_WITH_PID_CONTROL";
  const char* kController = "QUADROTOR_PID_MOTION_CONTROL";
  const auto calm = client_->checkSituation(kHover);
  EXPECT_TRUE(calm.feasible()) << calm.ShortDebugString();
  EXPECT_DOUBLE_EQ(calm.performance_ratio(), 1.0) << calm.ShortDebugString();
  EXPECT_DOUBLE_EQ(client_->checkSituation(kController).performance_ratio(), 1.0);

  // 6 m/s from the west: the vehicle leans about 11.5 degrees into it to hold
  // its point; the behaviors read the wind from that lean:
  // 1 - 0.8 (6 - 2) / (10 - 2) = 0.6.
  auto wind = stack_.failure(v1::FAILURE_COMPONENT_WIND, v1::FAILURE_TYPE_SET);
  wind.mutable_wind_velocity_m_s()->set_x(6.0);
  ASSERT_NO_FATAL_FAILURE(stack_.inject(wind));
  const double wind_at = stack_.simNow();
  ASSERT_TRUE(FlightStack::waitFor(
      [&] { return client_->checkSituation(kHover).performance_ratio() < 0.8; }, seconds(10)))
      << client_->checkSituation(kHover).ShortDebugString();
  const double lowered_after = stack_.simNow() - wind_at;
  stack_.sleepSim(4.0);  // the PID's integrator and the estimate settle
  const auto windy_hover = client_->checkSituation(kHover);
  const auto windy_controller = client_->checkSituation(kController);
  const auto windy_path = client_->checkSituation("FOLLOW_PATH");  // before activation
  std::printf(
      "wind 6 m/s: performance below 0.8 after %.2f s; then KEEP_HOVERING %.3f (wind %.2f m/s), "
      "QUADROTOR_PID_MOTION_CONTROL %.3f, FOLLOW_PATH (inactive) %.3f\n",
      lowered_after, windy_hover.performance_ratio(), windInReasons(windy_hover),
      windy_controller.performance_ratio(), windy_path.performance_ratio());
  for (const auto* situation : {&windy_hover, &windy_controller, &windy_path}) {
    EXPECT_TRUE(situation->feasible()) << situation->ShortDebugString();
    EXPECT_NEAR(situation->performance_ratio(), 0.6, 0.1) << situation->ShortDebugString();
    EXPECT_NEAR(windInReasons(*situation), 6.0, 1.0) << situation->ShortDebugString();
  }
  EXPECT_LT(lowered_after, 5.0);
  EXPECT_FALSE(client_->finished(hover, milliseconds(0))) << "still hovering, in the wind";

  // Calm again: back to 1 once the vehicle stops leaning.
  ASSERT_NO_FATAL_FAILURE(
      stack_.inject(stack_.failure(v1::FAILURE_COMPONENT_WIND, v1::FAILURE_TYPE_OK)));
  ASSERT_TRUE(FlightStack::waitFor(
      [&] { return client_->checkSituation(kHover).performance_ratio() >= 0.99; }, seconds(10)))
      << client_->checkSituation(kHover).ShortDebugString();
  ASSERT_TRUE(client_->deactivate(kHover).ok());
  EXPECT_EQ(finished(hover).finished().cause(), v1::TERMINATION_CAUSE_INTERRUPTED);
}

TEST_F(CausesWithPidTest, ABatteryDropWhileHoveringIsASituationChange) {
  ASSERT_NO_FATAL_FAILURE(flyWithPid(1.5));
  const std::string hover = client_->start("KEEP_HOVERING_WITH_PID_CONTROL", "{}");
  ASSERT_FALSE(hover.empty());
  stack_.sleepSim(1.0);
  ASSERT_FALSE(client_->finished(hover, milliseconds(0)));
  // Loses 90 % of its full charge at once: below min_battery_ratio (0.2).
  auto drop = stack_.failure(v1::FAILURE_COMPONENT_BATTERY, v1::FAILURE_TYPE_DEGRADED);
  drop.set_intensity(0.9);
  ASSERT_NO_FATAL_FAILURE(stack_.inject(drop));
  const auto event = finished(hover);
  std::printf("battery drop: KEEP_HOVERING_WITH_PID_CONTROL %s: %s\n",
              v1::TerminationCause_Name(event.finished().cause()).c_str(),
              event.finished().message().c_str());
  EXPECT_EQ(event.finished().cause(), v1::TERMINATION_CAUSE_SITUATION_CHANGE)
      << event.ShortDebugString();
  EXPECT_NE(event.finished().message().find("battery"), std::string::npos)
      << event.finished().message();
  // A new hover is refused in this situation.
  v1::ActivateResponse response;
  const grpc::Status status = client_->activate("KEEP_HOVERING_WITH_PID_CONTROL", "{}", &response);
  EXPECT_EQ(status.error_code(), grpc::StatusCode::FAILED_PRECONDITION) << describe(status);
}

TEST(CausesWithFlightActionTest, ABatteryDropWhileHoveringWithTheFlightActionIsASituationChange) {
  CausesStack stack;
  std::string error;
  ASSERT_TRUE(stack.start(&error)) << error;
  ASSERT_FALSE(stack.basic().start("SELF_LOCALIZE_WITH_GROUND_TRUTH", "{}").empty());
  ASSERT_TRUE(FlightStack::waitFor(
      [&] { return stack.basic().checkSituation("TAKE_OFF").feasible(); }, seconds(5)));
  const std::string take_off = stack.basic().start("TAKE_OFF", "{\"altitude_m\": 1.5}");
  auto done = stack.basic().finished(take_off);
  ASSERT_TRUE(done);
  ASSERT_EQ(done->finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED)
      << done->ShortDebugString();
  const std::string hover = stack.basic().start("HOVER_WITH_FLIGHT_ACTION_CONTROL", "{}");
  ASSERT_FALSE(hover.empty());
  stack.sleepSim(1.0);
  ASSERT_FALSE(stack.basic().finished(hover, milliseconds(0)));
  auto drop = stack.failure(v1::FAILURE_COMPONENT_BATTERY, v1::FAILURE_TYPE_DEGRADED);
  drop.set_intensity(0.9);
  ASSERT_NO_FATAL_FAILURE(stack.inject(drop));
  done = stack.basic().finished(hover);
  ASSERT_TRUE(done);
  std::printf("battery drop: HOVER_WITH_FLIGHT_ACTION_CONTROL %s: %s\n",
              v1::TerminationCause_Name(done->finished().cause()).c_str(),
              done->finished().message().c_str());
  EXPECT_EQ(done->finished().cause(), v1::TERMINATION_CAUSE_SITUATION_CHANGE)
      << done->ShortDebugString();
  EXPECT_NE(done->finished().message().find("battery"), std::string::npos)
      << done->finished().message();
  EXPECT_TRUE(stack.flightStatus().lease_holder().empty()) << "the hover released the lease";
  stack.stop();
}

}  // namespace
}  // namespace motion_test
