// SimClock over fake host clocks: it extrapolates the simulator's time line
// between samples, never reads backwards within an epoch, follows a new
// epoch at once, stands still in lock-step or while paused, and runs on at
// the last scale when the samples stop (a dead simulator).

#include "behaviorlib/channel/sim_clock.h"

#include <google/protobuf/util/time_util.h>
#include <gtest/gtest.h>

#include <atomic>

#include "behaviorlib/v1/types.pb.h"

namespace behaviorlib::channel {
namespace {

using std::chrono::milliseconds;
using std::chrono::nanoseconds;
using std::chrono::seconds;

// Host clocks a test moves by hand: steady and system advance together.
struct FakeHost {
  std::atomic<int64_t> ns{1'000'000'000'000};
  SimClock::HostClocks clocks() {
    return {
        .steady = [this] { return std::chrono::steady_clock::time_point(nanoseconds(ns)); },
        .system =
            [this] {
              return std::chrono::system_clock::time_point(
                  std::chrono::duration_cast<std::chrono::system_clock::duration>(nanoseconds(ns)));
            }};
  }
  void advance(nanoseconds d) { ns += d.count(); }
  google::protobuf::Timestamp wallAgo(nanoseconds ago) const {
    return google::protobuf::util::TimeUtil::NanosecondsToTimestamp(ns - ago.count());
  }
};

v1::Clock sample(int64_t sec, int32_t nanos, double time_scale, bool paused = false,
                 uint64_t epoch = 7) {
  v1::Clock c;
  c.mutable_time()->set_seconds(sec);
  c.mutable_time()->set_nanos(nanos);
  *c.mutable_header()->mutable_stamp() = c.time();
  c.set_time_scale(time_scale);
  c.set_paused(paused);
  c.set_epoch(epoch);
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
  EXPECT_EQ(clock.now(), TimePoint{});
  EXPECT_TRUE(clock.stale(seconds(100)));
  EXPECT_EQ(clock.lastWallUpdate(), TimePoint{});
  EXPECT_EQ(clock.wallWaitFor(seconds(1)), milliseconds(50));
}

TEST(SimClockTest, ExtrapolatesTheTimeLineBetweenSamples) {
  FakeHost host;
  SimClock clock(host.clocks());
  clock.onClockSample(sample(100, 250'000'000, 2.0));
  EXPECT_TRUE(clock.valid());
  EXPECT_EQ(clock.now(), TimePoint(seconds(100) + milliseconds(250)));
  host.advance(milliseconds(500));  // 0.5 wall seconds at 2x: one simulated second
  EXPECT_EQ(clock.now(), TimePoint(seconds(101) + milliseconds(250)));
  EXPECT_DOUBLE_EQ(clock.timeScale(), 2.0);
  EXPECT_FALSE(clock.paused());
  EXPECT_EQ(clock.sampleCount(), 1u);
}

TEST(SimClockTest, PlacesTheSampleAtItsWallTime) {
  FakeHost host;
  SimClock clock(host.clocks());
  v1::Clock s = sample(10, 0, 10.0);
  *s.mutable_wall_time() = host.wallAgo(milliseconds(3));  // 3 ms in transit
  clock.onClockSample(s);
  EXPECT_EQ(clock.now(), TimePoint(seconds(10) + milliseconds(30)));
  // A wall_time our host cannot agree with (a skewed publisher's host, or
  // from the future) counts as the time of arrival.
  s = sample(20, 0, 10.0);
  *s.mutable_wall_time() = host.wallAgo(seconds(3600));
  clock.onClockSample(s);
  EXPECT_EQ(clock.now(), TimePoint(seconds(20)));
  s = sample(30, 0, 10.0);
  *s.mutable_wall_time() = host.wallAgo(-seconds(1));
  clock.onClockSample(s);
  EXPECT_EQ(clock.now(), TimePoint(seconds(30)));
}

TEST(SimClockTest, NeverReadsBackwardsWithinAnEpochButFollowsANewOne) {
  FakeHost host;
  SimClock clock(host.clocks());
  clock.onClockSample(sample(50, 0, 10.0));
  host.advance(milliseconds(100));
  EXPECT_EQ(clock.now(), TimePoint(seconds(51)));
  // The simulator fell behind and published a slower line: the reading
  // holds until the line passes it.
  clock.onClockSample(sample(50, 800'000'000, 10.0));
  EXPECT_EQ(clock.now(), TimePoint(seconds(51)));
  host.advance(milliseconds(10));
  EXPECT_EQ(clock.now(), TimePoint(seconds(51))) << "the line is at 50.9 s";
  host.advance(milliseconds(20));
  EXPECT_EQ(clock.now(), TimePoint(seconds(51) + milliseconds(100)));
  // Reset (a new epoch): time restarts at once.
  clock.onClockSample(sample(0, 0, 10.0, false, /*epoch=*/8));
  EXPECT_EQ(clock.now(), TimePoint{});
  host.advance(milliseconds(10));
  EXPECT_EQ(clock.now(), TimePoint(milliseconds(100)));
}

TEST(SimClockTest, ALateOlderSampleMovesNothingBackEvenUnread) {
  FakeHost host;
  SimClock clock(host.clocks());
  clock.onClockSample(sample(7, 0, 0.0));            // a time grant, never read
  clock.onClockSample(sample(6, 995'000'000, 0.0));  // the channel's, late
  EXPECT_EQ(clock.now(), TimePoint(seconds(7)));
}

TEST(SimClockTest, StandsStillInLockStepOrWhilePaused) {
  FakeHost host;
  SimClock clock(host.clocks());
  clock.onClockSample(sample(5, 0, 0.0));  // lock-step
  host.advance(seconds(10));
  EXPECT_EQ(clock.now(), TimePoint(seconds(5)));
  clock.onClockSample(sample(5, 5'000'000, 0.0));
  EXPECT_EQ(clock.now(), TimePoint(seconds(5) + milliseconds(5)));
  clock.onClockSample(sample(6, 0, 10.0, /*paused=*/true));
  host.advance(seconds(10));
  EXPECT_EQ(clock.now(), TimePoint(seconds(6)));
  EXPECT_TRUE(clock.paused());
}

TEST(SimClockTest, RunsOnAtTheLastScaleWhenTheSamplesStop) {
  FakeHost host;
  SimClock clock(host.clocks());
  clock.onClockSample(sample(10, 0, 10.0));
  host.advance(seconds(3));  // the simulator died: no heartbeat for 3 s
  EXPECT_TRUE(clock.stale(seconds(2)));
  EXPECT_FALSE(clock.stale(seconds(4)));
  EXPECT_EQ(clock.now(), TimePoint(seconds(40)));
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

  clock.onClockSample(sample(4, 0, 10.0, /*paused=*/true));
  EXPECT_EQ(clock.wallWaitFor(milliseconds(1)), milliseconds(50));

  clock.onClockSample(sample(5, 0, 1e-9));  // tiny scale clamped to 1e-3
  EXPECT_EQ(clock.wallWaitFor(nanoseconds(10)), nanoseconds(10'000));
  EXPECT_EQ(clock.wallWaitFor(Duration::max()), milliseconds(50));
}

TEST(SimClockTest, StalenessAndLastWallUpdate) {
  FakeHost host;
  SimClock clock(host.clocks());
  clock.onClockSample(sample(1, 0, 1.0));
  EXPECT_EQ(clock.lastWallUpdate(), TimePoint(nanoseconds(host.ns.load())));
  EXPECT_FALSE(clock.stale(seconds(10)));
  host.advance(milliseconds(20));
  EXPECT_TRUE(clock.stale(milliseconds(5)));
  clock.onClockSample(sample(2, 0, 1.0));
  EXPECT_FALSE(clock.stale(milliseconds(5)));
}

}  // namespace
}  // namespace behaviorlib::channel
