// Simulator.InjectFailure end to end: the simulator binary (with
// --enable-fault-injection, in lock-step) and the channel broker as real
// processes on free loopback ports. Each fault is injected over gRPC at a
// known simulated time and its effect observed where a behavior would see
// it: on the data channel (sensors, flight state) and in the ground truth.

#include <google/protobuf/util/time_util.h>
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>

#include <chrono>
#include <cmath>
#include <map>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "behaviorlib/channel/channel_client.h"
#include "behaviorlib/error_details.h"
#include "behaviorlib/v1/channel.grpc.pb.h"
#include "behaviorlib/v1/platform.grpc.pb.h"
#include "behaviorlib/v1/simulator.grpc.pb.h"
#include "behaviorlib/v1/types.pb.h"
#include "support/server_process.h"

namespace {

namespace v1 = behaviorlib::v1;
using google::protobuf::util::TimeUtil;
using std::chrono::milliseconds;
using std::chrono::seconds;

constexpr int64_t kSecond = 1'000'000'000;

std::unique_ptr<grpc::ClientContext> deadline(seconds s = seconds(10)) {
  auto context = std::make_unique<grpc::ClientContext>();
  context->set_deadline(std::chrono::system_clock::now() + s);
  return context;
}

template <class F>
bool eventually(F condition, milliseconds timeout = seconds(10)) {
  const auto end = std::chrono::steady_clock::now() + timeout;
  while (std::chrono::steady_clock::now() < end) {
    if (condition()) return true;
    std::this_thread::sleep_for(milliseconds(5));
  }
  return condition();
}

/// Every sample of some topics, parsed as T (queued subscriptions: nothing
/// is lost).
template <class T>
class Recorder {
 public:
  Recorder(behaviorlib::channel::ChannelClient& client, const std::string& topic) {
    subscription_ = client.subscribeTyped<T>(
        topic, {.mode = v1::DELIVERY_MODE_QUEUE, .queue_size = 10000}, [this](const T& sample) {
          std::lock_guard lock(mutex_);
          samples_.push_back(sample);
        });
  }
  bool waitConnected() { return subscription_->waitConnected(seconds(10)); }
  std::vector<T> all() {
    std::lock_guard lock(mutex_);
    return samples_;
  }
  /// Those stamped within (from_ns, to_ns].
  std::vector<T> between(int64_t from_ns, int64_t to_ns) {
    std::vector<T> out;
    for (const T& s : all()) {
      const int64_t t = TimeUtil::TimestampToNanoseconds(s.header().stamp());
      if (t > from_ns && t <= to_ns) out.push_back(s);
    }
    return out;
  }
  /// Waits (wall time) for a sample stamped at or after `stamp_ns`.
  bool waitForStamp(int64_t stamp_ns) {
    return eventually([&] {
      std::lock_guard lock(mutex_);
      return !samples_.empty() &&
             TimeUtil::TimestampToNanoseconds(samples_.back().header().stamp()) >= stamp_ns;
    });
  }
  void clear() {
    std::lock_guard lock(mutex_);
    samples_.clear();
  }

 private:
  std::mutex mutex_;
  std::vector<T> samples_;
  std::unique_ptr<behaviorlib::channel::Subscription> subscription_;
};

int64_t stampNs(const v1::Header& header) {
  return TimeUtil::TimestampToNanoseconds(header.stamp());
}

class SimulatorFaultsTest : public ::testing::Test {
 protected:
  void SetUp() override {
    ASSERT_TRUE(broker_.start()) << broker_.error();
    simulator_ = std::make_unique<support::ServerProcess>(
        BEHAVIORLIB_SIMULATOR_PATH,
        std::vector<std::string>{"--channel", broker_.address(), "--vehicles", "drone1",
                                 "--lock-step", "--seed", "5", "--enable-fault-injection"});
    ASSERT_TRUE(simulator_->start()) << simulator_->error();
    auto channel = grpc::CreateChannel(simulator_->address(), grpc::InsecureChannelCredentials());
    sim_ = v1::Simulator::NewStub(channel);
    flight_ = v1::FlightController::NewStub(channel);
    client_ = std::make_unique<behaviorlib::channel::ChannelClient>(broker_.address());
    imu_ = std::make_unique<Recorder<v1::Imu>>(*client_, "robots/drone1/imu");
    ASSERT_TRUE(imu_->waitConnected());
  }

  /// Advances simulated time by `ms` (lock-step) and waits until the IMU
  /// sample of the new time arrived: every sensor sample published up to
  /// then has reached the broker (one ordered publishing stream).
  int64_t step(int ms) {
    v1::StepRequest request;
    *request.mutable_duration() = TimeUtil::MillisecondsToDuration(ms);
    v1::StepResponse response;
    const grpc::Status status = sim_->Step(deadline().get(), request, &response);
    EXPECT_TRUE(status.ok()) << status.error_message();
    now_ns_ = TimeUtil::TimestampToNanoseconds(response.time());
    EXPECT_TRUE(imu_->waitForStamp(now_ns_)) << "no IMU sample at " << now_ns_;
    return now_ns_;
  }

  grpc::Status inject(const v1::InjectFailureRequest& request) {
    v1::InjectFailureResponse response;
    return sim_->InjectFailure(deadline().get(), request, &response);
  }

  v1::InjectFailureRequest failure(v1::FailureComponent component, v1::FailureType type) {
    v1::InjectFailureRequest r;
    r.set_robot_id("drone1");
    r.set_component(component);
    r.set_type(type);
    return r;
  }

  /// The broker's count of samples published on `topic`.
  uint64_t publishedCount(const std::string& topic) {
    auto listed = client_->listTopics(topic);
    if (!listed.ok()) return 0;
    for (const auto& t : *listed) {
      if (t.name() == topic) return t.published_count();
    }
    return 0;
  }

  /// drone1's ground truth now (WatchState sends the current state first).
  v1::VehicleState state() {
    auto context = deadline();
    v1::WatchStateRequest request;
    request.add_robot_ids("drone1");
    auto reader = sim_->WatchState(context.get(), request);
    v1::WatchStateResponse response;
    EXPECT_TRUE(reader->Read(&response));
    context->TryCancel();
    reader->Finish();
    return response.state();
  }

  /// Takes drone1 off to `altitude_m` and leaves it hovering, lease released.
  void hover(double altitude_m) {
    v1::AcquireLeaseRequest lease_request;
    lease_request.set_robot_id("drone1");
    lease_request.set_holder("test");
    *lease_request.mutable_ttl() = TimeUtil::SecondsToDuration(10);
    v1::AcquireLeaseResponse lease;
    ASSERT_TRUE(flight_->AcquireLease(deadline().get(), lease_request, &lease).ok());
    v1::ExecuteFlightActionRequest takeoff;
    takeoff.set_robot_id("drone1");
    takeoff.set_lease_id(lease.lease_id());
    takeoff.set_action(v1::FLIGHT_ACTION_TAKE_OFF);
    takeoff.set_takeoff_altitude_m(altitude_m);
    v1::ExecuteFlightActionResponse reply;
    ASSERT_TRUE(flight_->ExecuteFlightAction(deadline().get(), takeoff, &reply).ok());
    for (int i = 0; i < 40 && state().flight_state() != v1::FLIGHT_STATE_HOVERING; ++i) step(250);
    ASSERT_EQ(state().flight_state(), v1::FLIGHT_STATE_HOVERING);
    v1::ReleaseLeaseRequest release;
    release.set_robot_id("drone1");
    release.set_lease_id(lease.lease_id());
    v1::ReleaseLeaseResponse released;
    ASSERT_TRUE(flight_->ReleaseLease(deadline().get(), release, &released).ok());
    step(2000);  // settle
  }

  support::ServerProcess broker_{BEHAVIORLIB_CHANNEL_BROKER_PATH, {}};
  std::unique_ptr<support::ServerProcess> simulator_;
  std::unique_ptr<v1::Simulator::Stub> sim_;
  std::unique_ptr<v1::FlightController::Stub> flight_;
  std::unique_ptr<behaviorlib::channel::ChannelClient> client_;
  std::unique_ptr<Recorder<v1::Imu>> imu_;
  int64_t now_ns_ = 0;
};

TEST_F(SimulatorFaultsTest, EachGpsFaultHasItsEffectOnTheChannel) {
  Recorder<v1::PositionFix> gps(*client_, "robots/drone1/gps");
  ASSERT_TRUE(gps.waitConnected());
  step(1000);
  ASSERT_TRUE(gps.waitForStamp(kSecond));
  ASSERT_EQ(gps.between(0, kSecond).size(), 10u);

  // OFF: nothing.
  ASSERT_TRUE(inject(failure(v1::FAILURE_COMPONENT_GPS, v1::FAILURE_TYPE_OFF)).ok());
  step(1000);
  EXPECT_EQ(publishedCount("robots/drone1/gps"), 10u);

  // STUCK: the last value, again and again, with new stamps.
  ASSERT_TRUE(inject(failure(v1::FAILURE_COMPONENT_GPS, v1::FAILURE_TYPE_STUCK)).ok());
  step(1000);
  ASSERT_TRUE(gps.waitForStamp(3 * kSecond));
  const v1::PositionFix last_healthy = gps.between(0, kSecond).back();
  const auto stuck = gps.between(2 * kSecond, 3 * kSecond);
  ASSERT_EQ(stuck.size(), 10u);
  for (std::size_t i = 0; i < stuck.size(); ++i) {
    EXPECT_EQ(stuck[i].position_m().SerializeAsString(),
              last_healthy.position_m().SerializeAsString());
    EXPECT_EQ(stampNs(stuck[i].header()), 2 * kSecond + static_cast<int64_t>(i + 1) * kSecond / 10);
    EXPECT_EQ(stuck[i].header().seq(), 10 + i);
  }

  // GARBAGE: far from the truth (the vehicle is landed at the origin).
  ASSERT_TRUE(inject(failure(v1::FAILURE_COMPONENT_GPS, v1::FAILURE_TYPE_GARBAGE)).ok());
  step(1000);
  ASSERT_TRUE(gps.waitForStamp(4 * kSecond));
  const auto garbage = gps.between(3 * kSecond, 4 * kSecond);
  ASSERT_EQ(garbage.size(), 10u);
  for (const auto& fix : garbage) {
    const auto& p = fix.position_m();
    EXPECT_GT(std::sqrt(p.x() * p.x() + p.y() * p.y() + p.z() * p.z()), 15.0);
  }

  // INTERMITTENT 0.5: about half of the 100 samples of 10 s.
  auto intermittent = failure(v1::FAILURE_COMPONENT_GPS, v1::FAILURE_TYPE_INTERMITTENT);
  intermittent.set_intensity(0.5);
  ASSERT_TRUE(inject(intermittent).ok());
  const uint64_t before = publishedCount("robots/drone1/gps");
  step(10000);
  const uint64_t kept = publishedCount("robots/drone1/gps") - before;
  EXPECT_GT(kept, 30u);
  EXPECT_LT(kept, 70u);

  // DELAYED 0.2 s: each sample reaches the channel 0.2 s of simulated time
  // after its stamp. Stepping 50 ms at a time, the broker's count tells at
  // which step each sample was published.
  auto delayed = failure(v1::FAILURE_COMPONENT_GPS, v1::FAILURE_TYPE_DELAYED);
  *delayed.mutable_delay() = TimeUtil::MillisecondsToDuration(200);
  ASSERT_TRUE(inject(delayed).ok());
  const int64_t delayed_from = now_ns_;
  const uint64_t base = publishedCount("robots/drone1/gps");
  std::vector<int64_t> published_at;  // simulated time of the step each sample came out in
  for (int i = 0; i < 40; ++i) {
    const int64_t now = step(50);
    while (published_at.size() < publishedCount("robots/drone1/gps") - base) {
      published_at.push_back(now);
    }
  }
  ASSERT_TRUE(gps.waitForStamp(now_ns_ - 300'000'000));
  const auto late = gps.between(delayed_from, now_ns_);
  ASSERT_EQ(late.size(), 18u) << "2 s hold 20 samples, the last two still delayed";
  ASSERT_EQ(published_at.size(), late.size());
  for (std::size_t i = 0; i < late.size(); ++i) {
    const int64_t stamp = stampNs(late[i].header());
    EXPECT_EQ(stamp, delayed_from + static_cast<int64_t>(i + 1) * kSecond / 10);
    // Released at the step that reaches stamp + 0.2 s; seen after that 50 ms step.
    EXPECT_GE(published_at[i] - stamp, 200'000'000) << i;
    EXPECT_LT(published_at[i] - stamp, 250'000'000) << i;
  }

  // OK: back to normal.
  ASSERT_TRUE(inject(failure(v1::FAILURE_COMPONENT_GPS, v1::FAILURE_TYPE_OK)).ok());
  const int64_t cleared = now_ns_;
  step(1000);
  ASSERT_TRUE(gps.waitForStamp(now_ns_));
  const auto healthy = gps.between(cleared, now_ns_);
  ASSERT_EQ(healthy.size(), 10u);
  for (const auto& fix : healthy) EXPECT_LT(std::abs(fix.position_m().x()), 4 * 0.5);
}

TEST_F(SimulatorFaultsTest, ALinearSpeedFaultIsSeenOnItsTopic) {
  Recorder<v1::TwistStamped> speed(*client_, "robots/drone1/linear_speed");
  ASSERT_TRUE(speed.waitConnected());
  step(1000);
  ASSERT_TRUE(inject(failure(v1::FAILURE_COMPONENT_LINEAR_SPEED, v1::FAILURE_TYPE_STUCK)).ok());
  step(1000);
  ASSERT_TRUE(speed.waitForStamp(2 * kSecond));
  const auto stuck = speed.between(kSecond, 2 * kSecond);
  ASSERT_EQ(stuck.size(), 30u);
  for (const auto& s : stuck) {
    EXPECT_EQ(s.twist().SerializeAsString(), stuck.front().twist().SerializeAsString());
  }
  ASSERT_TRUE(inject(failure(v1::FAILURE_COMPONENT_LINEAR_SPEED, v1::FAILURE_TYPE_OFF)).ok());
  const uint64_t before = publishedCount("robots/drone1/linear_speed");
  step(1000);
  EXPECT_EQ(publishedCount("robots/drone1/linear_speed"), before);
}

TEST_F(SimulatorFaultsTest, AMotorOffWhileHoveringCrashesTheVehicle) {
  hover(2.0);
  v1::VehicleState hovering = state();
  ASSERT_NEAR(hovering.pose().position_m().z(), 2.0, 0.2);
  ASSERT_FALSE(hovering.crashed());
  auto motor = failure(v1::FAILURE_COMPONENT_MOTOR, v1::FAILURE_TYPE_OFF);
  motor.set_motor_index(0);
  ASSERT_TRUE(inject(motor).ok());
  step(500);
  EXPECT_LT(state().pose().position_m().z(), 1.9) << "loses altitude at once";
  step(4500);
  const v1::VehicleState down = state();
  EXPECT_TRUE(down.crashed());
  EXPECT_NEAR(down.pose().position_m().z(), 0.0, 0.05);
}

TEST_F(SimulatorFaultsTest, ABatteryDropShowsOnTheBatteryTopicAndInTheFlightStatus) {
  Recorder<v1::BatteryState> battery(*client_, "robots/drone1/battery");
  Recorder<v1::FlightStatus> status(*client_, "robots/drone1/flight_state");
  ASSERT_TRUE(battery.waitConnected());
  ASSERT_TRUE(status.waitConnected());
  hover(1.5);
  // On a whole second: the battery (2 Hz) and the flight state (10 Hz) have a
  // sample stamped at the last step.
  if (now_ns_ % kSecond != 0) step(static_cast<int>((kSecond - now_ns_ % kSecond) / 1'000'000));
  ASSERT_TRUE(battery.waitForStamp(now_ns_));
  ASSERT_TRUE(status.waitForStamp(now_ns_ - 100'000'000));
  const double battery_before = battery.all().back().charge_ratio();
  const double status_before = status.all().back().battery_ratio();
  EXPECT_NEAR(battery_before, status_before, 0.002);

  auto drop = failure(v1::FAILURE_COMPONENT_BATTERY, v1::FAILURE_TYPE_DEGRADED);
  drop.set_intensity(0.3);
  ASSERT_TRUE(inject(drop).ok());
  step(1000);
  ASSERT_TRUE(battery.waitForStamp(now_ns_));
  ASSERT_TRUE(status.waitForStamp(now_ns_ - 100'000'000));
  std::this_thread::sleep_for(milliseconds(100));  // the flight state's last sample
  EXPECT_NEAR(battery_before - battery.all().back().charge_ratio(), 0.3, 0.005);
  EXPECT_NEAR(status_before - status.all().back().battery_ratio(), 0.3, 0.005);
  EXPECT_EQ(status.all().back().state(), v1::FLIGHT_STATE_HOVERING) << "still flying";
}

TEST_F(SimulatorFaultsTest, SteadyWindMakesAHoveringVehicleLeanIntoIt) {
  hover(2.0);
  const v1::VehicleState calm = state();
  auto wind = failure(v1::FAILURE_COMPONENT_WIND, v1::FAILURE_TYPE_SET);
  wind.clear_robot_id();
  wind.mutable_wind_velocity_m_s()->set_x(5.0);  // blowing towards the east
  ASSERT_TRUE(inject(wind).ok());
  step(30000);
  const v1::VehicleState held = state();
  EXPECT_NEAR(held.pose().position_m().x(), calm.pose().position_m().x(), 0.1);
  // Body z in the world: the x component of R e_z for q = (w, x, y, z).
  auto tilt_east = [](const v1::Quaternion& q) { return 2.0 * (q.x() * q.z() + q.w() * q.y()); };
  EXPECT_NEAR(tilt_east(calm.pose().orientation()), 0.0, 0.01);
  // Thrust leans west against 2.25 N of drag (5 m/s) on 14.7 N of weight.
  EXPECT_NEAR(std::asin(-tilt_east(held.pose().orientation())), std::atan(2.25 / 14.715), 0.03);
}

TEST_F(SimulatorFaultsTest, ResetClearsFaultsAndTheSameSeedReproducesAFaultyRun) {
  Recorder<v1::PositionFix> gps(*client_, "robots/drone1/gps");
  Recorder<v1::PoseStamped> pose(*client_, "robots/drone1/ground_truth/pose");
  ASSERT_TRUE(gps.waitConnected());
  ASSERT_TRUE(pose.waitConnected());
  auto run = [&](uint64_t seed) {
    v1::ResetRequest reset;
    reset.set_seed(seed);
    v1::ResetResponse reset_response;
    EXPECT_TRUE(sim_->Reset(deadline().get(), reset, &reset_response).ok());
    std::this_thread::sleep_for(milliseconds(100));  // samples of the old run in flight
    gps.clear();
    pose.clear();
    imu_->clear();
    hover(1.0);  // healthy: the previous run's faults are gone
    auto gusts = failure(v1::FAILURE_COMPONENT_WIND, v1::FAILURE_TYPE_SET);
    gusts.set_gust_stddev_m_s(2.0);
    EXPECT_TRUE(inject(gusts).ok());
    auto dropouts = failure(v1::FAILURE_COMPONENT_GPS, v1::FAILURE_TYPE_INTERMITTENT);
    dropouts.set_intensity(0.5);
    EXPECT_TRUE(inject(dropouts).ok());
    auto noisy = failure(v1::FAILURE_COMPONENT_IMU, v1::FAILURE_TYPE_NOISY);
    noisy.set_intensity(0.5);
    EXPECT_TRUE(inject(noisy).ok());
    for (int i = 0; i < 4; ++i) step(500);
    // Ground truth comes every 10 ms from the first step after the reset on.
    EXPECT_TRUE(pose.waitForStamp(now_ns_ - 10'000'000));
    std::this_thread::sleep_for(milliseconds(200));
    std::vector<std::string> out;
    for (const auto& s : gps.all()) out.push_back(s.SerializeAsString());
    for (const auto& s : pose.all()) out.push_back(s.SerializeAsString());
    for (const auto& s : imu_->all()) out.push_back(s.SerializeAsString());
    return out;
  };
  const auto a = run(42);
  const auto b = run(42);
  const auto c = run(43);
  ASSERT_GT(a.size(), 1000u);
  EXPECT_TRUE(a == b) << "the same seed and time-stamped requests: the same bytes";
  EXPECT_FALSE(a == c);
}

TEST_F(SimulatorFaultsTest, BadRequestsAreRefusedAndTheSimulatorGoesOn) {
  auto wind = failure(v1::FAILURE_COMPONENT_WIND, v1::FAILURE_TYPE_STUCK);
  grpc::Status s = inject(wind);
  EXPECT_EQ(s.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_NE(s.error_message().find("FAILURE_TYPE_SET"), std::string::npos) << s.error_message();

  auto motor = failure(v1::FAILURE_COMPONENT_MOTOR, v1::FAILURE_TYPE_OFF);
  motor.set_motor_index(9);
  s = inject(motor);
  EXPECT_EQ(s.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_NE(s.error_message().find("0..3"), std::string::npos) << s.error_message();

  auto noisy = failure(v1::FAILURE_COMPONENT_BARO, v1::FAILURE_TYPE_NOISY);
  noisy.set_intensity(2.0);
  EXPECT_EQ(inject(noisy).error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  auto delayed = failure(v1::FAILURE_COMPONENT_IMU, v1::FAILURE_TYPE_DELAYED);
  *delayed.mutable_delay() = TimeUtil::MillisecondsToDuration(-5);
  EXPECT_EQ(inject(delayed).error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_EQ(inject(failure(v1::FAILURE_COMPONENT_UNSPECIFIED, v1::FAILURE_TYPE_OFF)).error_code(),
            grpc::StatusCode::INVALID_ARGUMENT);

  auto unknown = failure(v1::FAILURE_COMPONENT_GPS, v1::FAILURE_TYPE_OFF);
  unknown.set_robot_id("drone9");
  s = inject(unknown);
  EXPECT_EQ(s.error_code(), grpc::StatusCode::NOT_FOUND);
  EXPECT_NE(s.error_message().find("drone1"), std::string::npos) << s.error_message();

  EXPECT_GT(step(100), 0) << "still running";
  EXPECT_TRUE(inject(failure(v1::FAILURE_COMPONENT_GPS, v1::FAILURE_TYPE_OK)).ok());
}

TEST(SimulatorFaultsDisabled, InjectFailureIsRefusedWithoutTheFlag) {
  support::ServerProcess simulator(BEHAVIORLIB_SIMULATOR_PATH, {"--lock-step"});
  ASSERT_TRUE(simulator.start()) << simulator.error();
  auto sim = v1::Simulator::NewStub(
      grpc::CreateChannel(simulator.address(), grpc::InsecureChannelCredentials()));
  v1::InjectFailureRequest request;
  request.set_robot_id("drone1");
  request.set_component(v1::FAILURE_COMPONENT_MOTOR);
  request.set_type(v1::FAILURE_TYPE_OFF);
  v1::InjectFailureResponse response;
  const grpc::Status s = sim->InjectFailure(deadline().get(), request, &response);
  EXPECT_EQ(s.error_code(), grpc::StatusCode::FAILED_PRECONDITION);
  EXPECT_NE(s.error_message().find("--enable-fault-injection"), std::string::npos);
  const auto info = behaviorlib::errors::errorInfo(s);
  ASSERT_TRUE(info.has_value());
  EXPECT_EQ(info->reason(), "FEATURE_NOT_ENABLED");
  EXPECT_EQ(info->metadata().at("feature"), "fault_injection");
  EXPECT_EQ(simulator.terminate(), 0);
}

}  // namespace
