#include <gtest/gtest.h>

#include <cmath>
#include <numbers>

#include "behaviorlib/motion_control/mpc_controller.h"
#include "behaviorlib/motion_control/path_tracker.h"
#include "behaviorlib/motion_control/pid_controller.h"
#include "unit/motion_control/closed_loop.h"

namespace behaviorlib::motion {
namespace {

using testing::ClosedLoop;
using testing::modelOf;
using testing::rms;
using testing::square;

ClosedLoop::Controller pidController(PidMotionController& pid) {
  return [&pid](const StateEstimate& s, const MotionReference& r, double dt) {
    return pid.update(s, r, dt);
  };
}

ClosedLoop::Controller mpcController(MpcMotionController& mpc) {
  return [&mpc](const StateEstimate& s, const MotionReference& r, double dt) {
    return mpc.update(s, r, dt);
  };
}

MotionReference holdAt(const Eigen::Vector3d& p, double yaw = 0.0) {
  MotionReference r;
  r.point.position_m = p;
  r.point.yaw_rad = yaw;
  return r;
}

TEST(AccelerationToAttitude, ZeroAccelerationIsLevelHoverThrust) {
  VehicleModel model;
  bool saturated = true;
  const AttitudeThrustCommand c =
      accelerationToAttitude(Eigen::Vector3d::Zero(), 0.5, model, &saturated);
  EXPECT_FALSE(saturated);
  EXPECT_NEAR(c.thrust_ratio, model.hoverThrustRatio(), 1e-9);
  const Eigen::Vector3d z = c.orientation * Eigen::Vector3d::UnitZ();
  EXPECT_NEAR(z.z(), 1.0, 1e-9);
  const Eigen::Vector3d x = c.orientation * Eigen::Vector3d::UnitX();
  EXPECT_NEAR(std::atan2(x.y(), x.x()), 0.5, 1e-9);
}

TEST(AccelerationToAttitude, TiltIsLimited) {
  VehicleModel model;
  bool saturated = false;
  const AttitudeThrustCommand c = accelerationToAttitude({50.0, 0.0, 0.0}, 0.0, model, &saturated);
  EXPECT_TRUE(saturated);
  const Eigen::Vector3d z = c.orientation * Eigen::Vector3d::UnitZ();
  EXPECT_NEAR(std::acos(z.z()), model.max_tilt_rad, 1e-6);
  EXPECT_GT(z.x(), 0.0);  // tilted towards +x to accelerate east
}

TEST(PidMotionController, ReachesAPositionAndYaw) {
  ClosedLoop loop({0, 0, 1});
  PidMotionController pid(modelOf(loop.params()), PidGains{});
  const MotionReference target = holdAt({1.0, 2.0, 2.0}, 1.0);
  for (int i = 0; i < 2000; ++i) loop.step(pidController(pid), target);  // 20 s
  EXPECT_LT((loop.estimate().position_m - Eigen::Vector3d(1, 2, 2)).norm(), 0.05);
  EXPECT_LT(loop.estimate().velocity_m_s.norm(), 0.05);
  EXPECT_NEAR(loop.estimate().yawRad(), 1.0, 0.03);
}

TEST(PidMotionController, HoldsPositionInSteadyWind) {
  ClosedLoop loop({0, 0, 2}, {3.0, 0.0, 0.0});
  PidMotionController pid(modelOf(loop.params()), PidGains{});
  const MotionReference target = holdAt({0, 0, 2});
  for (int i = 0; i < 2000; ++i) loop.step(pidController(pid), target);  // 20 s: integrators settle
  EXPECT_LT((loop.estimate().position_m - Eigen::Vector3d(0, 0, 2)).norm(), 0.05);
}

TEST(PidMotionController, TracksAVelocity) {
  ClosedLoop loop({0, 0, 1});
  PidMotionController pid(modelOf(loop.params()), PidGains{});
  MotionReference r;
  r.mode = MotionReference::Mode::kVelocity;
  r.point.velocity_m_s = {1.0, -0.5, 0.0};
  for (int i = 0; i < 500; ++i) loop.step(pidController(pid), r);
  EXPECT_LT((loop.estimate().velocity_m_s - Eigen::Vector3d(1.0, -0.5, 0.0)).norm(), 0.05);
  EXPECT_NEAR(loop.estimate().position_m.z(), 1.0, 0.1);
}

TEST(PidMotionController, FollowsTheSquareWithinTheTrackingBound) {
  ClosedLoop loop({0, 0, 1});
  PidMotionController pid(modelOf(loop.params()), PidGains{});
  auto tracker = PathTracker::create(square(), PathTrackerParams{});
  ASSERT_TRUE(tracker.ok());
  const std::vector<double> errors = loop.followPath(*tracker, pidController(pid), 60.0);
  EXPECT_TRUE(tracker->referenceAtEnd());
  EXPECT_LT(rms(errors), 0.15);
  EXPECT_LT((loop.estimate().position_m - Eigen::Vector3d(0, 0, 1)).norm(), 0.1);
}

TEST(PidMotionController, NonFiniteInputGivesHoverThrustAndSaysSo) {
  PidMotionController pid(VehicleModel{}, PidGains{});
  StateEstimate state;
  state.position_m.x() = std::nan("");
  ControllerDiagnostics diag;
  const AttitudeThrustCommand c = pid.update(state, holdAt({0, 0, 1}), 0.01, &diag);
  EXPECT_FALSE(diag.finite);
  EXPECT_NEAR(c.thrust_ratio, VehicleModel{}.hoverThrustRatio(), 1e-9);
}

TEST(AttitudeToBodyRates, PointsTowardsTheDesiredAttitude) {
  const Eigen::Quaterniond level = Eigen::Quaterniond::Identity();
  const Eigen::Quaterniond rolled(Eigen::AngleAxisd(0.2, Eigen::Vector3d::UnitX()));
  const Eigen::Vector3d rates = attitudeToBodyRates(level, rolled);
  EXPECT_GT(rates.x(), 0.0);
  EXPECT_NEAR(rates.y(), 0.0, 1e-9);
  EXPECT_NEAR(attitudeToBodyRates(rolled, rolled).norm(), 0.0, 1e-9);
}

TEST(MpcMotionController, ReachesAPositionWithinItsInputLimits) {
  ClosedLoop loop({0, 0, 1});
  MpcMotionController mpc(modelOf(loop.params()));
  const auto [lower, upper] = mpc.inputBounds();
  const MotionReference target = holdAt({6.0, -3.0, 3.0});
  bool hit_bound = false;
  for (int i = 0; i < 1000; ++i) {
    ControllerDiagnostics diag;
    const StateEstimate s = loop.estimate();
    const AttitudeThrustCommand c = mpc.update(s, target, 0.01, &diag);
    ASSERT_TRUE(diag.finite);
    for (int a = 0; a < 3; ++a) {
      EXPECT_GE(diag.acceleration_command_m_s2[a], lower[a] - 1e-9);
      EXPECT_LE(diag.acceleration_command_m_s2[a], upper[a] + 1e-9);
      hit_bound = hit_bound || mpc.lastSolve().at_bound[a];
    }
    loop.step([&](const StateEstimate&, const MotionReference&, double) { return c; }, target);
  }
  EXPECT_TRUE(hit_bound);  // a 7 m step needs the limits: the constraints were active
  EXPECT_LT((loop.estimate().position_m - Eigen::Vector3d(6, -3, 3)).norm(), 0.05);
}

TEST(MpcMotionController, FollowsTheSquareWithinTheTrackingBound) {
  ClosedLoop loop({0, 0, 1});
  MpcMotionController mpc(modelOf(loop.params()));
  auto tracker = PathTracker::create(square(), PathTrackerParams{});
  ASSERT_TRUE(tracker.ok());
  const std::vector<double> errors = loop.followPath(*tracker, mpcController(mpc), 60.0);
  EXPECT_TRUE(tracker->referenceAtEnd());
  EXPECT_LT(rms(errors), 0.15);
}

TEST(MpcMotionController, EstimatesTheWindAndHoldsPosition) {
  ClosedLoop loop({0, 0, 2}, {3.0, 0.0, 0.0});
  MpcMotionController mpc(modelOf(loop.params()));
  const MotionReference target = holdAt({0, 0, 2});
  for (int i = 0; i < 2000; ++i) loop.step(mpcController(mpc), target);
  EXPECT_LT((loop.estimate().position_m - Eigen::Vector3d(0, 0, 2)).norm(), 0.05);
  EXPECT_GT(mpc.disturbance().x(), 0.1);  // the wind pushes east
}

TEST(MpcMotionController, TheSolverConvergesOnASmoothReference) {
  MpcMotionController mpc(VehicleModel{});
  StateEstimate s;
  s.position_m = {0, 0, 1};
  mpc.update(s, holdAt({0.2, 0, 1}), 0.01);
  EXPECT_TRUE(mpc.lastSolve().converged);
  EXPECT_LE(mpc.lastSolve().iterations, mpc.params().max_iterations);
  // The plan ends near the target.
  const Eigen::MatrixXd predicted = mpc.predictedPositions();
  EXPECT_NEAR(predicted(predicted.rows() - 1, 0), 0.2, 0.05);
}

TEST(PathTracker, TimesTheProfileAndStopsAtTheEnd) {
  PathTrackerParams params;  // 1 m/s, 1 m/s^2
  auto tracker = PathTracker::create({{4, 0, 1}}, params);
  ASSERT_TRUE(tracker.ok());
  tracker->start({0, 0, 1}, 0.0);
  EXPECT_DOUBLE_EQ(tracker->lengthM(), 4.0);
  EXPECT_NEAR(tracker->totalTimeS(), 5.0, 1e-9);  // 1 s up, 3 s cruise, 1 s down
  EXPECT_NEAR(tracker->sample(0.5).velocity_m_s.x(), 0.5, 1e-9);
  EXPECT_NEAR(tracker->sample(2.5).position_m.x(), 2.0, 1e-9);
  EXPECT_NEAR(tracker->sample(100).position_m.x(), 4.0, 1e-9);
  EXPECT_NEAR(tracker->sample(100).velocity_m_s.norm(), 0.0, 1e-9);
}

// At its end the reference is at rest: no velocity and no acceleration
// feed-forward, whatever rounding the segments' times got. (The braking
// acceleration used to stay on when the time reached the end a hair inside the
// last segment: depending on where the path started, a vehicle held at the
// last waypoint was pushed back by 1 m/s^2 of feed-forward, and the demo's
// FOLLOW_PATH took 4 s longer in about one flight in five.)
TEST(PathTracker, AtTheEndTheReferenceIsAtRest) {
  int checked = 0;
  for (int i = 0; i < 200; ++i) {
    auto tracker = PathTracker::create({{4, 0, 1.5}, {4, 4, 1.5}, {0, 4, 1.5}, {0, 0, 1.5}},
                                       PathTrackerParams{});
    ASSERT_TRUE(tracker.ok());
    // Where the vehicle happened to be when the path began.
    tracker->start({-0.013 + 1e-4 * i, 0.0021 * (i % 7), 1.49 + 1e-5 * i}, 0.0);
    const double end = tracker->totalTimeS();
    for (const double t : {end, end + 0.01, end + 100.0}) {
      const ReferencePoint p = tracker->sample(t);
      EXPECT_EQ(p.acceleration_m_s2.norm(), 0.0) << "start " << i << ", t " << t;
      EXPECT_EQ(p.velocity_m_s.norm(), 0.0) << "start " << i << ", t " << t;
      EXPECT_NEAR((p.position_m - Eigen::Vector3d(0, 0, 1.5)).norm(), 0.0, 1e-9);
    }
    // Followed tick by tick past the end, as FOLLOW_PATH does.
    MotionReference reference;
    for (int k = 0; k < 3000 && !tracker->referenceAtEnd(); ++k) {
      reference = tracker->update(tracker->sample(tracker->timeS()).position_m, 0.01);
    }
    ASSERT_TRUE(tracker->referenceAtEnd());
    reference = tracker->update(Eigen::Vector3d(0, 0, 1.5), 0.01);
    EXPECT_EQ(reference.point.acceleration_m_s2.norm(), 0.0) << "start " << i;
    for (const ReferencePoint& h : reference.horizon) {
      EXPECT_EQ(h.acceleration_m_s2.norm(), 0.0) << "start " << i;
    }
    ++checked;
  }
  EXPECT_EQ(checked, 200);
}

TEST(PathTracker, TheReferenceWaitsForALaggingVehicle) {
  auto tracker = PathTracker::create({{10, 0, 1}}, PathTrackerParams{});
  ASSERT_TRUE(tracker.ok());
  tracker->start({0, 0, 1}, 0.0);
  const Eigen::Vector3d stuck(0, 0, 1);  // the vehicle does not move
  for (int i = 0; i < 1000; ++i) tracker->update(stuck, 0.01);
  EXPECT_LE(tracker->lagM(stuck), PathTrackerParams{}.max_lag_m + 1e-6);
  EXPECT_FALSE(tracker->referenceAtEnd());
  EXPECT_GT(tracker->remainingM(), 9.0);
}

TEST(PathTracker, RefusesBadPathsNamingThePoint) {
  EXPECT_EQ(PathTracker::create({}, {}).status().code(), absl::StatusCode::kInvalidArgument);
  auto nan = PathTracker::create({{0, 0, 1}, {1, std::nan(""), 1}}, {});
  EXPECT_NE(std::string(nan.status().message()).find("point 1"), std::string::npos);
  PathTrackerParams short_paths;
  short_paths.max_length_m = 5.0;
  auto too_long = PathTracker::create({{0, 0, 1}, {10, 0, 1}}, short_paths);
  EXPECT_NE(std::string(too_long.status().message()).find("exceeds the maximum"),
            std::string::npos);
  PathTrackerParams fast;
  fast.speed_m_s = 0.0;
  EXPECT_NE(
      std::string(PathTracker::create({{1, 0, 1}}, fast).status().message()).find("speed_m_s"),
      std::string::npos);
}

}  // namespace
// A path changed in flight (FOLLOW_PATH's Modify) continues from the
// reference of the old one: the position does not jump, and along the same
// direction the speed does not drop; across it, the crossing part is dropped.
TEST(PathTracker, APathChangedInFlightContinuesWithoutAJumpOrAStop) {
  PathTrackerParams params;  // 1 m/s, 1 m/s^2
  auto old_path = PathTracker::create({{10, 0, 1}}, params);
  ASSERT_TRUE(old_path.ok());
  old_path->start({0, 0, 1}, 0.0);
  for (int k = 0; k < 300; ++k) old_path->update(old_path->current().position_m, 0.01);
  const ReferencePoint before = old_path->current();  // 3 s in: cruising at 1 m/s
  ASSERT_NEAR(before.velocity_m_s.x(), 1.0, 1e-9);

  // Further along the same line, then aside: entered at full speed.
  auto ahead = PathTracker::create({{8, 0, 1}, {8, 3, 1}}, params);
  ASSERT_TRUE(ahead.ok());
  ahead->continueFrom(before, 0.0);
  const ReferencePoint first = ahead->current();
  EXPECT_NEAR((first.position_m - before.position_m).norm(), 0.0, 1e-12);
  EXPECT_NEAR((first.velocity_m_s - before.velocity_m_s).norm(), 0.0, 1e-9);
  // Followed tick by tick: each step at most what the speed covers, never at
  // rest before the first waypoint.
  Eigen::Vector3d last = first.position_m;
  double slowest = 1e9;
  for (int k = 0; k < 2000 && !ahead->referenceAtEnd(); ++k) {
    const MotionReference r = ahead->update(ahead->current().position_m, 0.01);
    EXPECT_LE((r.point.position_m - last).norm(), 1.0 * 0.01 + 1e-9) << "at step " << k;
    last = r.point.position_m;
    if (r.point.position_m.x() < 7.0) slowest = std::min(slowest, r.point.velocity_m_s.norm());
  }
  EXPECT_GT(slowest, 0.99) << "it slowed down before it had to";
  EXPECT_TRUE(ahead->referenceAtEnd());
  EXPECT_NEAR((ahead->current().position_m - Eigen::Vector3d(8, 3, 1)).norm(), 0.0, 1e-9);

  // Straight across: the crossing velocity is dropped, the position kept.
  auto across = PathTracker::create({{before.position_m.x(), 4, 1}}, params);
  ASSERT_TRUE(across.ok());
  across->continueFrom(before, 0.0);
  EXPECT_NEAR((across->current().position_m - before.position_m).norm(), 0.0, 1e-12);
  EXPECT_NEAR(across->current().velocity_m_s.norm(), 0.0, 1e-9);

  // Back towards where it came from at speed: 0 along the new segment too.
  auto back = PathTracker::create({{0, 0, 1}}, params);
  ASSERT_TRUE(back.ok());
  back->continueFrom(before, 0.0);
  EXPECT_NEAR(back->current().velocity_m_s.norm(), 0.0, 1e-9);
}

// Entered at a speed it cannot stop from within its first segment at the
// acceleration, the reference brakes harder and still stops on the waypoint.
TEST(PathTracker, AShortFirstSegmentAtSpeedBrakesHarderAndStopsOnTheWaypoint) {
  PathTrackerParams params;  // 1 m/s, 1 m/s^2: 0.5 m to stop
  ReferencePoint from;
  from.position_m = {0, 0, 1};
  from.velocity_m_s = {1, 0, 0};
  auto tracker = PathTracker::create({{0.2, 0, 1}}, params);
  ASSERT_TRUE(tracker.ok());
  tracker->continueFrom(from, 0.0);
  EXPECT_NEAR(tracker->totalTimeS(), 0.4, 1e-9);  // 2 L / u
  EXPECT_NEAR(tracker->sample(0.2).position_m.x(), 0.15, 1e-9);
  EXPECT_NEAR(tracker->sample(0.2).acceleration_m_s2.x(), -2.5, 1e-9);  // u^2 / 2L
  EXPECT_NEAR(tracker->sample(0.4).position_m.x(), 0.2, 1e-9);
  EXPECT_NEAR(tracker->sample(0.4).velocity_m_s.norm(), 0.0, 1e-9);
}

}  // namespace behaviorlib::motion
