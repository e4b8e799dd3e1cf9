// multi_sensor_fusion against the real simulator: the channel broker, the
// simulator at 5x with its default sensors and noise, and the behavior
// system (--clock sim) on free loopback ports. The vehicle is flown through
// the FlightController (take-off, then a circle of velocity setpoints); the
// estimate published by SELF_LOCALIZE_WITH_EKF_SENSOR_FUSION is compared
// with the simulator's ground truth, stamp by stamp. Injected GPS faults
// (garbage fixes, a silent receiver) and a dead simulator end the filter
// through its monitoring.

#include <google/protobuf/util/time_util.h>
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>

#include <chrono>
#include <cmath>
#include <cstdio>
#include <map>
#include <mutex>
#include <thread>

#include "behaviorlib/v1/behavior.grpc.pb.h"
#include "behaviorlib/v1/platform.grpc.pb.h"
#include "behaviorlib/v1/types.pb.h"
#include "channel/channel_client.h"
#include "sim_faults.h"
#include "support/server_process.h"

namespace {

namespace v1 = behaviorlib::v1;
using google::protobuf::util::TimeUtil;
using std::chrono::milliseconds;
using std::chrono::seconds;

constexpr char kRobot[] = "drone1";
// Simulated seconds per wall second. At 10x a loaded machine (a camera test
// beside it under ctest -j 2) starved the filter of IMU samples.
constexpr double kTimeScale = 5.0;

std::unique_ptr<grpc::ClientContext> deadline(milliseconds timeout = seconds(5)) {
  auto context = std::make_unique<grpc::ClientContext>();
  context->set_deadline(std::chrono::system_clock::now() + timeout);
  return context;
}

// Positions on a topic, by stamp (ns of simulated time).
class Track {
 public:
  void add(const v1::PoseStamped& pose) {
    const auto& p = pose.pose().position_m();
    std::lock_guard lock(mutex_);
    points_[TimeUtil::TimestampToNanoseconds(pose.header().stamp())] = {p.x(), p.y(), p.z()};
  }
  std::map<int64_t, std::array<double, 3>> points() const {
    std::lock_guard lock(mutex_);
    return points_;
  }

 private:
  mutable std::mutex mutex_;
  std::map<int64_t, std::array<double, 3>> points_;
};

class SensorFusionSystemTest : public ::testing::Test {
 protected:
  void SetUp() override {
    ASSERT_TRUE(broker_.start()) << broker_.error();
    simulator_ = std::make_unique<support::ServerProcess>(
        BEHAVIORLIB_SIMULATOR_PATH,
        std::vector<std::string>{"--channel", broker_.address(), "--vehicles", kRobot,
                                 "--time-scale", std::to_string(kTimeScale), "--seed", "7",
                                 "--enable-fault-injection"});
    ASSERT_TRUE(simulator_->start()) << simulator_->error();
    system_ = std::make_unique<support::ServerProcess>(
        BEHAVIORLIB_MULTI_SENSOR_FUSION_PATH,
        std::vector<std::string>{"--robot-id", kRobot, "--channel", broker_.address(), "--clock",
                                 "sim", "--config", BEHAVIORLIB_CONFIG_PATH});
    ASSERT_TRUE(system_->start()) << system_->error();
    behaviors_ = v1::BehaviorSystem::NewStub(
        grpc::CreateChannel(system_->address(), grpc::InsecureChannelCredentials()));
    flight_ = v1::FlightController::NewStub(
        grpc::CreateChannel(simulator_->address(), grpc::InsecureChannelCredentials()));
    channel_ = std::make_unique<behaviorlib::channel::ChannelClient>(broker_.address());
  }

  void TearDown() override {
    truth_sub_.reset();
    estimate_sub_.reset();
    if (system_ && system_->running()) system_->kill();
  }

  void takeOff() {
    v1::AcquireLeaseRequest lease;
    lease.set_robot_id(kRobot);
    lease.set_holder("sensor_fusion_system_test");
    *lease.mutable_ttl() = TimeUtil::SecondsToDuration(10);
    v1::AcquireLeaseResponse leased;
    ASSERT_TRUE(flight_->AcquireLease(deadline().get(), lease, &leased).ok());
    lease_id_ = leased.lease_id();
    v1::ExecuteFlightActionRequest action;
    action.set_robot_id(kRobot);
    action.set_lease_id(lease_id_);
    action.set_action(v1::FLIGHT_ACTION_TAKE_OFF);
    action.set_takeoff_altitude_m(2.0);
    v1::ExecuteFlightActionResponse done;
    ASSERT_TRUE(flight_->ExecuteFlightAction(deadline().get(), action, &done).ok());
    v1::WatchFlightStateRequest watch;
    watch.set_robot_id(kRobot);
    auto ctx = deadline(seconds(20));
    auto reader = flight_->WatchFlightState(ctx.get(), watch);
    v1::WatchFlightStateResponse state;
    bool hovering = false;
    while (!hovering && reader->Read(&state))
      hovering = state.status().state() == v1::FLIGHT_STATE_HOVERING;
    ctx->TryCancel();
    reader->Finish();
    ASSERT_TRUE(hovering);
  }

  // Activates the filter, retried while the system has no simulated time yet
  // (or no sensor data after a fault was cleared); its activation id.
  std::string activateFilter() {
    v1::ActivateBehaviorRequest request;
    request.set_behavior("SELF_LOCALIZE_WITH_EKF_SENSOR_FUSION");
    grpc::Status status;
    for (int attempt = 0; attempt < 50; ++attempt) {
      v1::ActivateResponse response;
      status = behaviors_->ActivateBehavior(deadline().get(), request, &response);
      if (status.ok()) return response.activation_id();
      std::this_thread::sleep_for(milliseconds(100));
    }
    ADD_FAILURE() << status.error_message();
    return "";
  }

  void inject(v1::FailureComponent component, v1::FailureType type) {
    const grpc::Status status = sim_faults::inject(simulator_->address(), kRobot, component, type);
    ASSERT_TRUE(status.ok()) << status.error_message();
  }

  void setVelocity(double vx, double vy) {
    v1::SetpointRequest setpoint;
    setpoint.set_robot_id(kRobot);
    setpoint.set_lease_id(lease_id_);
    auto* v = setpoint.mutable_velocity_yaw_rate()->mutable_velocity_m_s();
    v->set_x(vx);
    v->set_y(vy);
    v1::SendSetpointResponse response;
    ASSERT_TRUE(flight_->SendSetpoint(deadline().get(), setpoint, &response).ok());
  }

  // The finished event of `activation_id` (any activation's when empty).
  std::optional<v1::BehaviorEvent> finishedEvent(milliseconds timeout,
                                                 const std::string& activation_id = "") {
    v1::WatchEventsRequest request;
    auto ctx = deadline(timeout);
    auto reader = behaviors_->WatchEvents(ctx.get(), request);
    v1::WatchEventsResponse message;
    while (reader->Read(&message)) {
      if (message.has_event() && message.event().has_finished() &&
          (activation_id.empty() || message.event().activation_id() == activation_id)) {
        ctx->TryCancel();
        reader->Finish();
        return message.event();
      }
    }
    return std::nullopt;
  }

  support::ServerProcess broker_{BEHAVIORLIB_CHANNEL_BROKER_PATH, {}};
  std::unique_ptr<support::ServerProcess> simulator_, system_;
  std::unique_ptr<v1::BehaviorSystem::Stub> behaviors_;
  std::unique_ptr<v1::FlightController::Stub> flight_;
  std::unique_ptr<behaviorlib::channel::ChannelClient> channel_;
  std::unique_ptr<behaviorlib::channel::Subscription> truth_sub_, estimate_sub_;
  std::string lease_id_;
};

TEST_F(SensorFusionSystemTest, TheEstimateFollowsTheGroundTruthWithinFifteenCentimetres) {
  ASSERT_NO_FATAL_FAILURE(takeOff());
  ASSERT_FALSE(activateFilter().empty());
  Track truth, estimate;
  const behaviorlib::channel::SubscribeOptions queued{.mode = v1::DELIVERY_MODE_QUEUE,
                                                      .queue_size = 5000};
  truth_sub_ = channel_->subscribeTyped<v1::PoseStamped>(
      std::string("robots/") + kRobot + "/ground_truth/pose", queued,
      [&](const v1::PoseStamped& p) { truth.add(p); });
  estimate_sub_ = channel_->subscribeTyped<v1::PoseStamped>(
      std::string("robots/") + kRobot + "/self_localization/pose", queued,
      [&](const v1::PoseStamped& p) { estimate.add(p); });
  ASSERT_TRUE(truth_sub_->waitConnected(seconds(5)));
  ASSERT_TRUE(estimate_sub_->waitConnected(seconds(5)));
  // About 40 s of simulated flight along a circle of radius 3 m at 1.5 m/s
  // (8 s of wall time at 5x), a setpoint every 0.1 s of simulated time.
  const auto start = std::chrono::steady_clock::now();
  while (std::chrono::steady_clock::now() - start < seconds(8)) {
    const double t =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count() *
        kTimeScale;
    ASSERT_NO_FATAL_FAILURE(setVelocity(1.5 * std::cos(t / 2.0), 1.5 * std::sin(t / 2.0)));
    std::this_thread::sleep_for(milliseconds(20));
  }
  truth_sub_.reset();
  estimate_sub_.reset();

  // Pair each estimate with the ground truth at the same stamp
  // (interpolated between the neighbouring 100 Hz samples); skip the first
  // 5 s of simulated time while the filter converges.
  const auto t = truth.points();
  const auto e = estimate.points();
  ASSERT_GT(e.size(), 1000u) << "the estimate is published at 100 Hz of simulated time";
  const int64_t first = e.begin()->first + 5'000'000'000;
  double sum = 0;
  int n = 0;
  for (const auto& [stamp, p] : e) {
    if (stamp < first) continue;
    auto hi = t.lower_bound(stamp);
    if (hi == t.end() || hi == t.begin()) continue;
    auto lo = std::prev(hi);
    if (hi->first - lo->first > 50'000'000) continue;
    const double w =
        static_cast<double>(stamp - lo->first) / static_cast<double>(hi->first - lo->first);
    double d2 = 0;
    for (int i = 0; i < 3; ++i) {
      const double truth_i = (1 - w) * lo->second[i] + w * hi->second[i];
      d2 += (p[i] - truth_i) * (p[i] - truth_i);
    }
    sum += d2;
    ++n;
  }
  ASSERT_GT(n, 1000);
  const double rmse = std::sqrt(sum / n);
  std::printf("EKF position RMSE over %d estimates: %.3f m\n", n, rmse);
  EXPECT_LE(rmse, 0.15);
}

TEST_F(SensorFusionSystemTest, GarbageGpsIsWrongProgressAndASilentGpsAProcessFailure) {
  // Fixes tens of metres off: the filter rejects them (innovation gate), and
  // once more than max_rejected_ratio of the last gps_window are rejected
  // the monitoring ends it WRONG_PROGRESS.
  std::string id = activateFilter();
  ASSERT_FALSE(id.empty());
  std::this_thread::sleep_for(milliseconds(1000));  // 5 s simulated: the filter runs
  ASSERT_NO_FATAL_FAILURE(inject(v1::FAILURE_COMPONENT_GPS, v1::FAILURE_TYPE_GARBAGE));
  auto finished = finishedEvent(seconds(15), id);
  ASSERT_TRUE(finished.has_value());
  EXPECT_EQ(finished->finished().cause(), v1::TERMINATION_CAUSE_WRONG_PROGRESS)
      << finished->ShortDebugString();
  EXPECT_NE(finished->finished().message().find("rejects the GPS"), std::string::npos)
      << finished->finished().message();

  // The GPS falls silent (the IMU goes on): PROCESS_FAILURE naming it.
  ASSERT_NO_FATAL_FAILURE(inject(v1::FAILURE_COMPONENT_GPS, v1::FAILURE_TYPE_OK));
  id = activateFilter();
  ASSERT_FALSE(id.empty());
  std::this_thread::sleep_for(milliseconds(1000));
  ASSERT_NO_FATAL_FAILURE(inject(v1::FAILURE_COMPONENT_GPS, v1::FAILURE_TYPE_OFF));
  finished = finishedEvent(seconds(15), id);
  ASSERT_TRUE(finished.has_value());
  EXPECT_EQ(finished->finished().cause(), v1::TERMINATION_CAUSE_PROCESS_FAILURE)
      << finished->ShortDebugString();
  EXPECT_NE(finished->finished().message().find("GPS"), std::string::npos)
      << finished->finished().message();
  EXPECT_NE(finished->finished().message().find("silent"), std::string::npos)
      << finished->finished().message();
}

TEST_F(SensorFusionSystemTest, ASilentImuIsAProcessFailure) {
  ASSERT_FALSE(activateFilter().empty());
  std::this_thread::sleep_for(milliseconds(1000));  // 5 s simulated: the filter runs
  simulator_->kill();  // every sensor falls silent; the behavior clock dead-reckons
  auto finished = finishedEvent(seconds(15));
  ASSERT_TRUE(finished.has_value());
  EXPECT_EQ(finished->finished().cause(), v1::TERMINATION_CAUSE_PROCESS_FAILURE);
  EXPECT_NE(finished->finished().message().find("silent"), std::string::npos)
      << finished->finished().message();
}

}  // namespace
