// QUADROTOR_MPC_MOTION_CONTROL and HOVER_WITH_MPC_CONTROL (the MPC system's
// behaviors, from behaviorlib::motion_behaviors) against a fake vehicle and an
// in-memory motion link on a FakeClock.

#include <gtest/gtest.h>

#include <functional>
#include <thread>

#include "behaviorlib/behavior_host.h"
#include "behaviorlib/motion_behaviors/hover_behavior.h"
#include "behaviorlib/motion_behaviors/motion_control_behavior.h"
#include "behaviorlib/motion_behaviors/motion_messages.h"
#include "behaviorlib/v1/behaviors/quadrotor_motion_with_mpc_control.pb.h"
#include "fake_clock_flight.h"
#include "fake_motion_link.h"
#include "fake_vehicle.h"
#include "test_behaviors.h"

namespace behaviorlib::motion_behaviors {
namespace {

using std::chrono::milliseconds;
using FakeVehicle = basic::testing::FakeVehicle;
using testing::FakeMotionLink;

class MpcControlUnitTest : public ::testing::Test {
 protected:
  void SetUp() override {
    vehicle_.setState(v1::FLIGHT_STATE_HOVERING);
    vehicle_.setPosition(0, 0, 2);
    host_.add(std::make_unique<HoverBehavior<v1::HoverWithMpcControlParameters>>(vehicle_, link_));
    host_.add(std::make_unique<MotionControlBehavior<v1::QuadrotorMpcMotionControlParameters,
                                                     config::v1::MpcMotionControlConfig>>(
        vehicle_, link_, [](const ControllerConfig& config, const motion::VehicleModel& model) {
          return makeMpcController(model, config.mpc);
        }));
    ASSERT_TRUE(host_.start().ok());
    hover_ = host_.find("HOVER_WITH_MPC_CONTROL");
    controller_ = host_.find("QUADROTOR_MPC_MOTION_CONTROL");
  }

  // Advances the fake clock in 10 ms steps (one controller tick each) until
  // `total` passed or `behavior` ended; `each` runs after every step.
  void fly(Duration total, const BehaviorExecutionManager* behavior,
           const std::function<void()>& each = nullptr) {
    behaviorlib::testing::flyOnFakeClock(clock_, host_, total, milliseconds(10), behavior, each);
  }

  FakeClock clock_;
  FakeVehicle vehicle_{clock_};
  FakeMotionLink link_;
  BehaviorHost host_{
      behaviorlib::testing::hostOptions("drone1", "quadrotor_motion_with_mpc_control"), clock_};
  behaviorlib::testing::EventCollector events_{host_.events()};
  BehaviorExecutionManager* hover_ = nullptr;
  BehaviorExecutionManager* controller_ = nullptr;
};

TEST_F(MpcControlUnitTest, TheControllerFollowsTheHoverReferenceAndTheHoverSeesItFollowed) {
  auto params = std::make_unique<v1::QuadrotorMpcMotionControlParameters>();
  params->set_max_tilt_rad(0.3);
  ASSERT_TRUE(controller_->activateAndWait(std::move(params)).ok());
  auto hover = hover_->activateAndWait(std::make_unique<v1::HoverWithMpcControlParameters>());
  ASSERT_TRUE(hover.ok()) << hover.status();
  fly(std::chrono::seconds(3), hover_);
  EXPECT_EQ(hover_->state(), v1::BEHAVIOR_STATE_ACTIVE) << "a controller follows it";
  const auto statuses = link_.statuses();
  ASSERT_FALSE(statuses.empty());
  EXPECT_EQ(statuses.back().controller(), "QUADROTOR_MPC_MOTION_CONTROL");
  EXPECT_EQ(statuses.back().state(), v1::MOTION_CONTROLLER_STATE_TRACKING);
  EXPECT_EQ(statuses.back().reference_source(), hover->activation_id());
  const auto setpoints = vehicle_.setpoints();
  ASSERT_GE(setpoints.size(), 250u);
  EXPECT_NEAR(setpoints.back().attitude_thrust().thrust_ratio(), 1.5 * 9.81 / 48.0, 0.03);

  // The vehicle pushed 1 m away: the MPC tilts towards the point, within
  // its tilt limit; the hover drifts beyond 0.5 m: WRONG_PROGRESS.
  vehicle_.setPosition(-1, 0, 2);
  fly(milliseconds(100), hover_);
  const auto& q = vehicle_.setpoints().back().attitude_thrust().orientation();
  const double tilt = 2.0 * std::acos(std::min(1.0, std::sqrt(q.w() * q.w() + q.z() * q.z())));
  EXPECT_GT(q.y(), 0.01) << "pitched to accelerate east";
  EXPECT_LE(tilt, 0.3 + 1e-6);
  const auto finished = events_.waitFinished();
  EXPECT_EQ(finished.activation_id(), hover->activation_id());
  EXPECT_EQ(finished.finished().cause(), v1::TERMINATION_CAUSE_WRONG_PROGRESS)
      << finished.ShortDebugString();
  ASSERT_TRUE(controller_->deactivateAndWait().ok());
  EXPECT_EQ(link_.statuses().back().state(), v1::MOTION_CONTROLLER_STATE_STOPPED);
  EXPECT_EQ(vehicle_.commands().back(), "RELEASE");
}

TEST_F(MpcControlUnitTest, AnOutputThatIsNotFiniteEndsTheControllerWithProcessFailure) {
  ASSERT_TRUE(
      controller_->activateAndWait(std::make_unique<v1::QuadrotorMpcMotionControlParameters>())
          .ok());
  fly(milliseconds(100), controller_);
  const size_t sent = vehicle_.setpoints().size();
  ASSERT_GE(sent, 5u);
  // A diverged estimate: the MPC refuses it (output not finite), nothing
  // more is sent.
  vehicle_.setVelocity(0, NAN, 0);
  fly(milliseconds(200), controller_);
  const auto finished = events_.waitFinished();
  EXPECT_EQ(finished.finished().cause(), v1::TERMINATION_CAUSE_PROCESS_FAILURE)
      << finished.ShortDebugString();
  EXPECT_NE(finished.finished().message().find("output is not finite"), std::string::npos)
      << finished.finished().message();
  EXPECT_EQ(vehicle_.setpoints().size(), sent) << "no setpoint after the NaN";
  EXPECT_EQ(vehicle_.commands().back(), "RELEASE");
  EXPECT_EQ(link_.statuses().back().state(), v1::MOTION_CONTROLLER_STATE_STOPPED);
}

TEST_F(MpcControlUnitTest, AnOutputSaturatedLongerThanTheTimeoutEndsWithProcessFailure) {
  ASSERT_TRUE(
      controller_->activateAndWait(std::make_unique<v1::QuadrotorMpcMotionControlParameters>())
          .ok());
  // A fresh reference 50 m north that the (fake) vehicle never approaches:
  // the MPC's first input sits on its box limit every step.
  auto far_reference = [&] {
    v1::MotionReference reference = toProto(holdAt({0, 50, 2}, 0.0));
    stampHeader(clock_.now(), "drone1", 1, reference.mutable_header());
    reference.set_source("TEST-FAR");
    ASSERT_TRUE(link_.publishReference(reference).ok());
  };
  fly(milliseconds(1500), controller_, far_reference);
  EXPECT_EQ(controller_->state(), v1::BEHAVIOR_STATE_ACTIVE) << "saturation_timeout_s is 2 s";
  ASSERT_FALSE(link_.statuses().empty());
  EXPECT_TRUE(link_.statuses().back().saturated()) << link_.statuses().back().ShortDebugString();
  fly(milliseconds(1000), controller_, far_reference);
  const auto finished = events_.waitFinished();
  EXPECT_EQ(finished.finished().cause(), v1::TERMINATION_CAUSE_PROCESS_FAILURE)
      << finished.ShortDebugString();
  EXPECT_NE(finished.finished().message().find("saturated (tilt or thrust limit)"),
            std::string::npos)
      << finished.finished().message();
  EXPECT_NE(finished.finished().message().find("saturation_timeout_s"), std::string::npos)
      << finished.finished().message();
  EXPECT_EQ(vehicle_.commands().back(), "RELEASE");
}

}  // namespace
}  // namespace behaviorlib::motion_behaviors
