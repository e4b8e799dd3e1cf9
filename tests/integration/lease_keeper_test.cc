// LeaseKeeper against the real simulator's FlightController (free running at
// 1x, so its 2 s lease outlives the test): the keeper renews on its own clock
// (a FakeClock here, as a SimClock under the deterministic mode), and tells
// that clock whether the renewal due by a time is done
// (Clock::listenersCaughtUp), which is what the deterministic mode's follower
// waits for before it reports a granted time.

#include "behaviorlib/platform/lease_keeper.h"

#include <gtest/gtest.h>

#include <chrono>
#include <thread>

#include "behaviorlib/clock.h"
#include "behaviorlib/platform/flight_controller_client.h"
#include "support/server_process.h"

namespace behaviorlib::platform {
namespace {

using std::chrono::milliseconds;
using std::chrono::seconds;

TEST(LeaseKeeperTest, ARenewalDueByAGrantedTimeIsDoneBeforeTheClockCountsAsCaughtUp) {
  support::ServerProcess broker(BEHAVIORLIB_CHANNEL_BROKER_PATH, {});
  ASSERT_TRUE(broker.start()) << broker.error();
  support::ServerProcess simulator(BEHAVIORLIB_SIMULATOR_PATH,
                                   {"--channel", broker.address(), "--time-scale", "1"});
  ASSERT_TRUE(simulator.start()) << simulator.error();
  FlightControllerClient client(simulator.address(), "drone1");
  FakeClock clock;

  auto keeper = LeaseKeeper::acquire(client, clock, "lease_keeper_test", {.ttl = seconds(2)});
  ASSERT_TRUE(keeper.ok()) << keeper.status();
  EXPECT_TRUE(clock.listenersCaughtUp(clock.now())) << "nothing is due yet";
  EXPECT_EQ((*keeper)->renewals(), 0u);

  // A quarter of the ttl later a renewal is due: the clock is not caught up
  // with that time until the renewal is done.
  for (uint64_t round = 1; round <= 3; ++round) {
    clock.advance(milliseconds(600));
    const TimePoint granted = clock.now();
    const auto give_up = std::chrono::steady_clock::now() + seconds(10);
    while (!clock.listenersCaughtUp(granted)) {
      ASSERT_LT(std::chrono::steady_clock::now(), give_up) << "the renewal never completed";
      std::this_thread::sleep_for(milliseconds(1));
    }
    EXPECT_GE((*keeper)->renewals(), round) << "caught up before the renewal due was done";
    EXPECT_TRUE((*keeper)->status().ok()) << (*keeper)->status();
  }

  // Released: nothing of it is due any more.
  EXPECT_TRUE((*keeper)->release().ok());
  clock.advance(seconds(5));
  EXPECT_TRUE(clock.listenersCaughtUp(clock.now()));
  keeper->reset();
  EXPECT_EQ(simulator.terminate(), 0);
  EXPECT_EQ(broker.terminate(), 0);
}

}  // namespace
}  // namespace behaviorlib::platform
