// motion::WindEstimator on made-up inputs: attitudes that balance the
// simulator's drag model (body-axis linear + quadratic drag, thrust along
// body z) in a known wind, stamped by hand; then flown in closed loop
// against the simulator's dynamics (PID hovering in wind, the square in calm
// air). And windPerformance()'s mapping.

#include "behaviorlib/motion_control/wind_estimator.h"

#include <gtest/gtest.h>

#include <cmath>
#include <numbers>

#include "behaviorlib/motion_control/path_tracker.h"
#include "behaviorlib/motion_control/pid_controller.h"
#include "unit/motion_control/closed_loop.h"

namespace behaviorlib::motion {
namespace {

using testing::ClosedLoop;
using testing::modelOf;

constexpr double kMass = 1.5, kG = 9.81, kC1 = 0.25, kC2 = 0.04;

Eigen::Vector3d bodyDrag(const Eigen::Vector3d& air_body) {
  return -(kC1 * air_body + kC2 * air_body.cwiseAbs().cwiseProduct(air_body));
}

// The attitude (with `yaw`) whose thrust, along body z, holds the vehicle at
// acceleration `a` while it moves at `velocity` through `wind`: the
// simulator's drag model, solved by fixed-point iteration.
Eigen::Quaterniond balancing(const Eigen::Vector3d& velocity, const Eigen::Vector3d& wind,
                             const Eigen::Vector3d& a, double yaw) {
  const Eigen::Quaterniond heading(Eigen::AngleAxisd(yaw, Eigen::Vector3d::UnitZ()));
  Eigen::Quaterniond q = heading;
  for (int i = 0; i < 100; ++i) {
    const Eigen::Matrix3d r = q.toRotationMatrix();
    const Eigen::Vector3d drag = r * bodyDrag(r.transpose() * (velocity - wind));
    // m a = T z_b + drag - m g z  ->  z_b along m (a + g z) - drag.
    const Eigen::Vector3d z_b = (kMass * (a + Eigen::Vector3d(0, 0, kG)) - drag).normalized();
    // The tilt that takes heading's z to z_b.
    q = Eigen::Quaterniond::FromTwoVectors(Eigen::Vector3d::UnitZ(), z_b) * heading;
  }
  return q;
}

TEST(WindEstimator, AirSpeedForDragInvertsTheDragModel) {
  for (double v : {-12.0, -3.0, -0.5, 0.0, 0.7, 5.0, 20.0}) {
    const double drag = -(kC1 * v + kC2 * std::abs(v) * v);
    EXPECT_NEAR(WindEstimator::airSpeedForDrag(drag, kC1, kC2), v, 1e-9) << v;
  }
  EXPECT_NEAR(WindEstimator::airSpeedForDrag(-1.0, 0.5, 0.0), 2.0, 1e-12) << "linear only";
}

TEST(WindEstimator, AVehicleHoldingStillInSteadyWindReadsThatWind) {
  struct Case {
    Eigen::Vector3d wind;
    double yaw;
  };
  for (const Case& c : {Case{{6, 0, 0}, 0.0}, Case{{0, -4, 0}, 1.0}, Case{{3, 3, 0}, -2.5},
                        Case{{-9, 2, 0}, 0.3}}) {
    WindEstimator estimator;
    const Eigen::Quaterniond q =
        balancing(Eigen::Vector3d::Zero(), c.wind, Eigen::Vector3d::Zero(), c.yaw);
    // A single sample already reads it (steady flight assumed)...
    estimator.add(100.0, q, Eigen::Vector3d::Zero());
    EXPECT_NEAR((estimator.windMS() - c.wind.head<2>()).norm(), 0.0, 1e-6) << c.wind.transpose();
    // ... and 3 s of them at 50 Hz keep it.
    for (int i = 1; i <= 150; ++i) estimator.add(100.0 + i * 0.02, q, Eigen::Vector3d::Zero());
    EXPECT_NEAR((estimator.windMS() - c.wind.head<2>()).norm(), 0.0, 1e-6) << c.wind.transpose();
    EXPECT_NEAR(estimator.speedMS(), c.wind.norm(), 1e-6);
  }
}

TEST(WindEstimator, FlyingThroughCalmAirIsNotWindAndFlyingInWindIsTheWind) {
  const Eigen::Vector3d velocity(2.0, -1.0, 0.3);
  for (const Eigen::Vector3d& wind : {Eigen::Vector3d(0, 0, 0), Eigen::Vector3d(-5, 1, 0)}) {
    WindEstimator estimator;
    const Eigen::Quaterniond q = balancing(velocity, wind, Eigen::Vector3d::Zero(), 0.7);
    for (int i = 0; i <= 100; ++i) estimator.add(i * 0.02, q, velocity);
    EXPECT_NEAR((estimator.windMS() - wind.head<2>()).norm(), 0.0, 1e-6) << wind.transpose();
  }
}

TEST(WindEstimator, AccelerationIsNotMistakenForWind) {
  // Calm air, accelerating at 1.5 m/s^2 east for 2 s, then cruising: the
  // lean that accelerates is explained by the velocity's change (from the
  // second sample on: the first one alone looks like a vehicle leaning into
  // wind).
  WindEstimator estimator;
  const Eigen::Vector3d a(1.5, 0, 0);
  double worst = 0.0;
  for (int i = 0; i <= 400; ++i) {
    const double t = i * 0.02;
    const bool accelerating = t < 2.0;
    const Eigen::Vector3d velocity(accelerating ? 1.5 * t : 3.0, 0, 0);
    const Eigen::Quaterniond q = balancing(velocity, Eigen::Vector3d::Zero(),
                                           accelerating ? a : Eigen::Vector3d::Zero(), 0.0);
    estimator.add(t, q, velocity);
    if (i > 0) worst = std::max(worst, estimator.speedMS());
  }
  EXPECT_LT(worst, 0.3) << "the filter's lag on a changing speed";
  EXPECT_LT(estimator.speedMS(), 0.05) << "cruising for 6 s";
}

TEST(WindEstimator, FiltersWithItsTimeConstantRestartsAfterAGapAndIgnoresBadSamples) {
  WindEstimatorParams params;
  params.time_constant_s = 1.0;
  WindEstimator estimator(params);
  EXPECT_FALSE(estimator.hasEstimate());
  EXPECT_EQ(estimator.speedMS(), 0.0);
  const Eigen::Quaterniond level = Eigen::Quaterniond::Identity();
  const Eigen::Quaterniond windy =
      balancing(Eigen::Vector3d::Zero(), {6, 0, 0}, Eigen::Vector3d::Zero(), 0.0);
  for (int i = 0; i <= 50; ++i) estimator.add(i * 0.02, level, Eigen::Vector3d::Zero());
  EXPECT_NEAR(estimator.speedMS(), 0.0, 1e-9);
  // The wind rises at t = 1 s: the estimate follows within a few time
  // constants, not at once.
  for (int i = 1; i <= 10; ++i) estimator.add(1.0 + i * 0.02, windy, Eigen::Vector3d::Zero());
  EXPECT_GT(estimator.speedMS(), 0.5);
  EXPECT_LT(estimator.speedMS(), 3.0) << "0.2 s after the change";
  for (int i = 11; i <= 250; ++i) estimator.add(1.0 + i * 0.02, windy, Eigen::Vector3d::Zero());
  EXPECT_NEAR(estimator.speedMS(), 6.0, 0.05) << "5 s after the change";

  // An older sample, the same stamp again and non-finite samples are ignored.
  const double before = estimator.speedMS();
  estimator.add(2.0, level, Eigen::Vector3d::Zero());
  estimator.add(6.0, level, Eigen::Vector3d::Zero());
  estimator.add(6.01, level, Eigen::Vector3d(NAN, 0, 0));
  estimator.add(NAN, level, Eigen::Vector3d::Zero());
  EXPECT_DOUBLE_EQ(estimator.speedMS(), before);

  // After a gap longer than max_gap_s the estimate restarts from the new
  // sample.
  estimator.add(6.0 + params.max_gap_s + 0.1, level, Eigen::Vector3d::Zero());
  EXPECT_NEAR(estimator.speedMS(), 0.0, 1e-9);
  estimator.reset();
  EXPECT_FALSE(estimator.hasEstimate());
}

TEST(WindPerformance, OneInCalmAirFallingLinearlyToAFloorAtTheMaximum) {
  EXPECT_EQ(windPerformance(0.0, 2.0, 10.0), 1.0);
  EXPECT_EQ(windPerformance(2.0, 2.0, 10.0), 1.0);
  EXPECT_NEAR(windPerformance(4.0, 2.0, 10.0), 0.8, 1e-12);
  EXPECT_NEAR(windPerformance(6.0, 2.0, 10.0), 0.6, 1e-12);
  EXPECT_NEAR(windPerformance(10.0, 2.0, 10.0), 0.2, 1e-12);
  EXPECT_NEAR(windPerformance(25.0, 2.0, 10.0), 0.2, 1e-12);
}

// ---- closed loop against the simulator's dynamics ---------------------------

TEST(WindEstimator, ReadsTheSimulatorsWindWhileThePidHoldsPositionInIt) {
  const Eigen::Vector3d wind(4.0, 3.0, 0.0);  // 5 m/s towards the north-east
  ClosedLoop loop({0, 0, 2}, wind);
  PidMotionController pid(modelOf(loop.params()), PidGains{});
  MotionReference hold;
  hold.point.position_m = {0, 0, 2};
  WindEstimator estimator;
  for (int i = 0; i < 1500; ++i) {  // 15 s at 100 Hz
    loop.step([&](const StateEstimate& s, const MotionReference& r,
                  double dt) { return pid.update(s, r, dt); },
              hold);
    const StateEstimate e = loop.estimate();
    estimator.add((i + 1) * ClosedLoop::kControlDt, e.orientation, e.velocity_m_s);
  }
  std::printf("closed loop, 5 m/s wind: estimated (%.3f, %.3f) m/s\n", estimator.windMS().x(),
              estimator.windMS().y());
  EXPECT_LT((estimator.windMS() - wind.head<2>()).norm(), 0.25);
}

TEST(WindEstimator, StaysNearZeroWhileThePidFliesTheSquareInCalmAir) {
  ClosedLoop loop({0, 0, 1});
  PidMotionController pid(modelOf(loop.params()), PidGains{});
  auto tracker = PathTracker::create(testing::square(), PathTrackerParams{});
  ASSERT_TRUE(tracker.ok());
  tracker->start(loop.estimate().position_m, loop.estimate().yawRad());
  WindEstimator estimator;
  double worst = 0.0;
  for (int i = 0; i < 3000 && !tracker->referenceAtEnd(); ++i) {
    const MotionReference ref = tracker->update(loop.estimate().position_m, ClosedLoop::kControlDt);
    loop.step([&](const StateEstimate& s, const MotionReference& r,
                  double dt) { return pid.update(s, r, dt); },
              ref);
    const StateEstimate e = loop.estimate();
    estimator.add((i + 1) * ClosedLoop::kControlDt, e.orientation, e.velocity_m_s);
    worst = std::max(worst, estimator.speedMS());
  }
  std::printf("closed loop, calm square at 1 m/s: largest wind estimate %.3f m/s\n", worst);
  EXPECT_LT(worst, 1.0) << "well below calm_wind_m_s (2 m/s)";
}

}  // namespace
}  // namespace behaviorlib::motion
