// The deterministic mode's barrier for setpoints, both sides: the follower's
// SetpointLedger (what its reports name) and the simulator's SetpointBarrier
// (what the next step waits for). The whole path, over gRPC with real
// processes, is in simulator_service_test (SimulatorDeterministicTest).

#include "simulator/service/setpoint_barrier.h"

#include <gtest/gtest.h>

#include <chrono>
#include <string>
#include <thread>

#include "behaviorlib/server/setpoint_ledger.h"

namespace behaviorlib {
namespace {

using std::chrono::milliseconds;
using std::chrono::seconds;

std::map<std::string, uint64_t> named(server::SetpointLedger& ledger) {
  google::protobuf::Map<std::string, uint64_t> counts;
  ledger.fill(&counts);
  return {counts.begin(), counts.end()};
}

TEST(SetpointLedger, AReportNamesWhatWasWrittenOnEachStreamAndAClosedOneOnceMore) {
  server::SetpointLedger ledger;
  const std::string a = ledger.open();
  const std::string b = ledger.open();
  EXPECT_NE(a, b);
  EXPECT_NE(a, server::SetpointLedger().open()) << "two processes' keys met";
  EXPECT_TRUE(named(ledger).empty()) << "a stream with nothing written was named";
  ledger.wrote(a);
  ledger.wrote(a);
  ledger.wrote(b);
  EXPECT_EQ(named(ledger), (std::map<std::string, uint64_t>{{a, 2}, {b, 1}}));
  // Counts are totals of the stream, not what came since the last report.
  ledger.wrote(b);
  ledger.closed(b);
  EXPECT_EQ(named(ledger), (std::map<std::string, uint64_t>{{a, 2}, {b, 2}}));
  // Closed and reported: forgotten.
  EXPECT_EQ(named(ledger), (std::map<std::string, uint64_t>{{a, 2}}));
  ledger.wrote(b);  // a late write on a forgotten stream is not counted
  EXPECT_EQ(named(ledger), (std::map<std::string, uint64_t>{{a, 2}}));
}

TEST(SetpointBarrier, AStepWaitsUntilEveryReportedSetpointWasReadOrItsStreamEnded) {
  sim::SetpointBarrier barrier;
  ASSERT_TRUE(barrier.opened("k1"));
  EXPECT_FALSE(barrier.opened("k1")) << "a key in use was opened twice";
  EXPECT_TRUE(barrier.awaitRead({}, seconds(0)));
  EXPECT_TRUE(barrier.awaitRead({{"k1", 0}}, seconds(0)));
  // Written but not read yet: the wait gives up at its limit.
  EXPECT_FALSE(barrier.awaitRead({{"k1", 2}}, seconds(0)));
  EXPECT_EQ(barrier.timeoutCount(), 1u);
  barrier.read("k1");
  EXPECT_FALSE(barrier.awaitRead({{"k1", 2}}, seconds(0)));
  barrier.read("k1");
  EXPECT_TRUE(barrier.awaitRead({{"k1", 2}}, seconds(0)));
  // A stream that ended is not waited for (what it did not deliver never
  // comes), and its key is not used again.
  ASSERT_TRUE(barrier.opened("k2"));
  barrier.ended("k2");
  EXPECT_TRUE(barrier.awaitRead({{"k2", 5}}, seconds(0)));
  EXPECT_FALSE(barrier.opened("k2")) << "an ended stream's key was used again";
  // One the simulator has not seen yet (its first message is on its way) is
  // waited for; once a wait gave up on it (its process died, or its
  // setpoints went to another platform), it counts as ended.
  EXPECT_FALSE(barrier.awaitRead({{"k3", 1}}, seconds(0)));
  EXPECT_TRUE(barrier.awaitRead({{"k3", 1}}, seconds(0)));
  EXPECT_FALSE(barrier.opened("k3"));
  EXPECT_EQ(barrier.waitCount(), 3u);
  EXPECT_EQ(barrier.timeoutCount(), 3u);
}

TEST(SetpointBarrier, AWaitEndsWhenTheSetpointIsRead) {
  sim::SetpointBarrier barrier;
  ASSERT_TRUE(barrier.opened("k"));
  bool done = false;
  std::thread step([&] { done = barrier.awaitRead({{"k", 1}}, seconds(60)); });
  // Whether the wait began before this read or not, it ends with true.
  barrier.read("k");
  step.join();
  EXPECT_TRUE(done);
  EXPECT_EQ(barrier.timeoutCount(), 0u);
}

TEST(SetpointBarrier, KeysAreBounded) {
  sim::SetpointBarrier barrier;
  EXPECT_FALSE(barrier.opened(""));
  EXPECT_FALSE(barrier.opened(std::string(sim::SetpointBarrier::kMaxKeyBytes + 1, 'k')));
  EXPECT_TRUE(barrier.opened(std::string(sim::SetpointBarrier::kMaxKeyBytes, 'k')));
  // The keys of ended streams are kept up to a bound, the oldest forgotten.
  for (size_t i = 0; i <= sim::SetpointBarrier::kEndedKeysKept; ++i) {
    const std::string key = "s" + std::to_string(i);
    ASSERT_TRUE(barrier.opened(key));
    barrier.ended(key);
  }
  EXPECT_TRUE(barrier.awaitRead({{"s1", 1}}, seconds(0)));
  EXPECT_FALSE(barrier.awaitRead({{"s0", 1}}, milliseconds(1))) << "the oldest was kept";
  // A key too long is never counted, so never waited for.
  const std::string long_key(sim::SetpointBarrier::kMaxKeyBytes + 1, 'x');
  EXPECT_TRUE(barrier.awaitRead({{long_key, 1}}, seconds(0)));
}

}  // namespace
}  // namespace behaviorlib
