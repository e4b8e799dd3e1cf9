// The monitoring of TAKE_OFF, LAND and HOVER_WITH_FLIGHT_ACTION_CONTROL
// against a fake vehicle on a FakeClock: each termination cause provoked
// through the input that should cause it.

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <thread>

#include "behaviorlib/basic_quadrotor_behaviors/hover_with_flight_action_behavior.h"
#include "behaviorlib/basic_quadrotor_behaviors/land_behavior.h"
#include "behaviorlib/basic_quadrotor_behaviors/take_off_behavior.h"
#include "behaviorlib/behavior_host.h"
#include "fake_clock_flight.h"
#include "fake_vehicle.h"
#include "test_behaviors.h"

namespace behaviorlib::basic {
namespace {

using std::chrono::milliseconds;
using testing::FakeVehicle;

std::unique_ptr<v1::TakeOffParameters> altitude(double altitude_m) {
  auto p = std::make_unique<v1::TakeOffParameters>();
  p->set_altitude_m(altitude_m);
  return p;
}

std::unique_ptr<v1::HoverWithFlightActionControlParameters> drift(double max_drift_m) {
  auto p = std::make_unique<v1::HoverWithFlightActionControlParameters>();
  p->set_max_drift_m(max_drift_m);
  return p;
}

class FlightBehaviorsUnitTest : public ::testing::Test {
 protected:
  void SetUp() override {
    host_.add(std::make_unique<TakeOffBehavior>(vehicle_));
    host_.add(std::make_unique<LandBehavior>(vehicle_));
    host_.add(std::make_unique<HoverWithFlightActionControlBehavior>(vehicle_));
    ASSERT_TRUE(host_.start().ok());
    take_off_ = host_.find("TAKE_OFF");
    land_ = host_.find("LAND");
    hover_ = host_.find("HOVER_WITH_FLIGHT_ACTION_CONTROL");
  }

  // Advances the fake clock in 50 ms steps (one tick each at 20 Hz), giving
  // waiting for the worker to tick, until `total` passed or `behavior` ended.
  void fly(Duration total, const BehaviorExecutionManager* behavior) {
    behaviorlib::testing::flyOnFakeClock(clock_, host_, total, milliseconds(50), behavior);
  }

  // fly()s until `condition` holds, for at most `limit` of the fake clock:
  // a worker slowed down by a busy machine ticks later, not less.
  template <typename Condition>
  bool flyUntil(Condition condition, Duration limit) {
    for (Duration done{0}; done < limit && !condition(); done += milliseconds(50)) {
      fly(milliseconds(50), take_off_);
    }
    return behaviorlib::testing::eventually(condition);
  }

  FakeClock clock_;
  FakeVehicle vehicle_{clock_};
  BehaviorHost host_{behaviorlib::testing::hostOptions("drone1", "basic_quadrotor_behaviors"),
                     clock_};
  behaviorlib::testing::EventCollector events_{host_.events()};
  BehaviorExecutionManager* take_off_ = nullptr;
  BehaviorExecutionManager* land_ = nullptr;
  BehaviorExecutionManager* hover_ = nullptr;
};

TEST_F(FlightBehaviorsUnitTest, TakeOffAchievesItsGoalOnlyAfterHoldingTheAltitudeForTheDwell) {
  ASSERT_TRUE(take_off_->activateAndWait(altitude(1.5)).ok());
  EXPECT_EQ(vehicle_.commands(), std::vector<std::string>{"TAKE_OFF 1.50"});
  EXPECT_EQ(vehicle_.leaseHolder(), "drone1/TAKE_OFF");
  vehicle_.setState(v1::FLIGHT_STATE_TAKING_OFF);
  vehicle_.setPosition(0, 0, 0.8);
  vehicle_.setVerticalSpeed(1.0);
  fly(milliseconds(500), take_off_);
  vehicle_.setState(v1::FLIGHT_STATE_HOVERING);
  vehicle_.setPosition(0, 0, 1.45);
  vehicle_.setVerticalSpeed(0.02);
  fly(milliseconds(800), take_off_);
  EXPECT_EQ(take_off_->state(), v1::BEHAVIOR_STATE_ACTIVE) << "the dwell is 1 s";
  fly(milliseconds(1000), take_off_);
  const auto finished = events_.waitFinished();
  EXPECT_EQ(finished.finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED)
      << finished.ShortDebugString();
  EXPECT_NE(finished.finished().message().find("1.50"), std::string::npos);
  // Already hovering: no HOVER needed, the lease is released.
  EXPECT_EQ(vehicle_.commands(), (std::vector<std::string>{"TAKE_OFF 1.50", "RELEASE"}));
  EXPECT_EQ(vehicle_.followers(), 0);
}

TEST_F(FlightBehaviorsUnitTest, TakeOffClosesTheRestOfTheClimbOnTheEstimate) {
  ASSERT_TRUE(take_off_->activateAndWait(altitude(1.5)).ok());
  // The platform's take-off ended where it measures 1.5 m; the estimate
  // (a drifting barometer) says 1.3 m.
  vehicle_.setState(v1::FLIGHT_STATE_HOVERING);
  vehicle_.setPosition(0, 0, 1.3);
  vehicle_.setVerticalSpeed(0.0);
  fly(milliseconds(700), take_off_);
  EXPECT_TRUE(vehicle_.setpoints().empty()) << "the platform's climb settles for a second first";
  ASSERT_TRUE(flyUntil([&] { return !vehicle_.setpoints().empty(); }, milliseconds(3000)));
  const v1::SetpointRequest up = vehicle_.setpoints().back();
  ASSERT_TRUE(up.has_velocity_yaw_rate());
  EXPECT_NEAR(up.velocity_yaw_rate().velocity_m_s().z(), 0.2, 0.01) << "1/s of the 0.2 m to go";
  EXPECT_EQ(up.velocity_yaw_rate().velocity_m_s().x(), 0.0);
  // Within half the tolerance: a speed of zero, then the goal after the dwell.
  vehicle_.setState(v1::FLIGHT_STATE_FLYING);
  vehicle_.setPosition(0, 0, 1.48);
  ASSERT_TRUE(flyUntil(
      [&] { return vehicle_.setpoints().back().velocity_yaw_rate().velocity_m_s().z() == 0.0; },
      milliseconds(1000)));
  const size_t sent = vehicle_.setpoints().size();
  fly(milliseconds(1500), take_off_);
  EXPECT_EQ(events_.waitFinished().finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED);
  EXPECT_EQ(vehicle_.setpoints().size(), sent) << "no setpoint once there";
}

TEST_F(FlightBehaviorsUnitTest, TakeOffClosesTheClimbAgainWhenAConvergingEstimateMovesAway) {
  // An EKF's height at the take-off point was 0.27 m (the target is then
  // 1.77 m); it converges while the vehicle hovers. The fake vehicle moves
  // at the vertical speed last sent, and the estimate falls 0.12 m once the
  // first correction has ended.
  vehicle_.setPosition(0, 0, 0.27);
  ASSERT_TRUE(take_off_->activateAndWait(altitude(1.5)).ok());
  double z = 1.66;
  vehicle_.setState(v1::FLIGHT_STATE_HOVERING);
  vehicle_.setPosition(0, 0, z);
  vehicle_.setVerticalSpeed(0.0);
  int corrections = 0;
  double last_vz = 0.0;
  bool converged = false;
  for (int i = 0; i < 300 && take_off_->state() == v1::BEHAVIOR_STATE_ACTIVE; ++i) {
    fly(milliseconds(50), take_off_);
    const auto sent = vehicle_.setpoints();
    const double vz = sent.empty() ? 0.0 : sent.back().velocity_yaw_rate().velocity_m_s().z();
    if (vz != 0.0 && last_vz == 0.0) {
      ++corrections;
      EXPECT_GE(vz, 0.1) << "at least 0.1 m/s: a few centimetres close within the window";
    }
    if (vz == 0.0 && last_vz != 0.0 && !converged) {
      converged = true;
      z -= 0.12;
    }
    last_vz = vz;
    if (!sent.empty()) vehicle_.setState(v1::FLIGHT_STATE_FLYING);
    z += vz * 0.05;
    vehicle_.setPosition(0, 0, z);
    vehicle_.setVerticalSpeed(vz);
  }
  const auto finished = events_.waitFinished();
  EXPECT_EQ(finished.finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED)
      << finished.ShortDebugString();
  EXPECT_NE(finished.finished().message().find("target 1.77"), std::string::npos)
      << finished.ShortDebugString();
  EXPECT_EQ(corrections, 2) << "closed once after the take-off, once after the estimate moved";
}

TEST_F(FlightBehaviorsUnitTest, AVehicleFallingAfterItsTakeOffIsNotCorrectedButWrongProgress) {
  // A motor lost after the platform's take-off: the platform still reports
  // HOVERING while the vehicle falls at 0.5 m/s. That is no settle to
  // correct from; the progress window ends it before the vehicle reaches the
  // ground.
  ASSERT_TRUE(take_off_->activateAndWait(altitude(3.0)).ok());
  vehicle_.setState(v1::FLIGHT_STATE_HOVERING);
  vehicle_.setVerticalSpeed(-0.5);
  double z = 2.9;
  for (int i = 0; i < 80 && take_off_->state() == v1::BEHAVIOR_STATE_ACTIVE; ++i) {
    vehicle_.setPosition(0, 0, z);
    fly(milliseconds(50), take_off_);
    z = std::max(0.0, z - 0.025);
  }
  const auto finished = events_.waitFinished();
  EXPECT_EQ(finished.finished().cause(), v1::TERMINATION_CAUSE_WRONG_PROGRESS)
      << finished.ShortDebugString();
  EXPECT_GT(z, 0.0) << "ended before the ground";
  EXPECT_TRUE(vehicle_.setpoints().empty()) << "a fall is not an altitude to correct";
}

TEST_F(FlightBehaviorsUnitTest, TakeOffWithAVerticalSpeedAboveTheLimitIsNotAGoal) {
  ASSERT_TRUE(take_off_->activateAndWait(altitude(1.0)).ok());
  vehicle_.setState(v1::FLIGHT_STATE_HOVERING);
  vehicle_.setPosition(0, 0, 1.0);
  vehicle_.setVerticalSpeed(0.5);
  fly(milliseconds(2000), take_off_);
  EXPECT_EQ(take_off_->state(), v1::BEHAVIOR_STATE_ACTIVE);
  ASSERT_TRUE(take_off_->deactivateAndWait().ok());
  // Interrupted: hovering already, so only the release.
  EXPECT_EQ(vehicle_.commands().back(), "RELEASE");
}

TEST_F(FlightBehaviorsUnitTest, TakeOffModifiedSendsTheNewAltitudeOnceTheTakeOffActionEnded) {
  ASSERT_TRUE(take_off_->activateAndWait(altitude(1.0)).ok());
  vehicle_.setState(v1::FLIGHT_STATE_TAKING_OFF);
  vehicle_.setPosition(0, 0, 0.5);
  vehicle_.setVerticalSpeed(1.0);
  ASSERT_TRUE(take_off_->modifyAndWait(altitude(2.0)).ok());
  fly(milliseconds(200), take_off_);
  EXPECT_EQ(vehicle_.commands(), std::vector<std::string>{"TAKE_OFF 1.00"})
      << "no setpoint while the platform's take-off runs";
  vehicle_.setState(v1::FLIGHT_STATE_HOVERING);
  vehicle_.setPosition(0, 0, 1.0);
  vehicle_.setVerticalSpeed(0.0);
  fly(milliseconds(200), take_off_);
  EXPECT_TRUE(behaviorlib::testing::eventually([&] {
    return vehicle_.commands() == std::vector<std::string>{"TAKE_OFF 1.00", "GOTO 2.00"};
  }));
  EXPECT_EQ(take_off_->state(), v1::BEHAVIOR_STATE_ACTIVE) << "1.0 m is not the new goal";
  vehicle_.setState(v1::FLIGHT_STATE_FLYING);
  vehicle_.setPosition(0, 0, 2.0);
  fly(milliseconds(1500), take_off_);
  const auto finished = events_.waitFinished();
  EXPECT_EQ(finished.finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED)
      << finished.ShortDebugString();
  // FLYING on a setpoint when it ended: HOVER, then the release.
  EXPECT_EQ(vehicle_.commands(),
            (std::vector<std::string>{"TAKE_OFF 1.00", "GOTO 2.00", "HOVER", "RELEASE"}));
}

TEST_F(FlightBehaviorsUnitTest, TakeOffIsRefusedUnlessLandedWithEnoughBattery) {
  vehicle_.setState(v1::FLIGHT_STATE_HOVERING);
  auto refused = take_off_->activateAndWait(altitude(1.0));
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_NE(refused.status().message().find("LANDED"), std::string::npos)
      << refused.status().message();
  vehicle_.setState(v1::FLIGHT_STATE_LANDED);
  vehicle_.setBattery(0.1);
  refused = take_off_->activateAndWait(altitude(1.0));
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_NE(refused.status().message().find("battery"), std::string::npos)
      << refused.status().message();
  EXPECT_TRUE(vehicle_.commands().empty()) << "nothing was commanded";

  // The performance estimate falls with the battery.
  vehicle_.setBattery(0.9);
  const auto full = take_off_->checkSituationAndWait();
  vehicle_.setBattery(0.4);
  const auto low = take_off_->checkSituationAndWait();
  ASSERT_TRUE(full.ok() && low.ok());
  EXPECT_TRUE(full->feasible() && low->feasible());
  EXPECT_DOUBLE_EQ(full->performance_ratio(), 1.0);
  EXPECT_LT(low->performance_ratio(), 0.7);

  vehicle_.setReachable(false);
  const auto unreachable = take_off_->checkSituationAndWait();
  ASSERT_TRUE(unreachable.ok());
  EXPECT_FALSE(unreachable->feasible());
  EXPECT_NE(unreachable->reasons(0).find("unreachable"), std::string::npos);
}

TEST_F(FlightBehaviorsUnitTest, TakeOffWithoutClimbIsWrongProgress) {
  ASSERT_TRUE(take_off_->activateAndWait(altitude(2.0)).ok());
  vehicle_.setState(v1::FLIGHT_STATE_TAKING_OFF);
  vehicle_.setPosition(0, 0, 0.3);
  fly(milliseconds(4000), take_off_);
  const auto finished = events_.waitFinished();
  EXPECT_EQ(finished.finished().cause(), v1::TERMINATION_CAUSE_WRONG_PROGRESS)
      << finished.ShortDebugString();
  EXPECT_NE(finished.finished().message().find("no progress"), std::string::npos);
  // Left hovering: TAKING_OFF when it ended, so HOVER before the release.
  EXPECT_EQ(vehicle_.commands(), (std::vector<std::string>{"TAKE_OFF 2.00", "HOVER", "RELEASE"}));
}

TEST_F(FlightBehaviorsUnitTest, ASmallOvershootAfterAFastClimbIsNotWrongProgress) {
  ASSERT_TRUE(take_off_->activateAndWait(altitude(4.3)).ok());
  vehicle_.setState(v1::FLIGHT_STATE_TAKING_OFF);
  vehicle_.setPosition(0, 0, 1.0);
  vehicle_.setVerticalSpeed(2.0);
  fly(milliseconds(1000), take_off_);
  // Overshoots by 0.3 m (beyond the 0.1 m tolerance) after climbing 3.6 m:
  // the climb window says "away from the target", but it is the settling.
  vehicle_.setState(v1::FLIGHT_STATE_HOVERING);
  vehicle_.setPosition(0, 0, 4.6);
  vehicle_.setVerticalSpeed(0.0);
  fly(milliseconds(1500), take_off_);
  EXPECT_EQ(take_off_->state(), v1::BEHAVIOR_STATE_ACTIVE)
      << events_.waitFinished().ShortDebugString();
  // Back within the tolerance: the goal, after the dwell.
  vehicle_.setPosition(0, 0, 4.32);
  fly(milliseconds(2500), take_off_);
  EXPECT_EQ(events_.waitFinished().finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED);
}

TEST_F(FlightBehaviorsUnitTest, AnOvershootThatKeepsGoingIsWrongProgress) {
  ASSERT_TRUE(take_off_->activateAndWait(altitude(1.0)).ok());
  vehicle_.setState(v1::FLIGHT_STATE_FLYING);
  vehicle_.setVerticalSpeed(1.0);
  for (int i = 0; i < 40 && take_off_->state() == v1::BEHAVIOR_STATE_ACTIVE; ++i) {
    vehicle_.setPosition(0, 0, 1.2 + 0.1 * i);  // climbing on, past the target
    fly(milliseconds(100), take_off_);
  }
  const auto finished = events_.waitFinished();
  EXPECT_EQ(finished.finished().cause(), v1::TERMINATION_CAUSE_WRONG_PROGRESS)
      << finished.ShortDebugString();
}

TEST_F(FlightBehaviorsUnitTest, TakeOffEndsWithWrongProgressOnAnUnexpectedLanding) {
  ASSERT_TRUE(take_off_->activateAndWait(altitude(2.0)).ok());
  vehicle_.setState(v1::FLIGHT_STATE_TAKING_OFF);
  vehicle_.setPosition(0, 0, 0.5);
  fly(milliseconds(200), take_off_);
  vehicle_.setState(v1::FLIGHT_STATE_LANDING);
  fly(milliseconds(200), take_off_);
  const auto finished = events_.waitFinished();
  EXPECT_EQ(finished.finished().cause(), v1::TERMINATION_CAUSE_WRONG_PROGRESS);
  EXPECT_NE(finished.finished().message().find("unexpected landing"), std::string::npos)
      << finished.finished().message();
}

TEST_F(FlightBehaviorsUnitTest, TakeOffEndsWithProcessFailureWhenThePoseEstimateGoesStale) {
  ASSERT_TRUE(take_off_->activateAndWait(altitude(2.0)).ok());
  vehicle_.setState(v1::FLIGHT_STATE_TAKING_OFF);
  fly(milliseconds(200), take_off_);
  vehicle_.freezeEstimate(true);
  fly(milliseconds(450), take_off_);
  EXPECT_EQ(take_off_->state(), v1::BEHAVIOR_STATE_ACTIVE) << "0.45 s is within the 0.5 s limit";
  fly(milliseconds(200), take_off_);
  const auto finished = events_.waitFinished();
  EXPECT_EQ(finished.finished().cause(), v1::TERMINATION_CAUSE_PROCESS_FAILURE);
  EXPECT_NE(finished.finished().message().find("pose estimate"), std::string::npos)
      << finished.finished().message();
}

TEST_F(FlightBehaviorsUnitTest, AnUnreachableFlightControllerIsAProcessFailure) {
  ASSERT_TRUE(take_off_->activateAndWait(altitude(2.0)).ok());
  vehicle_.setState(v1::FLIGHT_STATE_TAKING_OFF);
  fly(milliseconds(100), take_off_);
  vehicle_.setReachable(false);
  fly(milliseconds(100), take_off_);
  const auto finished = events_.waitFinished();
  EXPECT_EQ(finished.finished().cause(), v1::TERMINATION_CAUSE_PROCESS_FAILURE);
  EXPECT_NE(finished.finished().message().find("unreachable"), std::string::npos)
      << finished.finished().message();
}

TEST_F(FlightBehaviorsUnitTest, LandAchievesItsGoalWhenLandedAndDetectsAStalledDescent) {
  auto refused = land_->activateAndWait(std::make_unique<v1::LandParameters>());
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_NE(refused.status().message().find("in the air"), std::string::npos);

  vehicle_.setState(v1::FLIGHT_STATE_HOVERING);
  vehicle_.setPosition(0, 0, 1.0);
  ASSERT_TRUE(land_->activateAndWait(std::make_unique<v1::LandParameters>()).ok());
  vehicle_.setState(v1::FLIGHT_STATE_LANDING);
  vehicle_.setPosition(0, 0, 0.5);
  fly(milliseconds(200), land_);
  vehicle_.setState(v1::FLIGHT_STATE_LANDED);
  vehicle_.setPosition(0, 0, 0.0);
  fly(milliseconds(200), land_);
  auto finished = events_.waitFinished();
  EXPECT_EQ(finished.finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED)
      << finished.ShortDebugString();
  EXPECT_EQ(vehicle_.commands(), (std::vector<std::string>{"LAND", "RELEASE"}));

  // Again, but the descent stalls at 0.8 m: WRONG_PROGRESS, and LAND leaves
  // the vehicle hovering.
  vehicle_.setState(v1::FLIGHT_STATE_HOVERING);
  vehicle_.setPosition(0, 0, 0.8);
  ASSERT_TRUE(land_->activateAndWait(std::make_unique<v1::LandParameters>()).ok());
  vehicle_.setState(v1::FLIGHT_STATE_LANDING);
  fly(milliseconds(4000), land_);
  finished = events_.waitFinished(1);
  EXPECT_EQ(finished.finished().cause(), v1::TERMINATION_CAUSE_WRONG_PROGRESS)
      << finished.ShortDebugString();
  EXPECT_NE(finished.finished().message().find("descent stalled"), std::string::npos);
  const auto commands = vehicle_.commands();
  ASSERT_GE(commands.size(), 2u);
  EXPECT_EQ(commands[commands.size() - 2], "HOVER");
}

TEST_F(FlightBehaviorsUnitTest, HoverReportsDriftAsWrongProgressAndALowBatteryAsSituationChange) {
  vehicle_.setState(v1::FLIGHT_STATE_HOVERING);
  vehicle_.setPosition(1, 2, 1.5);
  ASSERT_TRUE(hover_->activateAndWait(drift(0.3)).ok());
  EXPECT_EQ(vehicle_.commands(), std::vector<std::string>{"HOVER"});
  vehicle_.setPosition(1.2, 2, 1.5);
  fly(milliseconds(500), hover_);
  EXPECT_EQ(hover_->state(), v1::BEHAVIOR_STATE_ACTIVE) << "0.2 m is within 0.3 m";
  vehicle_.setPosition(1.4, 2, 1.5);
  fly(milliseconds(200), hover_);
  auto finished = events_.waitFinished();
  EXPECT_EQ(finished.finished().cause(), v1::TERMINATION_CAUSE_WRONG_PROGRESS);
  EXPECT_NE(finished.finished().message().find("drifted 0.40 m"), std::string::npos)
      << finished.finished().message();
  EXPECT_EQ(vehicle_.leaseHolder(), "") << "released";

  vehicle_.setPosition(1, 2, 1.5);
  ASSERT_TRUE(hover_->activateAndWait(drift(0.3)).ok());
  fly(milliseconds(500), hover_);
  vehicle_.setBattery(0.15);
  fly(milliseconds(200), hover_);
  finished = events_.waitFinished(1);
  EXPECT_EQ(finished.finished().cause(), v1::TERMINATION_CAUSE_SITUATION_CHANGE);
  EXPECT_NE(finished.finished().message().find("battery"), std::string::npos)
      << finished.finished().message();
}

TEST_F(FlightBehaviorsUnitTest, ALeaseTakenByAnotherHolderIsASituationChange) {
  vehicle_.setState(v1::FLIGHT_STATE_HOVERING);
  ASSERT_TRUE(hover_->activateAndWait(drift(0.5)).ok());
  fly(milliseconds(200), hover_);
  vehicle_.loseLease();
  fly(milliseconds(200), hover_);
  const auto finished = events_.waitFinished();
  EXPECT_EQ(finished.finished().cause(), v1::TERMINATION_CAUSE_SITUATION_CHANGE);
  EXPECT_NE(finished.finished().message().find("intruder"), std::string::npos)
      << finished.finished().message();
}

// The lean (pitch, rad) of the simulated airframe (1.5 kg, body drag
// 0.25 v + 0.04 v^2 N) holding still in a wind of `wind_m_s`.
double leanInWind(double wind_m_s) {
  return std::asin((0.25 * wind_m_s + 0.04 * wind_m_s * wind_m_s) / (1.5 * 9.81));
}

TEST_F(FlightBehaviorsUnitTest, HoverPerformanceFallsInTheWindTheVehicleLeansAgainst) {
  vehicle_.setState(v1::FLIGHT_STATE_HOVERING);
  vehicle_.setPosition(0, 0, 1.5);
  auto calm = hover_->checkSituationAndWait();
  ASSERT_TRUE(calm.ok());
  EXPECT_TRUE(calm->feasible());
  EXPECT_DOUBLE_EQ(calm->performance_ratio(), 1.0) << calm->ShortDebugString();

  // Leaning against 6 m/s of wind (seen along the body's x axis: 6.1 m/s of
  // horizontal wind): 1 - 0.8 (6.1 - 2) / (10 - 2) = 0.59, before
  // activation from the latest estimate...
  vehicle_.setTilt(0.0, leanInWind(6.0));
  clock_.advance(std::chrono::seconds(1));  // a new sample of the estimate
  auto windy = hover_->checkSituationAndWait();
  ASSERT_TRUE(windy.ok());
  EXPECT_TRUE(windy->feasible()) << "wind alone does not make it infeasible";
  EXPECT_NEAR(windy->performance_ratio(), 0.59, 0.03) << windy->ShortDebugString();
  ASSERT_EQ(windy->reasons_size(), 1);
  EXPECT_NE(windy->reasons(0).find("wind of about 6.1"), std::string::npos) << windy->reasons(0);

  // ... and while active, with the battery's factor on top.
  ASSERT_TRUE(hover_->activateAndWait(drift(1.0)).ok());
  fly(milliseconds(2000), hover_);
  windy = hover_->checkSituationAndWait();
  ASSERT_TRUE(windy.ok());
  EXPECT_NEAR(windy->performance_ratio(), 0.59, 0.03) << windy->ShortDebugString();
  vehicle_.setBattery(0.45);  // factor 0.2 + 0.8 * (0.45 - 0.3) / (0.6 - 0.3) = 0.6
  fly(milliseconds(100), hover_);
  windy = hover_->checkSituationAndWait();
  ASSERT_TRUE(windy.ok());
  EXPECT_NEAR(windy->performance_ratio(), 0.6 * 0.59, 0.03) << windy->ShortDebugString();

  // The wind drops: back to the battery's factor within a few seconds.
  vehicle_.setBattery(1.0);
  vehicle_.setTilt(0.0, 0.0);
  fly(milliseconds(300), hover_);
  auto easing = hover_->checkSituationAndWait();
  ASSERT_TRUE(easing.ok());
  EXPECT_LT(easing->performance_ratio(), 0.9) << "filtered: " << easing->ShortDebugString();
  fly(milliseconds(4000), hover_);
  calm = hover_->checkSituationAndWait();
  ASSERT_TRUE(calm.ok());
  EXPECT_DOUBLE_EQ(calm->performance_ratio(), 1.0) << calm->ShortDebugString();
  EXPECT_EQ(hover_->state(), v1::BEHAVIOR_STATE_ACTIVE);
  ASSERT_TRUE(hover_->deactivateAndWait().ok());
}

}  // namespace
}  // namespace behaviorlib::basic
