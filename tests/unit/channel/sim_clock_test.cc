#include "channel/sim_clock.h"

#include <gtest/gtest.h>

#include <atomic>
#include <thread>

#include "behaviorlib/v1/types.pb.h"

namespace behaviorlib::channel {
namespace {

using std::chrono::milliseconds;
using std::chrono::nanoseconds;
using std::chrono::seconds;

v1::Clock sample(int64_t sec, int32_t nanos, double time_scale, bool paused = false) {
  v1::Clock c;
  c.mutable_time()->set_seconds(sec);
  c.mutable_time()->set_nanos(nanos);
  *c.mutable_header()->mutable_stamp() = c.time();
  c.set_time_scale(time_scale);
  c.set_paused(paused);
  return c;
}

class CountingListener : public ClockListener {
 public:
  void onClockAdvanced() override { ++calls; }
  std::atomic<int> calls{0};
};

TEST(SimClockTest, InvalidAndStaleUntilFirstSample) {
  SimClock clock;
  EXPECT_FALSE(clock.valid());
  EXPECT_TRUE(clock.stale(seconds(100)));
  EXPECT_EQ(clock.lastWallUpdate(), TimePoint{});
  EXPECT_EQ(clock.wallWaitFor(seconds(1)), milliseconds(50));
}

TEST(SimClockTest, FollowsSamples) {
  SimClock clock;
  clock.onClockSample(sample(100, 250'000'000, 1.0));
  EXPECT_TRUE(clock.valid());
  EXPECT_EQ(clock.now(), TimePoint(seconds(100) + milliseconds(250)));
  EXPECT_DOUBLE_EQ(clock.timeScale(), 1.0);
  EXPECT_FALSE(clock.paused());
  clock.onClockSample(sample(101, 0, 5.0, true));
  EXPECT_EQ(clock.now(), TimePoint(seconds(101)));
  EXPECT_DOUBLE_EQ(clock.timeScale(), 5.0);
  EXPECT_TRUE(clock.paused());
}

TEST(SimClockTest, NotifiesListenersOnEverySample) {
  SimClock clock;
  CountingListener listener;
  clock.addListener(&listener);
  clock.onClockSample(sample(1, 0, 1.0));
  clock.onClockSample(sample(2, 0, 1.0));
  EXPECT_EQ(listener.calls.load(), 2);
  clock.removeListener(&listener);
  clock.onClockSample(sample(3, 0, 1.0));
  EXPECT_EQ(listener.calls.load(), 2);
}

TEST(SimClockTest, WallWaitForScalesAndIsBounded) {
  SimClock clock;
  clock.onClockSample(sample(1, 0, 1.0));
  EXPECT_EQ(clock.wallWaitFor(milliseconds(10)), milliseconds(10));
  EXPECT_EQ(clock.wallWaitFor(seconds(10)), milliseconds(50));
  EXPECT_EQ(clock.wallWaitFor(nanoseconds(0)), nanoseconds(0));
  EXPECT_EQ(clock.wallWaitFor(milliseconds(-5)), nanoseconds(0));

  clock.onClockSample(sample(2, 0, 20.0));  // 20x: 100 ms simulated = 5 ms wall
  EXPECT_EQ(clock.wallWaitFor(milliseconds(100)), milliseconds(5));

  clock.onClockSample(sample(3, 0, 0.0));  // lock-step: only the safety net
  EXPECT_EQ(clock.wallWaitFor(milliseconds(1)), milliseconds(50));

  clock.onClockSample(sample(4, 0, 1e-9));  // tiny scale clamped to 1e-3
  EXPECT_EQ(clock.wallWaitFor(nanoseconds(10)), nanoseconds(10'000));
  EXPECT_EQ(clock.wallWaitFor(Duration::max()), milliseconds(50));
}

TEST(SimClockTest, StalenessAndLastWallUpdate) {
  SimClock clock;
  const auto before = std::chrono::system_clock::now();
  clock.onClockSample(sample(1, 0, 1.0));
  const auto after = std::chrono::system_clock::now();
  EXPECT_GE(clock.lastWallUpdate(), before);
  EXPECT_LE(clock.lastWallUpdate(), after);
  EXPECT_FALSE(clock.stale(seconds(10)));
  std::this_thread::sleep_for(milliseconds(20));
  EXPECT_TRUE(clock.stale(milliseconds(5)));
  clock.onClockSample(sample(2, 0, 1.0));
  EXPECT_FALSE(clock.stale(seconds(10)));
}

}  // namespace
}  // namespace behaviorlib::channel
