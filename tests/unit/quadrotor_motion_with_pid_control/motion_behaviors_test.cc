// The behaviors of quadrotor_motion_with_pid_control (and the pieces of
// behaviorlib::motion_behaviors they share with the MPC system) against a
// fake vehicle and an in-memory motion link on a FakeClock: references and
// their conversions, path checks, FOLLOW_PATH's goal and its watch on the
// controller, and the controller's hold, tracking, status and failures.

#include <gtest/gtest.h>

#include <cmath>
#include <thread>

#include "behaviorlib/behavior_host.h"
#include "behaviorlib/motion_behaviors/follow_path_behavior.h"
#include "behaviorlib/motion_behaviors/motion_control_behavior.h"
#include "behaviorlib/motion_behaviors/motion_messages.h"
#include "behaviorlib/motion_behaviors/rotate_behavior.h"
#include "behaviorlib/v1/behaviors/quadrotor_motion_with_pid_control.pb.h"
#include "fake_clock_flight.h"
#include "fake_motion_link.h"
#include "fake_vehicle.h"
#include "test_behaviors.h"

namespace behaviorlib::motion_behaviors {
namespace {

using std::chrono::milliseconds;
using FakeVehicle = basic::testing::FakeVehicle;
using testing::FakeMotionLink;

// ---- messages and path checks (no threads) --------------------------------

motion::MotionReference straightTrajectory() {
  // 1 m/s along x: the point at x = 0, horizon[i] at x = (i + 1) * 0.1.
  motion::MotionReference r;
  r.mode = motion::MotionReference::Mode::kTrajectory;
  r.point.velocity_m_s = {1, 0, 0};
  r.horizon_step_s = 0.1;
  for (int i = 0; i < 20; ++i) {
    motion::ReferencePoint p;
    p.position_m = {(i + 1) * 0.1, 0, 1};
    p.velocity_m_s = {1, 0, 0};
    r.horizon.push_back(p);
  }
  r.point.position_m = {0, 0, 1};
  return r;
}

TEST(MotionMessagesTest, AReferenceSurvivesTheRoundTripThroughItsMessage) {
  const motion::MotionReference r = straightTrajectory();
  const motion::MotionReference back = fromProto(toProto(r));
  EXPECT_EQ(back.mode, motion::MotionReference::Mode::kTrajectory);
  ASSERT_EQ(back.horizon.size(), 20u);
  EXPECT_DOUBLE_EQ(back.horizon[7].position_m.x(), 0.8);
  EXPECT_DOUBLE_EQ(back.horizon_step_s, 0.1);
  EXPECT_EQ(fromProto(v1::MotionReference()).mode, motion::MotionReference::Mode::kPosition);
}

TEST(MotionMessagesTest, AnAgedTrajectoryMovesAlongItsHorizonAndStopsAtItsEnd) {
  const motion::MotionReference r = straightTrajectory();
  const motion::MotionReference aged = advance(r, 0.15);
  EXPECT_NEAR(aged.point.position_m.x(), 0.15, 1e-9);
  EXPECT_NEAR(aged.horizon[0].position_m.x(), 0.25, 1e-9);
  EXPECT_NEAR(advance(r, 5.0).point.position_m.x(), 2.0, 1e-9) << "held at the horizon's end";
  EXPECT_NEAR(advance(r, -1.0).point.position_m.x(), 0.0, 1e-9) << "a stamp ahead: as is";
  const motion::MotionReference hold = holdAt({1, 2, 3}, 0.5);
  EXPECT_EQ(advance(hold, 1.0).point.position_m, Eigen::Vector3d(1, 2, 3));
}

TEST(MotionMessagesTest, TurnTowardsTakesTheShorterWayAcrossPi) {
  EXPECT_NEAR(turnTowards(3.0, -3.0, 0.1), 3.1, 1e-9);
  EXPECT_NEAR(turnTowards(0.0, 1.0, 2.0), 1.0, 1e-9);
  EXPECT_NEAR(turnTowards(0.0, -1.0, 0.25), -0.25, 1e-9);
}

google::protobuf::RepeatedPtrField<v1::Vector3> path(
    std::initializer_list<std::array<double, 3>> points) {
  google::protobuf::RepeatedPtrField<v1::Vector3> out;
  for (const auto& p : points) {
    auto* v = out.Add();
    v->set_x(p[0]);
    v->set_y(p[1]);
    v->set_z(p[2]);
  }
  return out;
}

TEST(PathChecksTest, BadPathsAreInvalidArgumentNamingThePoint) {
  PathSettings settings;
  settings.max_path_points = 3;
  settings.max_path_length_m = 10;
  EXPECT_TRUE(makePathTracker(path({{1, 0, 1}, {2, 0, 1}}), 1, 1, settings, 0.2).ok());
  auto low = makePathTracker(path({{1, 0, 1}, {2, 0, 0.1}}), 1, 1, settings, 0.2);
  EXPECT_EQ(low.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(low.status().message().find("path_m[1]"), std::string::npos) << low.status();
  auto nan = makePathTracker(path({{1, NAN, 1}}), 1, 1, settings, 0.2);
  EXPECT_EQ(nan.status().code(), absl::StatusCode::kInvalidArgument) << nan.status();
  EXPECT_NE(nan.status().message().find("path_m[0]"), std::string::npos) << nan.status();
  auto many =
      makePathTracker(path({{1, 0, 1}, {2, 0, 1}, {3, 0, 1}, {4, 0, 1}}), 1, 1, settings, 0.2);
  EXPECT_NE(many.status().message().find("max_path_points"), std::string::npos) << many.status();
  auto long_path = makePathTracker(path({{0, 0, 1}, {20, 0, 1}}), 1, 1, settings, 0.2);
  EXPECT_EQ(long_path.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(long_path.status().message().find("path_m"), std::string::npos) << long_path.status();
  auto empty = makePathTracker(path({}), 1, 1, settings, 0.2);
  EXPECT_EQ(empty.status().code(), absl::StatusCode::kInvalidArgument);
}

// ---- behaviors on a fake clock --------------------------------------------

class MotionBehaviorsUnitTest : public ::testing::Test {
 protected:
  using FollowPath = FollowPathBehavior<v1::FollowPathParameters>;
  using Controller = MotionControlBehavior<v1::QuadrotorPidMotionControlParameters,
                                           config::v1::PidMotionControlConfig>;

  void SetUp() override {
    vehicle_.setState(v1::FLIGHT_STATE_FLYING);
    vehicle_.setPosition(0, 0, 1);
    host_.add(std::make_unique<FollowPath>(vehicle_, link_));
    host_.add(std::make_unique<Controller>(
        vehicle_, link_, [](const ControllerConfig& config, const motion::VehicleModel& model) {
          return makePidAttitudeController(model, config.pid);
        }));
    ASSERT_TRUE(host_.start().ok());
    follow_path_ = host_.find("FOLLOW_PATH");
    controller_ = host_.find("QUADROTOR_PID_MOTION_CONTROL");
  }

  // Advances the fake clock in 10 ms steps (one controller tick each),
  // waiting for the workers to tick, until `total` passed or `behavior` ended;
  // `each` runs after every step.
  void fly(Duration total, const BehaviorExecutionManager* behavior,
           const std::function<void()>& each = nullptr) {
    behaviorlib::testing::flyOnFakeClock(clock_, host_, total, milliseconds(10), behavior, each);
  }

  std::unique_ptr<v1::FollowPathParameters> line(double x) {
    auto p = std::make_unique<v1::FollowPathParameters>();
    auto* point = p->add_path_m();
    point->set_x(x);
    point->set_z(1);
    return p;
  }

  // The next activation's end: its cause, and its message contains `text`.
  void expectFinished(v1::TerminationCause cause, const std::string& text) {
    const auto finished = events_.waitFinished();
    EXPECT_EQ(finished.finished().cause(), cause) << finished.ShortDebugString();
    EXPECT_NE(finished.finished().message().find(text), std::string::npos)
        << finished.finished().message();
  }

  // A status as a controller following `source` publishes it now.
  void followedBy(const std::string& source) {
    v1::MotionControlStatus status;
    stampHeader(clock_.now(), "drone1", 1, status.mutable_header());
    status.set_controller("TEST_CONTROLLER");
    status.set_state(v1::MOTION_CONTROLLER_STATE_TRACKING);
    status.set_reference_source(source);
    ASSERT_TRUE(link_.publishStatus(status).ok());
  }

  FakeClock clock_;
  FakeVehicle vehicle_{clock_};
  FakeMotionLink link_;
  BehaviorHost host_{
      behaviorlib::testing::hostOptions("drone1", "quadrotor_motion_with_pid_control"), clock_};
  behaviorlib::testing::EventCollector events_{host_.events()};
  BehaviorExecutionManager* follow_path_ = nullptr;
  BehaviorExecutionManager* controller_ = nullptr;
};

TEST_F(MotionBehaviorsUnitTest, FollowPathPublishesTrajectoryReferencesAndFailsWithoutAController) {
  auto activated = follow_path_->activateAndWait(line(2.0));
  ASSERT_TRUE(activated.ok()) << activated.status();
  fly(milliseconds(500), follow_path_);
  const auto references = link_.references();
  ASSERT_GE(references.size(), 10u) << "50 Hz of the behavior clock";
  EXPECT_EQ(references.back().source(), activated->activation_id());
  EXPECT_EQ(references.back().mode(), v1::MOTION_REFERENCE_MODE_TRAJECTORY);
  EXPECT_EQ(references.back().horizon_size(), 20);
  EXPECT_GT(references.back().point().position_m().x(), 0.0) << "the reference moves along";
  EXPECT_EQ(follow_path_->state(), v1::BEHAVIOR_STATE_ACTIVE) << "within the grace";
  fly(std::chrono::seconds(2), follow_path_);
  expectFinished(v1::TERMINATION_CAUSE_PROCESS_FAILURE, "no motion controller");
  EXPECT_EQ(vehicle_.followers(), 0);
  EXPECT_EQ(link_.statusFollowers(), 0);
}

// The controller's grace runs from when the status subscription is
// established: a slow subscription (a busy host, the deterministic mode
// ahead of the wall clock) is not taken for a controller that does not follow.
TEST_F(MotionBehaviorsUnitTest, TheControllerGraceWaitsForTheStatusSubscription) {
  link_.setStatusFollowed(false);
  auto activated = follow_path_->activateAndWait(line(2.0));
  ASSERT_TRUE(activated.ok()) << activated.status();
  fly(std::chrono::seconds(3), follow_path_);
  EXPECT_EQ(follow_path_->state(), v1::BEHAVIOR_STATE_ACTIVE)
      << "3 s without a subscription, past the 1 s grace";
  link_.setStatusFollowed(true);
  fly(milliseconds(500), follow_path_);
  EXPECT_EQ(follow_path_->state(), v1::BEHAVIOR_STATE_ACTIVE) << "the grace starts now";
  fly(std::chrono::seconds(2), follow_path_);
  expectFinished(v1::TERMINATION_CAUSE_PROCESS_FAILURE, "no motion controller");
}

TEST_F(MotionBehaviorsUnitTest, FollowPathAchievesItsGoalWhenTheVehicleFollowsTheReference) {
  auto activated = follow_path_->activateAndWait(line(1.0));
  ASSERT_TRUE(activated.ok()) << activated.status();
  // A perfect controller: the vehicle is where the reference was.
  fly(std::chrono::seconds(6), follow_path_, [&] {
    const auto references = link_.references();
    if (references.empty()) return;
    const auto& p = references.back().point().position_m();
    vehicle_.setPosition(p.x(), p.y(), p.z());
    followedBy(activated->activation_id());
  });
  const auto finished = events_.waitFinished();
  EXPECT_EQ(finished.finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED)
      << finished.ShortDebugString();
  EXPECT_NE(finished.finished().message().find("reached the last waypoint (1.00, 0.00, 1.00)"),
            std::string::npos)
      << finished.finished().message();
}

TEST_F(MotionBehaviorsUnitTest, ControllerHoldsWithoutAReferenceFollowsAFreshOneAndReportsIt) {
  ASSERT_TRUE(
      controller_->activateAndWait(std::make_unique<v1::QuadrotorPidMotionControlParameters>())
          .ok());
  EXPECT_EQ(vehicle_.leaseHolder(), "drone1/QUADROTOR_PID_MOTION_CONTROL");
  fly(milliseconds(200), controller_);
  auto setpoints = vehicle_.setpoints();
  ASSERT_GE(setpoints.size(), 15u) << "100 Hz of the behavior clock";
  const auto& hold = setpoints.back().attitude_thrust();
  EXPECT_NEAR(hold.thrust_ratio(), 1.5 * 9.81 / 48.0, 0.03) << "hover thrust where it is";
  EXPECT_NEAR(hold.orientation().w(), 1.0, 1e-3) << "level";
  ASSERT_FALSE(link_.statuses().empty());
  EXPECT_EQ(link_.statuses().back().state(), v1::MOTION_CONTROLLER_STATE_HOLDING);

  // A fresh reference 1 m east: followed, and the status names its source.
  fly(milliseconds(200), controller_, [&] {
    v1::MotionReference reference = toProto(holdAt({1, 0, 1}, 0.0));
    stampHeader(clock_.now(), "drone1", 1, reference.mutable_header());
    reference.set_source("TEST-1");
    ASSERT_TRUE(link_.publishReference(reference).ok());
  });
  const auto statuses = link_.statuses();
  EXPECT_EQ(statuses.back().state(), v1::MOTION_CONTROLLER_STATE_TRACKING);
  EXPECT_EQ(statuses.back().reference_source(), "TEST-1");
  EXPECT_NEAR(statuses.back().position_error_m(), 1.0, 1e-6);
  setpoints = vehicle_.setpoints();
  EXPECT_GT(setpoints.back().attitude_thrust().orientation().y(), 0.01)
      << "pitched forward to accelerate east: " << setpoints.back().ShortDebugString();

  // The pose estimate freezes: PROCESS_FAILURE, the lease released, a last
  // STOPPED status.
  vehicle_.freezeEstimate(true);
  fly(std::chrono::seconds(1), controller_);
  const auto finished = events_.waitFinished();
  EXPECT_EQ(finished.finished().cause(), v1::TERMINATION_CAUSE_PROCESS_FAILURE)
      << finished.ShortDebugString();
  EXPECT_NE(finished.finished().message().find("pose estimate"), std::string::npos)
      << finished.finished().message();
  EXPECT_EQ(vehicle_.commands().back(), "RELEASE");
  EXPECT_EQ(link_.statuses().back().state(), v1::MOTION_CONTROLLER_STATE_STOPPED);
  EXPECT_EQ(link_.referenceFollowers(), 0);
}

TEST_F(MotionBehaviorsUnitTest, ControllerIsRefusedWhileAnotherCommanderHoldsTheLease) {
  auto other = vehicle_.acquireLease("drone1/OTHER", std::chrono::seconds(1), false);
  ASSERT_TRUE(other.ok());
  auto refused =
      controller_->activateAndWait(std::make_unique<v1::QuadrotorPidMotionControlParameters>());
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_NE(refused.status().message().find("drone1/OTHER"), std::string::npos) << refused.status();
  EXPECT_TRUE(vehicle_.setpoints().empty());
}

TEST_F(MotionBehaviorsUnitTest, ControllerThatLosesTheLeaseEndsWithProcessFailure) {
  ASSERT_TRUE(
      controller_->activateAndWait(std::make_unique<v1::QuadrotorPidMotionControlParameters>())
          .ok());
  fly(milliseconds(100), controller_);
  vehicle_.loseLease();
  fly(milliseconds(200), controller_);
  const auto finished = events_.waitFinished();
  EXPECT_EQ(finished.finished().cause(), v1::TERMINATION_CAUSE_PROCESS_FAILURE)
      << finished.ShortDebugString();
  EXPECT_NE(finished.finished().message().find("lease"), std::string::npos)
      << finished.finished().message();
}

TEST_F(MotionBehaviorsUnitTest, ControllerWhoseOutputIsNotFiniteEndsWithProcessFailure) {
  ASSERT_TRUE(
      controller_->activateAndWait(std::make_unique<v1::QuadrotorPidMotionControlParameters>())
          .ok());
  fly(milliseconds(100), controller_);
  const size_t sent = vehicle_.setpoints().size();
  ASSERT_GE(sent, 5u);
  // The estimate turns NaN (a diverged estimator): the PID's output is not
  // finite; nothing more is sent and the controller ends.
  vehicle_.setPosition(NAN, 0, 1);
  fly(milliseconds(200), controller_);
  const auto finished = events_.waitFinished();
  EXPECT_EQ(finished.finished().cause(), v1::TERMINATION_CAUSE_PROCESS_FAILURE)
      << finished.ShortDebugString();
  EXPECT_NE(finished.finished().message().find("output is not finite"), std::string::npos)
      << finished.finished().message();
  EXPECT_NE(finished.finished().message().find("no setpoint sent"), std::string::npos)
      << finished.finished().message();
  EXPECT_EQ(vehicle_.setpoints().size(), sent) << "no setpoint after the NaN";
  for (const auto& setpoint : vehicle_.setpoints()) {
    EXPECT_TRUE(std::isfinite(setpoint.attitude_thrust().thrust_ratio()));
  }
  EXPECT_EQ(vehicle_.commands().back(), "RELEASE");
}

TEST_F(MotionBehaviorsUnitTest, ControllerSaturatedLongerThanTheTimeoutEndsWithProcessFailure) {
  ASSERT_TRUE(
      controller_->activateAndWait(std::make_unique<v1::QuadrotorPidMotionControlParameters>())
          .ok());
  // A fresh reference 50 m east that the (fake) vehicle never approaches:
  // the PID asks for more than its tilt limit every step.
  auto far_reference = [&] {
    v1::MotionReference reference = toProto(holdAt({50, 0, 1}, 0.0));
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

// The lean (pitch, rad) of the simulated airframe (1.5 kg, body drag
// 0.25 v + 0.04 v^2 N) holding still in a wind of `wind_m_s`.
double leanInWind(double wind_m_s) {
  return std::asin((0.25 * wind_m_s + 0.04 * wind_m_s * wind_m_s) / (1.5 * 9.81));
}

TEST_F(MotionBehaviorsUnitTest, PerformanceFallsInTheWindTheVehicleLeansAgainst) {
  auto calm = follow_path_->checkSituationAndWait();
  ASSERT_TRUE(calm.ok());
  EXPECT_DOUBLE_EQ(calm->performance_ratio(), 1.0) << calm->ShortDebugString();
  ASSERT_TRUE(
      controller_->activateAndWait(std::make_unique<v1::QuadrotorPidMotionControlParameters>())
          .ok());
  fly(milliseconds(200), controller_);
  calm = controller_->checkSituationAndWait();
  ASSERT_TRUE(calm.ok());
  EXPECT_DOUBLE_EQ(calm->performance_ratio(), 1.0) << calm->ShortDebugString();

  // Leaning against 6 m/s of wind (6.1 m/s horizontal): performance
  // 1 - 0.8 (6.1 - 2) / (10 - 2) = 0.59, for the active controller (every
  // tick) and for FOLLOW_PATH before its activation (the latest estimate).
  vehicle_.setTilt(leanInWind(6.0), 0.0);
  fly(std::chrono::seconds(3), controller_);
  auto windy = controller_->checkSituationAndWait();
  ASSERT_TRUE(windy.ok());
  EXPECT_TRUE(windy->feasible());
  EXPECT_NEAR(windy->performance_ratio(), 0.59, 0.03) << windy->ShortDebugString();
  ASSERT_EQ(windy->reasons_size(), 1);
  EXPECT_NE(windy->reasons(0).find("wind"), std::string::npos) << windy->reasons(0);
  windy = follow_path_->checkSituationAndWait();
  ASSERT_TRUE(windy.ok());
  EXPECT_TRUE(windy->feasible());
  EXPECT_NEAR(windy->performance_ratio(), 0.59, 0.03) << windy->ShortDebugString();
  EXPECT_EQ(controller_->state(), v1::BEHAVIOR_STATE_ACTIVE);
  // A performance change of 0.1 or more is an event.
  bool reported = false;
  for (const auto& e : events_.events()) {
    if (e.has_situation_changed() && e.situation_changed().performance_ratio() < 0.75) {
      reported = true;
    }
  }
  EXPECT_TRUE(reported) << "a situation_changed event";
  ASSERT_TRUE(controller_->deactivateAndWait().ok());
}

}  // namespace
}  // namespace behaviorlib::motion_behaviors
