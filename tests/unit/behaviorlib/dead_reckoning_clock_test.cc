// DeadReckoningClock over a SimClock fed by hand: it follows the samples,
// stands still within the grace, then runs on at the last time scale; never
// in lock-step or while paused. (The grace is wall time by design: it
// measures the simulator's silence; the waits here are far from the bounds
// asserted.)

#include "behaviorlib/server/dead_reckoning_clock.h"

#include <google/protobuf/util/time_util.h>
#include <gtest/gtest.h>

#include <thread>

#include "behaviorlib/v1/types.pb.h"
#include "channel/sim_clock.h"

namespace behaviorlib::server {
namespace {

using google::protobuf::util::TimeUtil;
using std::chrono::milliseconds;
using std::chrono::seconds;

v1::Clock sample(double t_s, double scale, bool paused = false) {
  v1::Clock clock;
  *clock.mutable_time() = TimeUtil::NanosecondsToTimestamp(static_cast<int64_t>(t_s * 1e9));
  clock.set_time_scale(scale);
  clock.set_paused(paused);
  return clock;
}

double secondsOf(TimePoint t) {
  return std::chrono::duration<double>(t.time_since_epoch()).count();
}

TEST(DeadReckoningClockTest, FollowsSamplesThenRunsOnAtTheLastScaleAfterTheGrace) {
  channel::SimClock source;
  DeadReckoningClock clock(source, milliseconds(100));
  EXPECT_FALSE(clock.valid());
  source.onClockSample(sample(10.0, 10.0));
  EXPECT_TRUE(clock.valid());
  EXPECT_DOUBLE_EQ(secondsOf(clock.now()), 10.0);
  EXPECT_FALSE(clock.deadReckoning());
  std::this_thread::sleep_for(milliseconds(40));
  EXPECT_DOUBLE_EQ(secondsOf(clock.now()), 10.0) << "within the grace: time stands";
  std::this_thread::sleep_for(milliseconds(260));  // 300 ms silent, 200 ms beyond the grace
  EXPECT_TRUE(clock.deadReckoning());
  const double t = secondsOf(clock.now());
  EXPECT_GE(t, 12.0) << "at least 200 ms of wall time at 10x";
  EXPECT_LT(t, 30.0);
  // Samples again: it follows them.
  source.onClockSample(sample(11.0, 10.0));
  EXPECT_FALSE(clock.deadReckoning());
  EXPECT_DOUBLE_EQ(secondsOf(clock.now()), 11.0);
}

TEST(DeadReckoningClockTest, StandsStillInLockStepOrWhilePaused) {
  channel::SimClock source;
  DeadReckoningClock clock(source, milliseconds(20));
  source.onClockSample(sample(5.0, 0.0));  // lock-step
  std::this_thread::sleep_for(milliseconds(100));
  EXPECT_FALSE(clock.deadReckoning());
  EXPECT_DOUBLE_EQ(secondsOf(clock.now()), 5.0);
  source.onClockSample(sample(6.0, 10.0, /*paused=*/true));
  std::this_thread::sleep_for(milliseconds(100));
  EXPECT_DOUBLE_EQ(secondsOf(clock.now()), 6.0);
}

TEST(DeadReckoningClockTest, ForwardsTheSourcesAdvancesToItsListeners) {
  struct Counter final : ClockListener {
    void onClockAdvanced() override { ++count; }
    std::atomic<int> count{0};
  } counter;
  channel::SimClock source;
  DeadReckoningClock clock(source, seconds(1));
  clock.addListener(&counter);
  source.onClockSample(sample(1.0, 1.0));
  source.onClockSample(sample(1.01, 1.0));
  EXPECT_EQ(counter.count.load(), 2);
  clock.removeListener(&counter);
}

}  // namespace
}  // namespace behaviorlib::server
