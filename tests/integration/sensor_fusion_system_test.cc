// multi_sensor_fusion against the real simulator: the channel broker, the
// simulator in the deterministic mode (decision 18) with its default sensors
// and noise, and the behavior system following its time grants, on free
// loopback ports; so a loaded machine slows simulated time instead of
// starving the filter of IMU samples. The vehicle is flown through the
// FlightController (take-off, then a circle of velocity setpoints computed
// from simulated time); the
// estimate published by SELF_LOCALIZE_WITH_EKF_SENSOR_FUSION is compared
// with the simulator's ground truth, stamp by stamp. Injected GPS faults
// (garbage fixes, a silent receiver) and a dead simulator end the filter
// through its monitoring.

#include <google/protobuf/util/time_util.h>
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <map>
#include <mutex>
#include <thread>

#include "behaviorlib/channel/channel_client.h"
#include "behaviorlib/v1/behavior.grpc.pb.h"
#include "behaviorlib/v1/platform.grpc.pb.h"
#include "behaviorlib/v1/types.pb.h"
#include "motion_test_support.h"
#include "pose_tracks.h"
#include "sim_faults.h"
#include "support/deterministic.h"
#include "support/server_process.h"

namespace {

namespace v1 = behaviorlib::v1;
using google::protobuf::util::TimeUtil;
using std::chrono::milliseconds;
using std::chrono::seconds;

constexpr char kRobot[] = "drone1";
// How long the circle is flown, in simulated time; the wall-time bound.
constexpr double kCircleSeconds = 40.0;
constexpr seconds kCircleWallLimit(90);

std::unique_ptr<grpc::ClientContext> deadline(milliseconds timeout = seconds(5)) {
  auto context = std::make_unique<grpc::ClientContext>();
  context->set_deadline(std::chrono::system_clock::now() + timeout);
  return context;
}

class SensorFusionSystemTest : public ::testing::Test {
 protected:
  void SetUp() override {
    ASSERT_TRUE(broker_.start()) << broker_.error();
    simulator_ = std::make_unique<support::ServerProcess>(
        BEHAVIORLIB_SIMULATOR_PATH,
        support::deterministicSimulatorArgs({"--channel", broker_.address(), "--vehicles", kRobot,
                                             "--seed", "7", "--enable-fault-injection"},
                                            1));
    ASSERT_TRUE(simulator_->start()) << simulator_->error();
    system_ = std::make_unique<support::ServerProcess>(
        BEHAVIORLIB_MULTI_SENSOR_FUSION_PATH,
        support::followTimeArgs({"--robot-id", kRobot, "--channel", broker_.address(), "--clock",
                                 "sim", "--config", BEHAVIORLIB_FUSION_CONFIG_PATH},
                                simulator_->address()));
    ASSERT_TRUE(system_->start()) << system_->error();
    behaviors_ = v1::BehaviorSystem::NewStub(
        grpc::CreateChannel(system_->address(), grpc::InsecureChannelCredentials()));
    pilot_ = std::make_unique<motion_test::Pilot>(simulator_->address());
    channel_ = std::make_unique<behaviorlib::channel::ChannelClient>(broker_.address());
  }

  void TearDown() override {
    tracks_.stop();
    if (system_ && system_->running()) system_->kill();
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
  std::unique_ptr<motion_test::Pilot> pilot_;
  std::unique_ptr<behaviorlib::channel::ChannelClient> channel_;
  pose_tracks::PoseTracks tracks_;
};

TEST_F(SensorFusionSystemTest, TheEstimateFollowsTheGroundTruthWithinFifteenCentimetres) {
  // The filter first: while it is active the simulator waits for its
  // system, so simulated time (and the 10 s lease) cannot run away between
  // the take-off and the first setpoint.
  ASSERT_FALSE(activateFilter().empty());
  ASSERT_NO_FATAL_FAILURE(tracks_.record(*channel_, kRobot));
  ASSERT_NO_FATAL_FAILURE(pilot_->takeOff(2.0));
  // A circle of 3 m radius (1.5 m/s, 0.5 rad/s), its velocity set from the
  // newest ground truth's stamp: simulated time runs as fast as the filter
  // keeps up, so the setpoints follow it rather than the wall clock.
  const auto wall_start = std::chrono::steady_clock::now();
  int64_t first_ns = -1;
  while (true) {
    ASSERT_LT(std::chrono::steady_clock::now() - wall_start, kCircleWallLimit)
        << "simulated time did not advance " << kCircleSeconds << " s";
    const auto newest = tracks_.truth.newest();
    if (!newest) {
      std::this_thread::sleep_for(milliseconds(5));
      continue;
    }
    if (first_ns < 0) first_ns = newest->first;
    const double t = static_cast<double>(newest->first - first_ns) / 1e9;
    if (t >= kCircleSeconds) break;
    ASSERT_NO_FATAL_FAILURE(pilot_->setVelocity(1.5 * std::cos(t / 2.0), 1.5 * std::sin(t / 2.0)));
    std::this_thread::sleep_for(milliseconds(5));
  }
  tracks_.stop();

  // Pair each estimate with the ground truth at the same stamp
  // (interpolated between the neighbouring 100 Hz samples); skip the first
  // 5 s of simulated time of the circle while the filter converges after
  // the take-off.
  const auto t = tracks_.truth.points();
  const auto e = tracks_.estimate.points();
  ASSERT_GT(e.size(), 1000u) << "the estimate is published at 100 Hz of simulated time";
  const int64_t first = std::max(e.begin()->first, first_ns) + 5'000'000'000;
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
  std::this_thread::sleep_for(milliseconds(1000));  // the filter runs
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
  std::this_thread::sleep_for(milliseconds(1000));  // the filter runs
  simulator_->kill();  // the grants end: the system's clock runs on in real time  // every sensor
                       // falls silent; the behavior clock dead-reckons
  auto finished = finishedEvent(seconds(15));
  ASSERT_TRUE(finished.has_value());
  EXPECT_EQ(finished->finished().cause(), v1::TERMINATION_CAUSE_PROCESS_FAILURE);
  EXPECT_NE(finished->finished().message().find("silent"), std::string::npos)
      << finished->finished().message();
}

}  // namespace
