#include "behaviorlib/navigation/scan_thinner.h"

#include <gtest/gtest.h>

namespace behaviorlib::nav {
namespace {

constexpr int64_t kMs = 1'000'000;

TEST(ScanThinner, AMovingSensorIsMappedAtTheMinimumInterval) {
  ScanThinner thinner;  // 0.2 s, 5 cm, 0.05 rad, 1 s still
  const Eigen::Quaterniond level = Eigen::Quaterniond::Identity();
  int taken = 0;
  // A 10 Hz lidar moving at 1 m/s for 2 s: every other scan.
  for (int i = 0; i < 20; ++i) {
    taken += thinner.admit(i * 100 * kMs, Eigen::Vector3d(0.1 * i, 0, 1), level);
  }
  EXPECT_EQ(taken, 10);
}

TEST(ScanThinner, AStillSensorIsMappedOnceASecondAndATurnCounts) {
  ScanThinner thinner;
  const Eigen::Vector3d here(1, 2, 1);
  const Eigen::Quaterniond level = Eigen::Quaterniond::Identity();
  EXPECT_TRUE(thinner.admit(0, here, level));
  EXPECT_FALSE(thinner.admit(300 * kMs, here + Eigen::Vector3d(0.01, 0, 0), level));
  EXPECT_FALSE(thinner.admit(900 * kMs, here, level));
  EXPECT_TRUE(thinner.admit(1000 * kMs, here, level));
  // Turning on the spot by 0.1 rad counts as moving.
  const Eigen::Quaterniond turned(Eigen::AngleAxisd(0.1, Eigen::Vector3d::UnitZ()));
  EXPECT_FALSE(thinner.admit(1100 * kMs, here, turned));  // within the minimum interval
  EXPECT_TRUE(thinner.admit(1200 * kMs, here, turned));
}

TEST(ScanThinner, AResetOrAnEarlierStampTakesTheNextScan) {
  ScanThinner thinner;
  const Eigen::Vector3d here(0, 0, 1);
  const Eigen::Quaterniond level = Eigen::Quaterniond::Identity();
  EXPECT_TRUE(thinner.admit(5000 * kMs, here, level));
  EXPECT_FALSE(thinner.admit(5100 * kMs, here, level));
  thinner.reset();
  EXPECT_TRUE(thinner.admit(5150 * kMs, here, level));
  EXPECT_TRUE(thinner.admit(10 * kMs, here, level));  // the simulation restarted
}

}  // namespace
}  // namespace behaviorlib::nav
