#include "simulator/platform/vehicle_platform.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <limits>

namespace behaviorlib::sim {
namespace {

using std::chrono::milliseconds;
using std::chrono::seconds;
using ::testing::HasSubstr;
using Kind = PlatformCommand::Kind;

class VehiclePlatformTest : public ::testing::Test {
 protected:
  // Advances time and feeds the platform a vehicle snapshot.
  void at(SimDuration t, double z, bool on_ground = false) {
    now_ = t;
    vehicle_.position_m = {3.0, 4.0, z};
    vehicle_.on_ground = on_ground;
    platform_.update(now_, vehicle_);
  }
  std::string lease(const std::string& holder = "controller", bool preempt = false) {
    auto r = platform_.acquireLease(holder, milliseconds(500), preempt, now_);
    EXPECT_TRUE(r.ok()) << r.status();
    return r.ok() ? r->lease_id() : "";
  }
  // Takes off to 2 m and reaches HOVERING.
  std::string flyToHover() {
    at(seconds(0), 0.0, true);
    const std::string id = lease();
    EXPECT_TRUE(platform_.executeAction(v1::FLIGHT_ACTION_TAKE_OFF, id, 2.0, false, now_).ok());
    at(milliseconds(400), 2.0);  // within the lease's 0.5 s
    EXPECT_EQ(platform_.state(), v1::FLIGHT_STATE_HOVERING);
    return id;
  }
  v1::SetpointRequest velocity(const std::string& lease_id, double vx) {
    v1::SetpointRequest r;
    r.set_robot_id("drone1");
    r.set_lease_id(lease_id);
    r.mutable_velocity_yaw_rate()->mutable_velocity_m_s()->set_x(vx);
    return r;
  }

  VehiclePlatform platform_{"drone1", PlatformOptions{}};
  VehicleSnapshot vehicle_;
  SimTime now_{0};
};

TEST_F(VehiclePlatformTest, TakeOffClimbsThenHoversAtTheTargetAltitude) {
  at(seconds(0), 0.0, true);
  EXPECT_EQ(platform_.state(), v1::FLIGHT_STATE_LANDED);
  EXPECT_EQ(platform_.command().kind, Kind::kIdle);
  const std::string id = lease();
  auto state = platform_.executeAction(v1::FLIGHT_ACTION_TAKE_OFF, id, 2.0, false, now_);
  ASSERT_TRUE(state.ok()) << state.status();
  EXPECT_EQ(*state, v1::FLIGHT_STATE_TAKING_OFF);
  at(milliseconds(100), 0.1);
  EXPECT_EQ(platform_.command().kind, Kind::kVelocityYawRate);
  EXPECT_GT(platform_.command().vector.z(), 0.0);
  EXPECT_TRUE(platform_.renewLease(id, now_).ok());
  at(milliseconds(400), 1.95);
  EXPECT_EQ(platform_.state(), v1::FLIGHT_STATE_HOVERING);
  EXPECT_EQ(platform_.command().kind, Kind::kPositionYaw);
  EXPECT_DOUBLE_EQ(platform_.command().vector.z(), 2.0);
  EXPECT_DOUBLE_EQ(platform_.command().vector.x(), 3.0);
}

TEST_F(VehiclePlatformTest, TakeOffRefusedWithoutLeaseOrWhenFlyingOrWithBadAltitude) {
  at(seconds(0), 0.0, true);
  auto no_lease = platform_.executeAction(v1::FLIGHT_ACTION_TAKE_OFF, "", 2.0, false, now_);
  EXPECT_EQ(no_lease.status().code(), absl::StatusCode::kFailedPrecondition);
  const std::string id = lease();
  EXPECT_EQ(
      platform_.executeAction(v1::FLIGHT_ACTION_TAKE_OFF, id, 500.0, false, now_).status().code(),
      absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(
      platform_.executeAction(v1::FLIGHT_ACTION_UNSPECIFIED, id, 0, false, now_).status().code(),
      absl::StatusCode::kInvalidArgument);
  ASSERT_TRUE(platform_.executeAction(v1::FLIGHT_ACTION_TAKE_OFF, id, 0.0, false, now_).ok());
  auto again = platform_.executeAction(v1::FLIGHT_ACTION_TAKE_OFF, id, 1.0, false, now_);
  EXPECT_EQ(again.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(again.status().message(), HasSubstr("TAKING_OFF"));
}

TEST_F(VehiclePlatformTest, LeaseRefusesASecondCommanderUnlessPreempted) {
  const std::string first = flyToHover();
  auto second = platform_.acquireLease("intruder", milliseconds(500), false, now_);
  EXPECT_EQ(second.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(second.status().message(), HasSubstr("'controller'"));
  EXPECT_EQ(platform_.setpoint(velocity("forged", 1.0), now_).status().code(),
            absl::StatusCode::kFailedPrecondition);
  EXPECT_EQ(platform_.setpoint(velocity("", 1.0), now_).status().code(),
            absl::StatusCode::kFailedPrecondition);
  ASSERT_TRUE(platform_.setpoint(velocity(first, 1.0), now_).ok());
  EXPECT_EQ(platform_.state(), v1::FLIGHT_STATE_FLYING);

  const std::string safety = lease("safety", /*preempt=*/true);
  EXPECT_EQ(platform_.leaseHolder(), "safety");
  EXPECT_EQ(platform_.setpoint(velocity(first, 2.0), now_).status().code(),
            absl::StatusCode::kFailedPrecondition);
  EXPECT_TRUE(platform_.setpoint(velocity(safety, 0.0), now_).ok());
}

TEST_F(VehiclePlatformTest, SetpointsAreValidated) {
  const std::string id = flyToHover();
  auto nan = velocity(id, std::numeric_limits<double>::quiet_NaN());
  auto r = platform_.setpoint(nan, now_);
  EXPECT_EQ(r.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(r.status().message(), HasSubstr("velocity_yaw_rate.velocity_m_s"));
  EXPECT_EQ(platform_.setpoint(velocity(id, 50.0), now_).status().code(),
            absl::StatusCode::kInvalidArgument);

  v1::SetpointRequest thrust;
  thrust.set_lease_id(id);
  thrust.mutable_thrust_rates()->set_thrust_ratio(1.5);
  EXPECT_EQ(platform_.setpoint(thrust, now_).status().code(), absl::StatusCode::kInvalidArgument);

  v1::SetpointRequest attitude;
  attitude.set_lease_id(id);
  attitude.mutable_attitude_thrust()->mutable_orientation()->set_w(2.0);
  attitude.mutable_attitude_thrust()->set_thrust_ratio(0.5);
  auto q = platform_.setpoint(attitude, now_);
  EXPECT_EQ(q.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(q.status().message(), HasSubstr("unit quaternion"));

  v1::SetpointRequest empty;
  empty.set_lease_id(id);
  EXPECT_EQ(platform_.setpoint(empty, now_).status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(platform_.state(), v1::FLIGHT_STATE_HOVERING) << "refused setpoints change nothing";

  v1::SetpointRequest position;
  position.set_lease_id(id);
  position.mutable_position_yaw()->mutable_position_m()->set_z(5.0);
  position.mutable_position_yaw()->set_yaw_rad(1.0);
  ASSERT_TRUE(platform_.setpoint(position, now_).ok());
  EXPECT_EQ(platform_.command().kind, Kind::kPositionYaw);
  EXPECT_DOUBLE_EQ(platform_.command().yaw_rad, 1.0);
}

TEST_F(VehiclePlatformTest, SetpointsOnTheGroundAreRefused) {
  at(seconds(0), 0.0, true);
  const std::string id = lease();
  auto r = platform_.setpoint(velocity(id, 1.0), now_);
  EXPECT_EQ(r.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(r.status().message(), HasSubstr("TAKE_OFF first"));
}

TEST_F(VehiclePlatformTest, LeaseLossHoversThenLands) {
  const std::string id = flyToHover();
  ASSERT_TRUE(platform_.setpoint(velocity(id, 1.0), now_).ok());  // at 0.4 s: expires at 0.9 s
  at(milliseconds(850), 2.0);
  EXPECT_EQ(platform_.state(), v1::FLIGHT_STATE_FLYING) << "lease still alive";
  at(seconds(1), 2.0);
  EXPECT_EQ(platform_.state(), v1::FLIGHT_STATE_HOVERING);
  EXPECT_TRUE(platform_.failsafeActive());
  EXPECT_EQ(platform_.leaseHolder(), "");
  EXPECT_EQ(platform_.command().kind, Kind::kPositionYaw);
  EXPECT_EQ(platform_.setpoint(velocity(id, 1.0), now_).status().code(),
            absl::StatusCode::kFailedPrecondition);
  at(milliseconds(5900), 2.0);
  EXPECT_EQ(platform_.state(), v1::FLIGHT_STATE_HOVERING) << "hovers for 5 s first";
  at(milliseconds(6100), 2.0);
  EXPECT_EQ(platform_.state(), v1::FLIGHT_STATE_LANDING);
  EXPECT_LT(platform_.command().vector.z(), 0.0);
  at(seconds(10), 0.0, true);
  EXPECT_EQ(platform_.state(), v1::FLIGHT_STATE_LANDED);
  EXPECT_EQ(platform_.command().kind, Kind::kIdle);
  EXPECT_FALSE(platform_.failsafeActive());
}

TEST_F(VehiclePlatformTest, NewLeaseDuringFailsafeCancelsTheLanding) {
  const std::string id = flyToHover();
  ASSERT_TRUE(platform_.setpoint(velocity(id, 1.0), now_).ok());
  at(seconds(2), 2.0);
  ASSERT_TRUE(platform_.failsafeActive());
  const std::string fresh = lease("controller2");
  EXPECT_FALSE(platform_.failsafeActive());
  ASSERT_TRUE(platform_.renewLease(fresh, now_).ok());
  at(seconds(2) + milliseconds(300), 2.0);
  EXPECT_EQ(platform_.state(), v1::FLIGHT_STATE_HOVERING);
}

TEST_F(VehiclePlatformTest, ReleasedLeaseHoversWithoutFailsafe) {
  const std::string id = flyToHover();
  ASSERT_TRUE(platform_.setpoint(velocity(id, 1.0), now_).ok());
  ASSERT_TRUE(platform_.releaseLease(id, now_).ok());
  EXPECT_EQ(platform_.state(), v1::FLIGHT_STATE_HOVERING);
  at(seconds(30), 2.0);
  EXPECT_EQ(platform_.state(), v1::FLIGHT_STATE_HOVERING);
  EXPECT_FALSE(platform_.failsafeActive());
}

TEST_F(VehiclePlatformTest, EmergencyLandAndKillOverrideTheLease) {
  flyToHover();
  auto emergency = platform_.executeAction(v1::FLIGHT_ACTION_EMERGENCY_LAND, "", 0.0, false, now_);
  ASSERT_TRUE(emergency.ok()) << emergency.status();
  EXPECT_EQ(*emergency, v1::FLIGHT_STATE_EMERGENCY);
  at(seconds(2), 1.0);
  EXPECT_EQ(platform_.command().kind, Kind::kVelocityYawRate);
  EXPECT_LT(platform_.command().vector.z(), -1.0);

  auto unconfirmed = platform_.executeAction(v1::FLIGHT_ACTION_KILL, "", 0.0, false, now_);
  EXPECT_EQ(unconfirmed.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(unconfirmed.status().message(), HasSubstr("confirm"));
  ASSERT_TRUE(platform_.executeAction(v1::FLIGHT_ACTION_KILL, "", 0.0, true, now_).ok());
  at(seconds(3), 0.5);
  EXPECT_EQ(platform_.command().kind, Kind::kIdle) << "killed motors stay off";
  at(seconds(4), 0.0, true);
  EXPECT_EQ(platform_.state(), v1::FLIGHT_STATE_LANDED);
}

TEST_F(VehiclePlatformTest, LandDescendsToLanded) {
  const std::string id = flyToHover();
  ASSERT_TRUE(platform_.executeAction(v1::FLIGHT_ACTION_LAND, id, 0.0, false, now_).ok());
  at(seconds(2), 1.0);
  EXPECT_EQ(platform_.state(), v1::FLIGHT_STATE_LANDING);
  EXPECT_NEAR(platform_.command().vector.z(), -0.6, 1e-9);
  at(seconds(4), 0.0, true);
  EXPECT_EQ(platform_.state(), v1::FLIGHT_STATE_LANDED);
  auto again = platform_.executeAction(v1::FLIGHT_ACTION_LAND, id, 0.0, false, now_);
  EXPECT_EQ(again.status().code(), absl::StatusCode::kFailedPrecondition);
}

TEST_F(VehiclePlatformTest, CrashIsTerminalUntilReset) {
  const std::string id = flyToHover();
  vehicle_.crashed = true;
  at(seconds(2), 0.0, true);
  EXPECT_EQ(platform_.state(), v1::FLIGHT_STATE_CRASHED);
  EXPECT_EQ(platform_.command().kind, Kind::kIdle);
  EXPECT_EQ(
      platform_.executeAction(v1::FLIGHT_ACTION_TAKE_OFF, id, 1.0, false, now_).status().code(),
      absl::StatusCode::kFailedPrecondition);
  EXPECT_EQ(platform_.acquireLease("x", milliseconds(500), true, now_).status().code(),
            absl::StatusCode::kFailedPrecondition);
}

TEST_F(VehiclePlatformTest, LeaseArgumentsAreValidated) {
  EXPECT_EQ(platform_.acquireLease("", milliseconds(500), false, now_).status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(platform_.acquireLease("c", milliseconds(10), false, now_).status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(platform_.acquireLease("c", seconds(60), false, now_).status().code(),
            absl::StatusCode::kInvalidArgument);
  auto r = platform_.acquireLease("c", SimDuration::zero(), false, now_);
  ASSERT_TRUE(r.ok());
  EXPECT_EQ(r->expire_time().nanos(), 500000000) << "default ttl 0.5 s";
}

}  // namespace
}  // namespace behaviorlib::sim
