// The estimation cores of ESTIMATE_POSITION_WITH_SENSOR and
// ESTIMATE_POSITION_WITH_LINEAR_SPEED on synthetic samples (fixed seeds).

#include "behaviorlib/basic_quadrotor_behaviors/position_estimators.h"

#include <gtest/gtest.h>

#include <cmath>
#include <random>

namespace behaviorlib::basic {
namespace {

constexpr double kImuDt = 0.005;  // 200 Hz
constexpr int kImuPerFix = 20;    // 10 Hz fixes
constexpr int kImuPerBaro = 8;    // 25 Hz altitudes

// Flies a synthetic trajectory p(t) through the filter with the simulator's
// default noise: fix 0.5 m / 1 m, barometer 0.1 m plus `baro_offset_m`.
struct Flight {
  SensorPositionFilter filter;
  std::mt19937_64 rng{42};
  std::normal_distribution<double> unit{0.0, 1.0};

  template <class Position, class Acceleration>
  void run(double seconds, Position position, Acceleration acceleration, double baro_offset_m,
           double* rms_after_5s) {
    double sum = 0.0;
    int n = 0;
    for (int k = 0; k * kImuDt < seconds; ++k) {
      const double t = k * kImuDt;
      if (k % kImuPerFix == 0) {
        const Eigen::Vector3d noise(0.5 * unit(rng), 0.5 * unit(rng), 1.0 * unit(rng));
        const Eigen::Vector3d fix = position(t) + noise;
        filter.updateFix(fix, 0.5, 1.0, t, t, 5.0);
      }
      if (k % kImuPerBaro == 0) {
        filter.updateAltitude(position(t).z() + baro_offset_m + 0.1 * unit(rng), 0.1, 5.0);
      }
      const Eigen::Vector3d force =
          acceleration(t) + Eigen::Vector3d(0, 0, kGravityM_S2) +
          Eigen::Vector3d(0.05 * unit(rng), 0.05 * unit(rng), 0.05 * unit(rng));
      filter.predict(Eigen::Quaterniond::Identity(), force, kImuDt);
      if (t > 5.0) {
        sum += (filter.position() - position(t + kImuDt)).squaredNorm();
        ++n;
      }
    }
    *rms_after_5s = std::sqrt(sum / n);
  }
};

TEST(SensorPositionFilter, StartsAtTheFirstFixAndConvergesOnAStillVehicle) {
  Flight flight;
  EXPECT_FALSE(flight.filter.initialized());
  double rms = 0.0;
  const Eigen::Vector3d at(3, -2, 1.5);
  flight.run(
      30.0, [&](double) { return at; }, [](double) { return Eigen::Vector3d::Zero(); }, 0.0, &rms);
  EXPECT_TRUE(flight.filter.initialized());
  EXPECT_LT(rms, 0.2);
  EXPECT_LT(flight.filter.velocity().norm(), 0.1);
  EXPECT_TRUE(flight.filter.finite());
}

TEST(SensorPositionFilter, FollowsAnAcceleratingVehicleAndLearnsTheBarometerOffset) {
  Flight flight;
  double rms = 0.0;
  // A circle of radius 3 m at 1.5 m/s, climbing 0.1 m/s.
  const double w = 0.5;
  auto position = [&](double t) {
    return Eigen::Vector3d(3 * std::cos(w * t), 3 * std::sin(w * t), 1 + 0.1 * t);
  };
  auto acceleration = [&](double t) {
    return Eigen::Vector3d(-3 * w * w * std::cos(w * t), -3 * w * w * std::sin(w * t), 0);
  };
  flight.run(60.0, position, acceleration, 0.4, &rms);
  EXPECT_LT(rms, 0.3);
  EXPECT_NEAR(flight.filter.position().z(), position(60.0).z(), 0.2)
      << "the barometer's 0.4 m offset is not taken for height";
  EXPECT_LT((flight.filter.velocity() -
             Eigen::Vector3d(-1.5 * std::sin(w * 60), 1.5 * std::cos(w * 60), 0.1))
                .norm(),
            0.3);
}

TEST(SensorPositionFilter, AFixBeyondTheGateIsRejectedAndChangesNothing) {
  SensorPositionFilter filter;
  filter.updateFix({1, 2, 3}, 0.5, 1.0, 0.0, 0.0, 5.0);
  const Eigen::Vector3d before = filter.position();
  const auto far = filter.updateFix({41, 2, 3}, 0.5, 1.0, 0.1, 0.1, 5.0);
  EXPECT_FALSE(far.accepted);
  EXPECT_NEAR(far.innovation_m, 40.0, 1e-9);
  EXPECT_EQ(filter.position(), before);
  const auto altitude = filter.updateAltitude(100.0, 0.1, 5.0);
  EXPECT_FALSE(altitude.accepted);
  EXPECT_EQ(filter.position(), before);
  const auto near = filter.updateFix({1.2, 2, 3}, 0.5, 1.0, 0.2, 0.2, 5.0);
  EXPECT_TRUE(near.accepted);
  EXPECT_FALSE(filter.updateFix({NAN, 0, 0}, 0.5, 1.0, 0.3, 0.3, 5.0).accepted);
}

TEST(LinearSpeedDeadReckoning, IntegratesTheBodySpeedRotatedByTheOrientation) {
  LinearSpeedDeadReckoning reckoning({1, 1, 2}, 10.0);
  // Yawed 90 degrees: body forward is world north.
  const Eigen::Quaterniond yaw90(Eigen::AngleAxisd(M_PI / 2, Eigen::Vector3d::UnitZ()));
  for (int k = 1; k <= 30; ++k) {
    EXPECT_TRUE(reckoning.add(10.0 + k / 30.0, {1.0, 0.0, 0.0}, yaw90, 0.5));
  }
  // The first sample counts from the start time at its own speed.
  EXPECT_NEAR(reckoning.position().x(), 1.0, 1e-9);
  EXPECT_NEAR(reckoning.position().y(), 2.0, 1e-9);
  EXPECT_NEAR(reckoning.position().z(), 2.0, 1e-9);
  EXPECT_NEAR(reckoning.distanceM(), 1.0, 1e-9);
  EXPECT_NEAR(reckoning.velocity().y(), 1.0, 1e-9);
  // Older or repeated stamps are ignored; a gap counts at most max_gap_s.
  EXPECT_FALSE(reckoning.add(10.5, {5, 0, 0}, yaw90, 0.5));
  EXPECT_TRUE(reckoning.add(21.0, {1.0, 0.0, 0.0}, yaw90, 0.5));
  EXPECT_NEAR(reckoning.position().y(), 2.5, 1e-9);
  EXPECT_DOUBLE_EQ(reckoning.lastTimeS(), 21.0);
}

TEST(FrozenDetector, TellsARepeatedValueFromANoisyOne) {
  FrozenDetector frozen;
  EXPECT_EQ(frozen.frozenForS(), 0.0);
  frozen.add(1.0, Eigen::Vector2d(0.1, 0.2));
  frozen.add(1.1, Eigen::Vector2d(0.1, 0.2000001));
  EXPECT_EQ(frozen.frozenForS(), 0.0);
  frozen.add(1.2, Eigen::Vector2d(0.1, 0.2000001));
  frozen.add(1.7, Eigen::Vector2d(0.1, 0.2000001));
  EXPECT_NEAR(frozen.frozenForS(), 0.6, 1e-12);
  frozen.add(1.8, Eigen::Vector2d(0.3, 0.2));
  EXPECT_EQ(frozen.frozenForS(), 0.0);
}

}  // namespace
}  // namespace behaviorlib::basic
