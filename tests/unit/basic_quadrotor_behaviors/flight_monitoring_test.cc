// The clock-driven helpers of the flight behaviors' monitoring, on fake times.

#include "behaviorlib/flight_common/flight_monitoring.h"

#include <gtest/gtest.h>

namespace behaviorlib::flight {
namespace {

using std::chrono::milliseconds;
using std::chrono::seconds;

const TimePoint kStart(std::chrono::hours(1));

TEST(DwellTrackerTest, HoldsOnlyAfterTheConditionHeldForTheWholeDwell) {
  DwellTracker dwell(seconds(1));
  EXPECT_FALSE(dwell.update(kStart, true));
  EXPECT_FALSE(dwell.update(kStart + milliseconds(999), true));
  EXPECT_EQ(dwell.heldFor(kStart + milliseconds(999)), milliseconds(999));
  EXPECT_TRUE(dwell.update(kStart + milliseconds(1000), true));
}

TEST(DwellTrackerTest, AnInterruptionRestartsTheDwell) {
  DwellTracker dwell(seconds(1));
  dwell.update(kStart, true);
  EXPECT_FALSE(dwell.update(kStart + milliseconds(900), false));
  EXPECT_FALSE(dwell.update(kStart + milliseconds(950), true));
  EXPECT_FALSE(dwell.update(kStart + milliseconds(1900), true));
  EXPECT_TRUE(dwell.update(kStart + milliseconds(1950), true));
  dwell.reset();
  EXPECT_FALSE(dwell.update(kStart + milliseconds(2000), true));
}

TEST(DwellTrackerTest, ZeroDwellHoldsAtOnce) {
  DwellTracker dwell(Duration::zero());
  EXPECT_TRUE(dwell.update(kStart, true));
  EXPECT_FALSE(dwell.update(kStart, false));
}

TEST(ProgressWindowTest, ChangeSpansExactlyTheLastWindow) {
  ProgressWindow window(seconds(3));
  EXPECT_FALSE(window.full());
  EXPECT_EQ(window.change(), 0.0);
  for (int i = 0; i <= 10; ++i) window.add(kStart + seconds(i), i * 0.5);  // 0.5 m/s
  EXPECT_TRUE(window.full());
  EXPECT_DOUBLE_EQ(window.change(), 1.5) << "three seconds at 0.5 m/s";
}

TEST(ProgressWindowTest, IsNotFullBeforeAWindowOfSamples) {
  ProgressWindow window(seconds(3));
  window.add(kStart, 0.0);
  window.add(kStart + milliseconds(2999), 1.0);
  EXPECT_FALSE(window.full());
  window.add(kStart + seconds(3), 1.0);
  EXPECT_TRUE(window.full());
  EXPECT_DOUBLE_EQ(window.change(), 1.0);
}

TEST(ProgressWindowTest, StallAfterMovementShowsAsNoChange) {
  ProgressWindow window(seconds(2));
  for (int i = 0; i <= 20; ++i) {  // climbs for 1 s, then stalls at 1 m
    window.add(kStart + milliseconds(100 * i), std::min(1.0, i * 0.1));
  }
  EXPECT_TRUE(window.full());
  EXPECT_NEAR(window.change(), 1.0, 1e-9);
  for (int i = 21; i <= 40; ++i) window.add(kStart + milliseconds(100 * i), 1.0);
  EXPECT_NEAR(window.change(), 0.0, 1e-9);
  window.add(kStart + seconds(1), 5.0);  // older than the newest: ignored
  EXPECT_NEAR(window.change(), 0.0, 1e-9);
  window.reset();
  EXPECT_FALSE(window.full());
}

TEST(BatteryPerformanceTest, FallsWithTheBatteryAndIsZeroBelowTheMinimum) {
  EXPECT_DOUBLE_EQ(batteryPerformance(0.9, 0.3, 0.6), 1.0);
  EXPECT_DOUBLE_EQ(batteryPerformance(0.6, 0.3, 0.6), 1.0);
  EXPECT_DOUBLE_EQ(batteryPerformance(0.3, 0.3, 0.6), 0.2);
  EXPECT_NEAR(batteryPerformance(0.45, 0.3, 0.6), 0.6, 1e-9);
  EXPECT_LT(batteryPerformance(0.4, 0.3, 0.6), batteryPerformance(0.5, 0.3, 0.6));
  EXPECT_DOUBLE_EQ(batteryPerformance(0.29, 0.3, 0.6), 0.0);
}

}  // namespace
}  // namespace behaviorlib::flight
