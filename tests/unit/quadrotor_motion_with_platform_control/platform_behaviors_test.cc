// The behaviors of quadrotor_motion_with_platform_control against a fake
// vehicle on a FakeClock: the setpoints they stream under the lease, their
// goals, and bad parameters refused before anything is commanded.

#include "behaviorlib/quadrotor_motion_with_platform_control/platform_behaviors.h"

#include <gtest/gtest.h>

#include <thread>

#include "behaviorlib/behavior_host.h"
#include "fake_clock_flight.h"
#include "fake_vehicle.h"
#include "test_behaviors.h"

namespace behaviorlib::platform_motion {
namespace {

using std::chrono::milliseconds;
using FakeVehicle = basic::testing::FakeVehicle;

class PlatformBehaviorsUnitTest : public ::testing::Test {
 protected:
  void SetUp() override {
    vehicle_.setState(v1::FLIGHT_STATE_HOVERING);
    vehicle_.setPosition(1, 2, 1);
    host_.add(std::make_unique<MoveVerticalBehavior>(vehicle_));
    host_.add(std::make_unique<MoveAtSpeedBehavior>(vehicle_));
    host_.add(std::make_unique<RotateWithPlatformControlBehavior>(vehicle_));
    ASSERT_TRUE(host_.start().ok());
    move_vertical_ = host_.find("MOVE_VERTICAL_WITH_PLATFORM_CONTROL");
    move_at_speed_ = host_.find("MOVE_AT_SPEED_WITH_PLATFORM_CONTROL");
    rotate_ = host_.find("ROTATE_WITH_PLATFORM_CONTROL");
  }

  // 50 ms steps (one tick each at 20 Hz); `each` runs after every step.
  void fly(Duration total, const BehaviorExecutionManager* behavior,
           const std::function<void()>& each = nullptr) {
    behaviorlib::testing::flyOnFakeClock(clock_, host_, total, milliseconds(50), behavior, each);
  }

  FakeClock clock_;
  FakeVehicle vehicle_{clock_};
  BehaviorHost host_{
      behaviorlib::testing::hostOptions("drone1", "quadrotor_motion_with_platform_control"),
      clock_};
  behaviorlib::testing::EventCollector events_{host_.events()};
  BehaviorExecutionManager* move_vertical_ = nullptr;
  BehaviorExecutionManager* move_at_speed_ = nullptr;
  BehaviorExecutionManager* rotate_ = nullptr;
};

TEST_F(PlatformBehaviorsUnitTest, MoveVerticalRampsTheAltitudeSetpointAndAchievesItsGoal) {
  auto p = std::make_unique<v1::MoveVerticalWithPlatformControlParameters>();
  p->set_distance_m(1.0);
  p->set_speed_m_s(0.5);
  ASSERT_TRUE(move_vertical_->activateAndWait(std::move(p)).ok());
  EXPECT_EQ(vehicle_.leaseHolder(), "drone1/MOVE_VERTICAL_WITH_PLATFORM_CONTROL");
  fly(milliseconds(1000), move_vertical_);
  auto setpoints = vehicle_.setpoints();
  ASSERT_FALSE(setpoints.empty());
  const auto& sp = setpoints.back().position_yaw();
  EXPECT_NEAR(sp.position_m().x(), 1.0, 1e-9) << "holds its horizontal position";
  EXPECT_NEAR(sp.position_m().y(), 2.0, 1e-9);
  EXPECT_NEAR(sp.position_m().z(), 1.5, 0.05) << "0.5 m/s for 1 s";
  // The vehicle follows the setpoint.
  fly(std::chrono::seconds(4), move_vertical_, [&] {
    const auto last = vehicle_.setpoints().back().position_yaw().position_m();
    vehicle_.setPosition(last.x(), last.y(), last.z());
  });
  const auto finished = events_.waitFinished();
  EXPECT_EQ(finished.finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED)
      << finished.ShortDebugString();
  EXPECT_NEAR(vehicle_.setpoints().back().position_yaw().position_m().z(), 2.0, 1e-9);
  EXPECT_EQ(vehicle_.commands().back(), "RELEASE");
}

TEST_F(PlatformBehaviorsUnitTest, MoveVerticalWithoutProgressIsWrongProgress) {
  auto p = std::make_unique<v1::MoveVerticalWithPlatformControlParameters>();
  p->set_altitude_m(3.0);
  ASSERT_TRUE(move_vertical_->activateAndWait(std::move(p)).ok());
  fly(std::chrono::seconds(5), move_vertical_);  // the fake vehicle never climbs
  const auto finished = events_.waitFinished();
  EXPECT_EQ(finished.finished().cause(), v1::TERMINATION_CAUSE_WRONG_PROGRESS)
      << finished.ShortDebugString();
}

TEST_F(PlatformBehaviorsUnitTest, BadTargetsAreRefusedBeforeTheLeaseIsTaken) {
  auto both = std::make_unique<v1::MoveVerticalWithPlatformControlParameters>();
  both->set_altitude_m(2.0);
  both->set_distance_m(1.0);
  auto refused = move_vertical_->activateAndWait(std::move(both));
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(refused.status().message().find("distance_m"), std::string::npos) << refused.status();
  auto low = std::make_unique<v1::MoveVerticalWithPlatformControlParameters>();
  low->set_distance_m(-0.95);
  refused = move_vertical_->activateAndWait(std::move(low));
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(refused.status().message().find("minimum altitude"), std::string::npos)
      << refused.status();
  EXPECT_TRUE(vehicle_.commands().empty()) << "no lease taken";
  EXPECT_TRUE(vehicle_.setpoints().empty());
  EXPECT_EQ(vehicle_.followers(), 0);
}

TEST_F(PlatformBehaviorsUnitTest, MoveAtSpeedStreamsVelocitySetpointsForItsDuration) {
  auto p = std::make_unique<v1::MoveAtSpeedWithPlatformControlParameters>();
  p->set_velocity_x_m_s(0.5);
  p->set_yaw_rate_rad_s(0.1);
  p->set_duration_s(1.0);
  ASSERT_TRUE(move_at_speed_->activateAndWait(std::move(p)).ok());
  vehicle_.setVelocity(0.5, 0, 0);
  fly(std::chrono::seconds(2), move_at_speed_);
  const auto finished = events_.waitFinished();
  EXPECT_EQ(finished.finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED)
      << finished.ShortDebugString();
  const auto setpoints = vehicle_.setpoints();
  ASSERT_GE(setpoints.size(), 15u);
  EXPECT_DOUBLE_EQ(setpoints.back().velocity_yaw_rate().velocity_m_s().x(), 0.5);
  EXPECT_DOUBLE_EQ(setpoints.back().velocity_yaw_rate().yaw_rate_rad_s(), 0.1);
}

TEST_F(PlatformBehaviorsUnitTest, RotateTurnsTheYawSetpointTheShorterWayToItsTarget) {
  vehicle_.setYaw(3.0);
  auto p = std::make_unique<v1::RotateWithPlatformControlParameters>();
  p->set_yaw_rad(-3.0);  // 0.28 rad away across pi
  ASSERT_TRUE(rotate_->activateAndWait(std::move(p)).ok());
  fly(milliseconds(200), rotate_);
  const double yaw = vehicle_.setpoints().back().position_yaw().yaw_rad();
  EXPECT_TRUE(yaw > 3.0 || yaw < -3.0) << "through pi, not through zero: " << yaw;
  fly(std::chrono::seconds(3), rotate_,
      [&] { vehicle_.setYaw(vehicle_.setpoints().back().position_yaw().yaw_rad()); });
  const auto finished = events_.waitFinished();
  EXPECT_EQ(finished.finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED)
      << finished.ShortDebugString();
}

}  // namespace
}  // namespace behaviorlib::platform_motion
