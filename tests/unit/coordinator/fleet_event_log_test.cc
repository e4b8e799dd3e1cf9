// The coordinator's event log: numbering, resumable replay, filters, bounded
// retention and slow subscribers.

#include "coordinator/events/fleet_event_log.h"

#include <gtest/gtest.h>

#include <atomic>
#include <string>
#include <vector>

namespace behaviorlib::coordinator {
namespace {

v1::FleetEvent behaviorEvent(const std::string& robot, const std::string& behavior,
                             uint64_t system_seq = 1) {
  v1::FleetEvent event;
  auto* e = event.mutable_behavior_event();
  e->set_robot_id(robot);
  e->set_behavior(behavior);
  e->set_seq(system_seq);
  e->mutable_activated();
  return event;
}

v1::FleetEvent systemEvent(const std::string& robot) {
  v1::FleetEvent event;
  auto* changed = event.mutable_system_state_changed();
  changed->mutable_system()->set_robot_id(robot);
  changed->mutable_system()->set_state(v1::SYSTEM_STATE_UP);
  return event;
}

FleetSubscribeOptions resumeAt(const FleetEventLog& log, uint64_t since_seq) {
  FleetSubscribeOptions options;
  options.since_seq = since_seq;
  options.incarnation = log.incarnation();
  return options;
}

FleetSubscribeOptions filter(std::vector<std::string> robot_ids,
                             std::vector<std::string> behaviors) {
  FleetSubscribeOptions options;
  options.robot_ids = std::move(robot_ids);
  options.behaviors = std::move(behaviors);
  return options;
}

FleetEventLogOptions limits(size_t capacity, size_t queue_limit) {
  FleetEventLogOptions options;
  options.capacity = capacity;
  options.subscriber_queue_limit = queue_limit;
  return options;
}

std::vector<uint64_t> drain(FleetSubscription& sub) {
  std::vector<uint64_t> seqs;
  while (auto e = sub.pop()) seqs.push_back(e->seq());
  return seqs;
}

TEST(FleetEventLogTest, NumbersEventsConsecutivelyUnderOneIncarnation) {
  FleetEventLog log;
  ASSERT_EQ(log.incarnation().size(), 32u);
  FleetEventLog other;
  EXPECT_NE(log.incarnation(), other.incarnation());
  for (uint64_t i = 1; i <= 3; ++i) {
    auto stored = log.append(behaviorEvent("a", "WAIT", 100 + i));
    EXPECT_EQ(stored->seq(), i);
    EXPECT_EQ(stored->incarnation(), log.incarnation());
    EXPECT_TRUE(stored->has_wall_time());
    // The system's own numbering is kept inside.
    EXPECT_EQ(stored->behavior_event().seq(), 100 + i);
  }
  EXPECT_EQ(log.latestSeq(), 3u);
}

TEST(FleetEventLogTest, ResumeReplaysExactlyTheEventsAfterSinceSeqThenLiveOnes) {
  FleetEventLog log;
  for (int i = 0; i < 5; ++i) log.append(behaviorEvent("a", "WAIT"));
  auto sub = log.subscribe(resumeAt(log, 3), [] {});
  EXPECT_FALSE(sub->start().incarnation_changed());
  EXPECT_FALSE(sub->start().events_dropped());
  EXPECT_EQ(sub->start().latest_seq(), 5u);
  EXPECT_EQ(sub->start().oldest_retained_seq(), 1u);
  EXPECT_EQ(sub->lastPoppedSeq(), 3u) << "the resume point before anything is popped";
  EXPECT_EQ(drain(*sub), (std::vector<uint64_t>{4, 5}));
  log.append(behaviorEvent("a", "WAIT"));
  EXPECT_EQ(drain(*sub), (std::vector<uint64_t>{6}));
  EXPECT_EQ(sub->lastPoppedSeq(), 6u);
  EXPECT_TRUE(drain(*sub).empty());
}

TEST(FleetEventLogTest, AnotherIncarnationReplaysEverythingRetained) {
  FleetEventLog log;
  for (int i = 0; i < 3; ++i) log.append(behaviorEvent("a", "WAIT"));
  FleetSubscribeOptions otherRun;
  otherRun.since_seq = 2;
  otherRun.incarnation = "a-previous-run";
  auto sub = log.subscribe(otherRun, [] {});
  EXPECT_TRUE(sub->start().incarnation_changed());
  EXPECT_EQ(sub->start().incarnation(), log.incarnation());
  EXPECT_EQ(drain(*sub), (std::vector<uint64_t>{1, 2, 3}));
}

TEST(FleetEventLogTest, FiltersByRobotAndBehavior) {
  FleetEventLog log;
  log.append(behaviorEvent("a", "WAIT"));   // 1
  log.append(behaviorEvent("b", "WAIT"));   // 2
  log.append(behaviorEvent("a", "HOVER"));  // 3
  log.append(systemEvent("a"));             // 4
  log.append(systemEvent("b"));             // 5

  auto robot_a = log.subscribe(filter({"a"}, {}), [] {});
  EXPECT_EQ(drain(*robot_a), (std::vector<uint64_t>{1, 3, 4}));
  auto waits = log.subscribe(filter({}, {"WAIT"}), [] {});
  EXPECT_EQ(drain(*waits), (std::vector<uint64_t>{1, 2}))
      << "no system events with a behavior filter";
  auto b_waits = log.subscribe(filter({"b"}, {"WAIT"}), [] {});
  EXPECT_EQ(drain(*b_waits), (std::vector<uint64_t>{2}));

  // Live events are filtered the same way.
  log.append(behaviorEvent("b", "WAIT"));  // 6
  log.append(behaviorEvent("a", "WAIT"));  // 7
  EXPECT_EQ(drain(*robot_a), (std::vector<uint64_t>{7}));
  EXPECT_EQ(drain(*waits), (std::vector<uint64_t>{6, 7}));
  EXPECT_EQ(drain(*b_waits), (std::vector<uint64_t>{6}));
}

TEST(FleetEventLogTest, EvictsTheOldestAndSaysHowManyWereLost) {
  FleetEventLog log(limits(3, 4096));
  for (int i = 0; i < 7; ++i) log.append(behaviorEvent("a", "WAIT"));
  EXPECT_EQ(log.retainedCount(), 3u);
  auto sub = log.subscribe(resumeAt(log, 2), [] {});
  EXPECT_TRUE(sub->start().events_dropped());
  EXPECT_EQ(sub->start().dropped_count(), 2u) << "seqs 3 and 4 are gone";
  EXPECT_EQ(sub->start().oldest_retained_seq(), 5u);
  EXPECT_EQ(drain(*sub), (std::vector<uint64_t>{5, 6, 7}));

  auto up_to_date = log.subscribe(resumeAt(log, 6), [] {});
  EXPECT_FALSE(up_to_date->start().events_dropped());
  EXPECT_EQ(drain(*up_to_date), (std::vector<uint64_t>{7}));
}

TEST(FleetEventLogTest, SlowSubscriberIsCutOffButKeepsWhatItHas) {
  FleetEventLog log(limits(10000, 2));
  int wakes = 0;
  auto slow = log.subscribe({}, [&] { ++wakes; });
  auto fast = log.subscribe({}, [] {});
  for (int i = 0; i < 5; ++i) {
    log.append(behaviorEvent("a", "WAIT"));
    drain(*fast);
  }
  EXPECT_TRUE(slow->overflowed());
  EXPECT_FALSE(fast->overflowed());
  EXPECT_EQ(wakes, 2) << "once when the queue became non-empty, once on overflow";
  EXPECT_EQ(drain(*slow), (std::vector<uint64_t>{1, 2}));
  EXPECT_EQ(slow->lastPoppedSeq(), 2u) << "where it resumes";
  // The replay of a resumed subscription does not count against the limit.
  auto resumed = log.subscribe(resumeAt(log, 2), [] {});
  EXPECT_FALSE(resumed->overflowed());
  EXPECT_EQ(drain(*resumed), (std::vector<uint64_t>{3, 4, 5}));
}

TEST(FleetEventLogTest, WakeMayCancelItsOwnSubscriptionAndNothingArrivesAfterCancel) {
  FleetEventLog log;
  std::unique_ptr<FleetSubscription> sub;
  std::atomic<int> wakes{0};
  sub = log.subscribe({}, [&] {
    ++wakes;
    sub->cancel();
  });
  log.append(behaviorEvent("a", "WAIT"));
  log.append(behaviorEvent("a", "WAIT"));
  EXPECT_EQ(wakes.load(), 1);
  EXPECT_EQ(drain(*sub), (std::vector<uint64_t>{1}));
}

}  // namespace
}  // namespace behaviorlib::coordinator

namespace behaviorlib::coordinator {
namespace {

// The stored wire form is the event as appended (with its seq), and a batch
// stops before its byte budget, but never pops nothing.
TEST(FleetEventLogTest, RecordsCarryTheEventsWireFormAndBatchesKeepToTheirByteBudget) {
  FleetEventLog log;
  auto sub = log.subscribe({}, [] {});
  for (int i = 0; i < 5; ++i) {
    v1::FleetEvent event = behaviorEvent("drone1", "WAIT");
    event.mutable_behavior_event()->set_activation_id(std::string(100, 'x'));
    log.append(std::move(event));
  }
  const auto first = sub->popRecordsUpTo(1);
  ASSERT_EQ(first.size(), 1u);
  v1::FleetEvent parsed;
  ASSERT_TRUE(parsed.ParseFromString(first[0]->wire()));
  EXPECT_EQ(parsed.seq(), 1u);
  EXPECT_EQ(parsed.incarnation(), log.incarnation());
  EXPECT_EQ(parsed.SerializeAsString(), first[0]->event().SerializeAsString());

  const size_t size = first[0]->wire().size();
  ASSERT_GT(size, 100u);
  // Room for two and a half events: two are popped.
  auto two = sub->popRecordsUpTo(10, size * 5 / 2);
  ASSERT_EQ(two.size(), 2u);
  EXPECT_EQ(two[0]->event().seq(), 2u);
  EXPECT_EQ(two[1]->event().seq(), 3u);
  // A budget smaller than one event still pops one.
  auto one = sub->popRecordsUpTo(10, 1);
  ASSERT_EQ(one.size(), 1u);
  EXPECT_EQ(one[0]->event().seq(), 4u);
  EXPECT_EQ(sub->lastPoppedSeq(), 4u);
  EXPECT_EQ(drain(*sub), std::vector<uint64_t>({5}));
}

}  // namespace
}  // namespace behaviorlib::coordinator
