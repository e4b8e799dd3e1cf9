#include "behaviorlib/event_log.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <atomic>
#include <chrono>
#include <future>
#include <memory>
#include <regex>
#include <set>
#include <string>
#include <thread>
#include <vector>

namespace behaviorlib {
namespace {

using std::chrono::nanoseconds;
using std::chrono::seconds;
using ::testing::ElementsAre;
using ::testing::IsEmpty;

v1::BehaviorEvent activated(const std::string& behavior, const std::string& activation) {
  v1::BehaviorEvent event;
  event.set_behavior(behavior);
  event.set_activation_id(activation);
  event.mutable_activated();
  return event;
}

v1::BehaviorEvent modified(const std::string& behavior, const std::string& activation) {
  v1::BehaviorEvent event;
  event.set_behavior(behavior);
  event.set_activation_id(activation);
  event.mutable_modified();
  return event;
}

v1::BehaviorEvent finished(const std::string& behavior, const std::string& activation) {
  v1::BehaviorEvent event;
  event.set_behavior(behavior);
  event.set_activation_id(activation);
  event.mutable_finished()->set_message("done");
  return event;
}

// Designated initializers that skip fields trip -Wmissing-field-initializers.
SubscribeOptions subscribeOptions(uint64_t since_seq, std::string incarnation = "",
                                  std::vector<std::string> behaviors = {}) {
  SubscribeOptions options;
  options.since_seq = since_seq;
  options.incarnation = std::move(incarnation);
  options.behaviors = std::move(behaviors);
  return options;
}

// Pops everything queued and returns the seqs, in order.
std::vector<uint64_t> drain(EventSubscription& subscription) {
  std::vector<uint64_t> seqs;
  while (EventPtr event = subscription.pop()) seqs.push_back(event->seq());
  return seqs;
}

std::vector<uint64_t> range(uint64_t first, uint64_t last) {
  std::vector<uint64_t> seqs;
  for (uint64_t seq = first; seq <= last; ++seq) seqs.push_back(seq);
  return seqs;
}

// Retention time under test control.
class FakeWallClock {
 public:
  void set(nanoseconds now) { now_ = now.count(); }
  void advance(nanoseconds by) { now_ += by.count(); }
  std::function<nanoseconds()> fn() {
    return [this] { return nanoseconds(now_.load()); };
  }

 private:
  std::atomic<int64_t> now_{0};
};

EventLogOptions testOptions() {
  EventLogOptions options;
  options.robot_id = "drone1";
  options.system = "basic_quadrotor_behaviors";
  options.incarnation = "run-b";
  return options;
}

TEST(EventLogTest, AssignsConsecutiveSeqsAndFillsFields) {
  EventLog log(testOptions());
  auto subscription = log.subscribe({}, [] {});
  EXPECT_EQ(log.latestSeq(), 0u);

  v1::BehaviorEvent event = activated("WAIT", "a1");
  // Whatever the caller put there is overwritten.
  event.set_seq(99);
  event.set_incarnation("bogus");
  event.set_robot_id("other");
  event.set_system("other");
  event.mutable_time()->set_seconds(42);

  const auto before = std::chrono::system_clock::now();
  EventPtr first = log.append(event);
  EventPtr second = log.append(modified("WAIT", "a1"));
  EventPtr third = log.append(finished("WAIT", "a1"));
  const auto after = std::chrono::system_clock::now();

  EXPECT_EQ(first->seq(), 1u);
  EXPECT_EQ(second->seq(), 2u);
  EXPECT_EQ(third->seq(), 3u);
  EXPECT_EQ(log.latestSeq(), 3u);
  for (const EventPtr& stored : {first, second, third}) {
    EXPECT_EQ(stored->incarnation(), "run-b");
    EXPECT_EQ(stored->robot_id(), "drone1");
    EXPECT_EQ(stored->system(), "basic_quadrotor_behaviors");
    EXPECT_EQ(stored->behavior(), "WAIT");
    EXPECT_EQ(stored->activation_id(), "a1");
    const auto wall = std::chrono::system_clock::time_point(
        std::chrono::duration_cast<std::chrono::system_clock::duration>(
            seconds(stored->wall_time().seconds()) + nanoseconds(stored->wall_time().nanos())));
    EXPECT_GE(wall, before);
    EXPECT_LE(wall, after);
  }
  EXPECT_EQ(first->time().seconds(), 42);
  EXPECT_TRUE(first->has_activated());
  EXPECT_EQ(third->finished().message(), "done");
  EXPECT_EQ(log.incarnation(), "run-b");
  EXPECT_EQ(log.robotId(), "drone1");
  EXPECT_EQ(log.system(), "basic_quadrotor_behaviors");

  // Subscribers get the very object that is stored, not a copy.
  EXPECT_EQ(subscription->pop(), first);
  EXPECT_EQ(subscription->pop(), second);
  EXPECT_EQ(subscription->pop(), third);
  EXPECT_EQ(subscription->pop(), nullptr);
  EXPECT_EQ(subscription->lastPoppedSeq(), 3u);
}

TEST(EventLogTest, GeneratesIncarnationWhenNoneGiven) {
  EventLogOptions options = testOptions();
  options.incarnation.clear();
  EventLog a(options);
  EventLog b(options);
  const std::regex hex32("[0-9a-f]{32}");
  EXPECT_TRUE(std::regex_match(a.incarnation(), hex32)) << a.incarnation();
  EXPECT_NE(a.incarnation(), b.incarnation());
  EXPECT_EQ(a.append(activated("WAIT", "a1"))->incarnation(), a.incarnation());
}

TEST(EventLogTest, NewIncarnationIdIs32LowercaseHexDigitsAndUnique) {
  const std::regex hex32("[0-9a-f]{32}");
  std::set<std::string> ids;
  for (int i = 0; i < 200; ++i) {
    const std::string id = newIncarnationId();
    EXPECT_TRUE(std::regex_match(id, hex32)) << id;
    ids.insert(id);
  }
  EXPECT_EQ(ids.size(), 200u);
}

TEST(EventLogTest, ReplaysEventsAfterSinceSeq) {
  EventLog log(testOptions());
  for (int i = 0; i < 5; ++i) log.append(modified("WAIT", "a1"));

  auto subscription = log.subscribe(subscribeOptions(2), [] {});
  const v1::WatchEventsStart& start = subscription->start();
  EXPECT_EQ(start.incarnation(), "run-b");
  EXPECT_FALSE(start.incarnation_changed());
  EXPECT_FALSE(start.events_dropped());
  EXPECT_EQ(start.dropped_count(), 0u);
  EXPECT_EQ(start.oldest_retained_seq(), 1u);
  EXPECT_EQ(start.latest_seq(), 5u);
  EXPECT_THAT(drain(*subscription), ElementsAre(3, 4, 5));
  EXPECT_EQ(subscription->lastPoppedSeq(), 5u);

  // Then live events follow.
  log.append(modified("WAIT", "a1"));
  EXPECT_THAT(drain(*subscription), ElementsAre(6));

  EXPECT_THAT(drain(*log.subscribe(subscribeOptions(0), [] {})), ElementsAre(1, 2, 3, 4, 5, 6));
  EXPECT_THAT(drain(*log.subscribe(subscribeOptions(6), [] {})), IsEmpty());
}

TEST(EventLogTest, StartOfEmptyLog) {
  EventLog log(testOptions());
  auto subscription = log.subscribe({}, [] {});
  const v1::WatchEventsStart& start = subscription->start();
  EXPECT_EQ(start.incarnation(), "run-b");
  EXPECT_FALSE(start.incarnation_changed());
  EXPECT_FALSE(start.events_dropped());
  EXPECT_EQ(start.oldest_retained_seq(), 0u);
  EXPECT_EQ(start.latest_seq(), 0u);
  EXPECT_EQ(subscription->pop(), nullptr);
  EXPECT_EQ(subscription->lastPoppedSeq(), 0u);
  EXPECT_FALSE(subscription->overflowed());
}

TEST(EventLogTest, SinceSeqBeyondLatestReplaysNothingWithoutFlags) {
  EventLog log(testOptions());
  for (int i = 0; i < 3; ++i) log.append(modified("WAIT", "a1"));
  auto subscription = log.subscribe(subscribeOptions(10, "run-b"), [] {});
  const v1::WatchEventsStart& start = subscription->start();
  EXPECT_FALSE(start.incarnation_changed());
  EXPECT_FALSE(start.events_dropped());
  EXPECT_EQ(start.dropped_count(), 0u);
  EXPECT_EQ(start.latest_seq(), 3u);
  EXPECT_THAT(drain(*subscription), IsEmpty());
  log.append(modified("WAIT", "a1"));
  EXPECT_THAT(drain(*subscription), ElementsAre(4));
}

TEST(EventLogTest, FiltersByBehavior) {
  EventLog log(testOptions());
  log.append(activated("WAIT", "a1"));     // 1
  log.append(activated("TAKE_OFF", "b"));  // 2
  log.append(activated("LAND", "c"));      // 3
  log.append(finished("WAIT", "a1"));      // 4

  auto subscription = log.subscribe(subscribeOptions(0, "", {"WAIT", "LAND"}), [] {});
  EXPECT_EQ(subscription->start().latest_seq(), 4u);
  EXPECT_THAT(drain(*subscription), ElementsAre(1, 3, 4));

  log.append(finished("TAKE_OFF", "b"));  // 5
  log.append(finished("LAND", "c"));      // 6
  EXPECT_THAT(drain(*subscription), ElementsAre(6));

  auto take_off = log.subscribe(subscribeOptions(1, "", {"TAKE_OFF"}), [] {});
  EXPECT_THAT(drain(*take_off), ElementsAre(2, 5));
}

TEST(EventLogTest, FilteredOutEventsDoNotWake) {
  EventLog log(testOptions());
  int wakes = 0;
  auto subscription = log.subscribe(subscribeOptions(0, "", {"WAIT"}), [&] { ++wakes; });
  log.append(activated("LAND", "c"));
  EXPECT_EQ(wakes, 0);
  log.append(activated("WAIT", "a"));
  EXPECT_EQ(wakes, 1);
}

TEST(EventLogTest, ReportsIncarnationChangedAndReplaysAllRetained) {
  EventLog log(testOptions());
  for (int i = 0; i < 5; ++i) log.append(modified("WAIT", "a1"));

  auto other = log.subscribe(subscribeOptions(3, "run-a"), [] {});
  EXPECT_EQ(other->start().incarnation(), "run-b");
  EXPECT_TRUE(other->start().incarnation_changed());
  EXPECT_FALSE(other->start().events_dropped());
  EXPECT_THAT(drain(*other), ElementsAre(1, 2, 3, 4, 5));

  auto same = log.subscribe(subscribeOptions(3, "run-b"), [] {});
  EXPECT_FALSE(same->start().incarnation_changed());
  EXPECT_THAT(drain(*same), ElementsAre(4, 5));

  auto unspecified = log.subscribe(subscribeOptions(3), [] {});
  EXPECT_FALSE(unspecified->start().incarnation_changed());
  EXPECT_THAT(drain(*unspecified), ElementsAre(4, 5));

  // A since_seq far beyond this run's latest does not hide this run's events.
  auto far = log.subscribe(subscribeOptions(1000, "run-a"), [] {});
  EXPECT_TRUE(far->start().incarnation_changed());
  EXPECT_THAT(drain(*far), ElementsAre(1, 2, 3, 4, 5));
}

TEST(EventLogTest, IncarnationChangedReportsEventsOfThisRunAlreadyDropped) {
  EventLogOptions options = testOptions();
  options.capacity = 3;
  EventLog log(options);
  for (int i = 0; i < 5; ++i) log.append(modified("WAIT", "a1"));
  auto subscription = log.subscribe(subscribeOptions(4, "run-a"), [] {});
  const v1::WatchEventsStart& start = subscription->start();
  EXPECT_TRUE(start.incarnation_changed());
  EXPECT_TRUE(start.events_dropped());
  EXPECT_EQ(start.dropped_count(), 2u);
  EXPECT_EQ(start.oldest_retained_seq(), 3u);
  EXPECT_THAT(drain(*subscription), ElementsAre(3, 4, 5));
}

TEST(EventLogTest, ReportsDroppedEventsAfterCapacityEviction) {
  EventLogOptions options = testOptions();
  options.capacity = 5;
  EventLog log(options);
  for (int i = 0; i < 8; ++i) log.append(activated("WAIT", std::to_string(i)));
  EXPECT_EQ(log.retainedCount(), 5u);
  EXPECT_EQ(log.latestSeq(), 8u);

  auto from0 = log.subscribe(subscribeOptions(0), [] {});
  EXPECT_TRUE(from0->start().events_dropped());
  EXPECT_EQ(from0->start().dropped_count(), 3u);
  EXPECT_EQ(from0->start().oldest_retained_seq(), 4u);
  EXPECT_EQ(from0->start().latest_seq(), 8u);
  EXPECT_THAT(drain(*from0), ElementsAre(4, 5, 6, 7, 8));

  auto from1 = log.subscribe(subscribeOptions(1), [] {});
  EXPECT_TRUE(from1->start().events_dropped());
  EXPECT_EQ(from1->start().dropped_count(), 2u);
  EXPECT_THAT(drain(*from1), ElementsAre(4, 5, 6, 7, 8));

  // since_seq + 1 == oldest retained: nothing lost.
  auto from3 = log.subscribe(subscribeOptions(3), [] {});
  EXPECT_FALSE(from3->start().events_dropped());
  EXPECT_EQ(from3->start().dropped_count(), 0u);
  EXPECT_THAT(drain(*from3), ElementsAre(4, 5, 6, 7, 8));

  auto from6 = log.subscribe(subscribeOptions(6), [] {});
  EXPECT_FALSE(from6->start().events_dropped());
  EXPECT_THAT(drain(*from6), ElementsAre(7, 8));
}

TEST(EventLogTest, ReportsDroppedWhenNothingIsRetained) {
  EventLogOptions options = testOptions();
  options.capacity = 0;
  EventLog log(options);
  for (int i = 0; i < 4; ++i) log.append(activated("WAIT", "a"));
  EXPECT_EQ(log.retainedCount(), 0u);

  auto subscription = log.subscribe(subscribeOptions(1), [] {});
  EXPECT_EQ(subscription->start().oldest_retained_seq(), 0u);
  EXPECT_EQ(subscription->start().latest_seq(), 4u);
  EXPECT_TRUE(subscription->start().events_dropped());
  EXPECT_EQ(subscription->start().dropped_count(), 3u);
  EXPECT_THAT(drain(*subscription), IsEmpty());

  auto caught_up = log.subscribe(subscribeOptions(4), [] {});
  EXPECT_FALSE(caught_up->start().events_dropped());

  // Live delivery does not depend on retention.
  log.append(activated("WAIT", "a"));
  EXPECT_THAT(drain(*subscription), ElementsAre(5));
  EXPECT_THAT(drain(*caught_up), ElementsAre(5));
}

TEST(EventLogTest, EventsWithoutActivationExpireAfterRetention) {
  FakeWallClock clock;
  EventLogOptions options = testOptions();
  options.retention = seconds(10);
  EventLog log(options);
  log.setWallClockForTesting(clock.fn());

  log.append(modified("WAIT", ""));  // 1, expires at 10 s
  clock.set(seconds(5));
  log.append(modified("WAIT", ""));  // 2, expires at 15 s
  clock.set(seconds(10) - nanoseconds(1));
  EXPECT_EQ(log.retainedCount(), 2u);
  clock.set(seconds(10));
  EXPECT_EQ(log.retainedCount(), 1u);

  auto subscription = log.subscribe({}, [] {});
  EXPECT_EQ(subscription->start().oldest_retained_seq(), 2u);
  EXPECT_EQ(subscription->start().dropped_count(), 1u);
  EXPECT_THAT(drain(*subscription), ElementsAre(2));

  clock.set(seconds(15));
  EXPECT_EQ(log.retainedCount(), 0u);
  auto late = log.subscribe({}, [] {});
  EXPECT_EQ(late->start().oldest_retained_seq(), 0u);
  EXPECT_EQ(late->start().latest_seq(), 2u);
  EXPECT_EQ(late->start().dropped_count(), 2u);
  EXPECT_THAT(drain(*late), IsEmpty());
}

TEST(EventLogTest, RetentionCountdownStartsOnlyWhenActivationFinishes) {
  FakeWallClock clock;
  EventLogOptions options = testOptions();
  options.retention = seconds(10);
  EventLog log(options);
  log.setWallClockForTesting(clock.fn());

  log.append(activated("WAIT", "a1"));  // 1
  clock.set(seconds(5));
  log.append(modified("WAIT", "a1"));  // 2
  // Long past the retention: the activation is still running, so it is kept.
  clock.set(seconds(100));
  log.append(activated("LAND", "b1"));  // 3
  EXPECT_EQ(log.retainedCount(), 3u);
  EXPECT_THAT(drain(*log.subscribe({}, [] {})), ElementsAre(1, 2, 3));

  log.append(finished("WAIT", "a1"));  // 4: 1, 2 and 4 expire at 110 s
  clock.set(seconds(110) - nanoseconds(1));
  EXPECT_EQ(log.retainedCount(), 4u);
  EXPECT_THAT(drain(*log.subscribe({}, [] {})), ElementsAre(1, 2, 3, 4));

  clock.set(seconds(110));
  EXPECT_EQ(log.retainedCount(), 2u);
  log.append(modified("LAND", "b1"));  // 5
  // 4 has expired but stays behind the running b1 activation's event 3, which
  // keeps the retained seqs consecutive.
  auto after_a1 = log.subscribe({}, [] {});
  EXPECT_EQ(after_a1->start().oldest_retained_seq(), 3u);
  EXPECT_EQ(after_a1->start().dropped_count(), 2u);
  EXPECT_THAT(drain(*after_a1), ElementsAre(3, 4, 5));

  clock.set(seconds(120));
  log.append(finished("LAND", "b1"));  // 6: 3, 5 and 6 expire at 130 s
  EXPECT_EQ(log.retainedCount(), 4u);
  clock.set(seconds(130));
  EXPECT_EQ(log.retainedCount(), 0u);
  auto after_b1 = log.subscribe(subscribeOptions(2), [] {});
  EXPECT_EQ(after_b1->start().oldest_retained_seq(), 0u);
  EXPECT_EQ(after_b1->start().latest_seq(), 6u);
  EXPECT_EQ(after_b1->start().dropped_count(), 4u);
  EXPECT_THAT(drain(*after_b1), IsEmpty());
}

TEST(EventLogTest, FinishedReleasesOnlyItsOwnBehaviorAndActivation) {
  FakeWallClock clock;
  EventLogOptions options = testOptions();
  options.retention = seconds(10);
  EventLog log(options);
  log.setWallClockForTesting(clock.fn());

  log.append(activated("WAIT", "x"));  // 1: same behavior, other activation
  log.append(activated("LAND", "a"));  // 2: same activation id, other behavior
  log.append(activated("WAIT", "a"));  // 3
  log.append(finished("WAIT", "a"));   // 4
  clock.set(seconds(1000));
  log.append(modified("WAIT", "x"));  // 5
  EXPECT_EQ(log.retainedCount(), 5u);

  log.append(finished("WAIT", "x"));  // 6: releases 1, 5, 6
  clock.set(seconds(1010));
  // 1 expires; 2 (LAND/a, still running) now heads the log.
  EXPECT_EQ(log.retainedCount(), 5u);
  auto subscription = log.subscribe({}, [] {});
  EXPECT_EQ(subscription->start().oldest_retained_seq(), 2u);
  EXPECT_THAT(drain(*subscription), ElementsAre(2, 3, 4, 5, 6));
}

TEST(EventLogTest, DuplicateFinishedDoesNotExtendRetention) {
  FakeWallClock clock;
  EventLogOptions options = testOptions();
  options.retention = seconds(10);
  EventLog log(options);
  log.setWallClockForTesting(clock.fn());

  log.append(activated("WAIT", "a"));  // 1
  log.append(finished("WAIT", "a"));   // 2: 1, 2 expire at 10 s
  clock.set(seconds(8));
  log.append(finished("WAIT", "a"));  // 3: expires at 18 s; 1, 2 unchanged
  clock.set(seconds(10));
  EXPECT_EQ(log.retainedCount(), 1u);
}

TEST(EventLogTest, CapacityEvictsEvenRunningActivations) {
  EventLogOptions options = testOptions();
  options.capacity = 2;
  EventLog log(options);
  log.append(activated("WAIT", "a"));
  log.append(activated("LAND", "b"));
  log.append(activated("TAKE_OFF", "c"));
  EXPECT_EQ(log.retainedCount(), 2u);
  EXPECT_THAT(drain(*log.subscribe({}, [] {})), ElementsAre(2, 3));
}

TEST(EventLogTest, WakesWhenQueueBecomesNonEmpty) {
  EventLog log(testOptions());
  int wakes = 0;
  auto subscription = log.subscribe({}, [&] { ++wakes; });
  log.append(modified("WAIT", "a"));
  log.append(modified("WAIT", "a"));
  log.append(modified("WAIT", "a"));
  EXPECT_EQ(wakes, 1);
  EXPECT_THAT(drain(*subscription), ElementsAre(1, 2, 3));
  log.append(modified("WAIT", "a"));
  EXPECT_EQ(wakes, 2);
}

TEST(EventLogTest, ReplayIsQueuedWithoutWake) {
  EventLog log(testOptions());
  log.append(modified("WAIT", "a"));
  log.append(modified("WAIT", "a"));
  int wakes = 0;
  auto subscription = log.subscribe({}, [&] { ++wakes; });
  EXPECT_EQ(wakes, 0);
  // Live events behind an undrained replay do not wake either: the reader is
  // expected to drain after subscribing.
  log.append(modified("WAIT", "a"));
  EXPECT_EQ(wakes, 0);
  EXPECT_THAT(drain(*subscription), ElementsAre(1, 2, 3));
  log.append(modified("WAIT", "a"));
  EXPECT_EQ(wakes, 1);
}

TEST(EventLogTest, WakeMayPopOnTheAppendingThread) {
  EventLog log(testOptions());
  std::vector<uint64_t> received;
  std::unique_ptr<EventSubscription> subscription;
  subscription = log.subscribe({}, [&] {
    while (EventPtr event = subscription->pop()) received.push_back(event->seq());
  });
  for (int i = 0; i < 5; ++i) log.append(modified("WAIT", "a"));
  EXPECT_THAT(received, ElementsAre(1, 2, 3, 4, 5));
}

TEST(EventLogTest, WakeMayAppendReentrantly) {
  EventLog log(testOptions());
  std::vector<uint64_t> received;
  std::unique_ptr<EventSubscription> subscription;
  subscription = log.subscribe({}, [&] {
    while (EventPtr event = subscription->pop()) {
      received.push_back(event->seq());
      if (log.latestSeq() < 4) log.append(modified("WAIT", "a"));
    }
  });
  log.append(modified("WAIT", "a"));
  EXPECT_THAT(received, ElementsAre(1, 2, 3, 4));
}

TEST(EventLogTest, OverflowMarksSlowSubscriberWhileOthersKeepReceiving) {
  EventLogOptions options = testOptions();
  options.subscriber_queue_limit = 3;
  EventLog log(options);

  int slow_wakes = 0;
  auto slow = log.subscribe({}, [&] { ++slow_wakes; });
  std::vector<uint64_t> fast_received;
  std::unique_ptr<EventSubscription> fast;
  fast = log.subscribe({}, [&] {
    while (EventPtr event = fast->pop()) fast_received.push_back(event->seq());
  });

  // The slow subscriber never pops; appending must not wait for it.
  for (int i = 0; i < 10; ++i) log.append(modified("WAIT", "a"));

  EXPECT_TRUE(slow->overflowed());
  EXPECT_EQ(slow_wakes, 2);  // empty -> non-empty, then the overflow
  EXPECT_FALSE(fast->overflowed());
  EXPECT_EQ(fast_received, range(1, 10));

  // What was queued before the overflow can still be drained.
  EXPECT_THAT(drain(*slow), ElementsAre(1, 2, 3));
  EXPECT_TRUE(slow->overflowed());
  EXPECT_EQ(slow->lastPoppedSeq(), 3u);
  log.append(modified("WAIT", "a"));  // 11
  EXPECT_EQ(slow->pop(), nullptr);
  EXPECT_EQ(slow_wakes, 2);

  // Resuming replays the rest, more than the queue limit: the replay does not
  // count against it.
  auto resumed = log.subscribe(subscribeOptions(slow->lastPoppedSeq()), [] {});
  EXPECT_FALSE(resumed->start().events_dropped());
  log.append(modified("WAIT", "a"));  // 12
  EXPECT_FALSE(resumed->overflowed());
  EXPECT_EQ(drain(*resumed), range(4, 12));
  EXPECT_EQ(fast_received, range(1, 12));
}

TEST(EventLogTest, QueueLimitCountsLiveEventsBehindReplay) {
  EventLogOptions options = testOptions();
  options.subscriber_queue_limit = 2;
  EventLog log(options);
  for (int i = 0; i < 5; ++i) log.append(modified("WAIT", "a"));
  auto subscription = log.subscribe({}, [] {});
  log.append(modified("WAIT", "a"));  // 6
  log.append(modified("WAIT", "a"));  // 7
  EXPECT_FALSE(subscription->overflowed());
  EXPECT_EQ(subscription->pop()->seq(), 1u);  // one replayed event fewer
  log.append(modified("WAIT", "a"));          // 8: still 2 live events queued
  EXPECT_TRUE(subscription->overflowed());
  EXPECT_EQ(drain(*subscription), range(2, 7));
}

TEST(EventLogTest, AppendNeverBlocksOnSubscriberThatDoesNotRead) {
  EventLogOptions options = testOptions();
  options.subscriber_queue_limit = 16;
  EventLog log(options);
  auto idle = log.subscribe({}, [] {});
  // A reader holding its subscription busy on another thread cannot stall
  // appends either.
  std::atomic<bool> stop{false};
  auto reader = log.subscribe({}, [] {});
  std::thread reading([&] {
    while (!stop) {
      reader->pop();
      reader->overflowed();
      reader->lastPoppedSeq();
    }
  });
  auto appending = std::async(std::launch::async, [&] {
    for (int i = 0; i < 100000; ++i) log.append(modified("WAIT", "a"));
  });
  EXPECT_EQ(appending.wait_for(std::chrono::seconds(30)), std::future_status::ready);
  stop = true;
  reading.join();
  EXPECT_TRUE(idle->overflowed());
  EXPECT_EQ(drain(*idle), range(1, 16));
  EXPECT_EQ(log.latestSeq(), 100000u);
}

// Subscribes repeatedly while another thread appends, and checks that every
// subscription sees consecutive seqs from since_seq + 1 (after the reported
// drops) to the end: nothing lost or duplicated between replay and live.
void checkReplayLiveHandoff(size_t capacity) {
  constexpr uint64_t kEvents = 10000;
  EventLogOptions options = testOptions();
  options.capacity = capacity;
  options.subscriber_queue_limit = 2 * kEvents;
  EventLog log(options);

  struct Subscriber {
    uint64_t since_seq;
    std::unique_ptr<EventSubscription> subscription;
    // Filled from the appender's thread by wake, which may run before
    // subscribe() returns, hence the atomic pointer.
    std::atomic<EventSubscription*> live{nullptr};
    std::vector<uint64_t> woken;
    bool draining_in_wake;
  };
  std::vector<std::unique_ptr<Subscriber>> subscribers;

  std::thread appender([&] {
    for (uint64_t i = 0; i < kEvents; ++i) {
      log.append(modified(i % 2 == 0 ? "WAIT" : "LAND", "a"));
      if (i % 64 == 0) std::this_thread::yield();
    }
  });
  // A bounded number of subscriptions spread over the run: each one costs
  // every later append a delivery.
  constexpr uint64_t kSubscriptions = 48;
  for (uint64_t round = 0; round < kSubscriptions; ++round) {
    while (log.latestSeq() < kEvents * round / kSubscriptions) std::this_thread::yield();
    auto subscriber = std::make_unique<Subscriber>();
    const uint64_t latest = log.latestSeq();
    switch (round % 4) {
      case 0:
        subscriber->since_seq = 0;
        break;
      case 1:
        subscriber->since_seq = latest;
        break;
      case 2:
        subscriber->since_seq = latest / 2;
        break;
      default:
        subscriber->since_seq = latest > 3 ? latest - 3 : 0;
        break;
    }
    subscriber->draining_in_wake = round % 2 == 0;
    Subscriber* raw = subscriber.get();
    std::function<void()> wake = [] {};
    if (raw->draining_in_wake) {
      wake = [raw] {
        if (EventSubscription* live = raw->live.load()) {
          while (EventPtr event = live->pop()) raw->woken.push_back(event->seq());
        }
      };
    }
    subscriber->subscription = log.subscribe(subscribeOptions(subscriber->since_seq), wake);
    // From here wake pops on the appender's thread; the rest is drained after
    // the appender finished, so the queue has one popper at a time.
    subscriber->live.store(subscriber->subscription.get());
    subscribers.push_back(std::move(subscriber));
  }
  appender.join();

  for (const auto& subscriber : subscribers) {
    const v1::WatchEventsStart& start = subscriber->subscription->start();
    ASSERT_FALSE(subscriber->subscription->overflowed());
    std::vector<uint64_t> seqs = subscriber->woken;
    for (uint64_t seq : drain(*subscriber->subscription)) seqs.push_back(seq);
    const uint64_t first = subscriber->since_seq + 1 + start.dropped_count();
    if (capacity >= kEvents) {
      EXPECT_FALSE(start.events_dropped());
    }
    ASSERT_EQ(seqs, range(first, kEvents))
        << "since_seq " << subscriber->since_seq << " oldest " << start.oldest_retained_seq()
        << " latest " << start.latest_seq();
  }
}

TEST(EventLogTest, NoGapOrDuplicateBetweenReplayAndLive) { checkReplayLiveHandoff(100000); }

TEST(EventLogTest, NoGapOrDuplicateBetweenReplayAndLiveWithEviction) { checkReplayLiveHandoff(50); }

TEST(EventLogTest, FilteredSubscriptionGetsExactlyItsBehaviorUnderConcurrentAppends) {
  constexpr int kEvents = 10000;
  EventLogOptions options = testOptions();
  options.capacity = kEvents;  // everything stays retained: the filter is under test
  EventLog log(options);
  std::thread appender([&] {
    for (int i = 0; i < kEvents; ++i) log.append(modified(i % 3 == 0 ? "WAIT" : "LAND", "a"));
  });
  while (log.latestSeq() < kEvents / 2) std::this_thread::yield();
  const uint64_t since = log.latestSeq() / 2;
  auto subscription = log.subscribe(subscribeOptions(since, "", {"WAIT"}), [] {});
  appender.join();
  std::vector<uint64_t> expected;
  for (uint64_t seq = since + 1; seq <= kEvents; ++seq) {
    if ((seq - 1) % 3 == 0) expected.push_back(seq);
  }
  EXPECT_EQ(drain(*subscription), expected);
}

TEST(EventLogTest, CancelStopsWake) {
  EventLog log(testOptions());
  int wakes = 0;
  auto subscription = log.subscribe({}, [&] { ++wakes; });
  log.append(modified("WAIT", "a"));
  EXPECT_EQ(wakes, 1);
  EXPECT_THAT(drain(*subscription), ElementsAre(1));
  subscription->cancel();
  log.append(modified("WAIT", "a"));
  EXPECT_EQ(wakes, 1);
  EXPECT_EQ(subscription->pop(), nullptr);
  subscription->cancel();  // idempotent
  subscription.reset();
  log.append(modified("WAIT", "a"));
}

TEST(EventLogTest, NoWakeAfterCancelReturnsUnderConcurrentAppends) {
  for (int attempt = 0; attempt < 20; ++attempt) {
    EventLog log(testOptions());
    std::atomic<bool> cancel_returned{false};
    std::atomic<int> wakes{0};
    std::atomic<int> late_wakes{0};
    std::atomic<EventSubscription*> live{nullptr};
    auto subscription = log.subscribe({}, [&] {
      if (cancel_returned) ++late_wakes;
      ++wakes;
      if (EventSubscription* s = live.load()) {
        while (s->pop()) {
        }
      }
    });
    live = subscription.get();
    std::atomic<bool> stop{false};
    std::thread appender([&] {
      while (!stop) log.append(modified("WAIT", "a"));
    });
    while (wakes < 10) std::this_thread::yield();
    subscription->cancel();
    cancel_returned = true;
    const uint64_t seq_at_cancel = log.latestSeq();
    while (log.latestSeq() < seq_at_cancel + 100) std::this_thread::yield();
    stop = true;
    appender.join();
    EXPECT_EQ(late_wakes, 0);
  }
}

TEST(EventLogTest, CancelWaitsForWakeRunningOnAnotherThread) {
  EventLog log(testOptions());
  std::atomic<bool> in_wake{false};
  std::atomic<bool> release{false};
  auto subscription = log.subscribe({}, [&] {
    in_wake = true;
    while (!release) std::this_thread::yield();
  });
  std::thread appender([&] { log.append(modified("WAIT", "a")); });
  while (!in_wake) std::this_thread::yield();

  std::atomic<bool> cancelled{false};
  std::thread canceller([&] {
    subscription->cancel();
    cancelled = true;
  });
  std::this_thread::sleep_for(std::chrono::milliseconds(50));
  EXPECT_FALSE(cancelled);  // the wake is still running
  release = true;
  canceller.join();
  appender.join();
  EXPECT_TRUE(cancelled);
}

TEST(EventLogTest, WakeMayCancelItsOwnSubscription) {
  EventLog log(testOptions());
  int wakes = 0;
  std::unique_ptr<EventSubscription> subscription;
  subscription = log.subscribe({}, [&] {
    ++wakes;
    subscription->cancel();
  });
  log.append(modified("WAIT", "a"));
  EXPECT_THAT(drain(*subscription), ElementsAre(1));
  log.append(modified("WAIT", "a"));
  EXPECT_EQ(wakes, 1);
}

TEST(EventLogTest, WakeMayDestroyItsOwnSubscription) {
  EventLog log(testOptions());
  int wakes = 0;
  std::unique_ptr<EventSubscription> subscription;
  auto other = log.subscribe({}, [] {});
  subscription = log.subscribe({}, [&] {
    ++wakes;
    subscription.reset();
  });
  log.append(modified("WAIT", "a"));
  EXPECT_EQ(subscription, nullptr);
  log.append(modified("WAIT", "a"));
  EXPECT_EQ(wakes, 1);
  EXPECT_THAT(drain(*other), ElementsAre(1, 2));
}

TEST(EventLogTest, DestroyingSubscriptionUnsubscribes) {
  EventLog log(testOptions());
  int wakes = 0;
  auto kept = log.subscribe({}, [] {});
  auto dropped = log.subscribe({}, [&] { ++wakes; });
  dropped.reset();
  log.append(modified("WAIT", "a"));
  EXPECT_EQ(wakes, 0);
  EXPECT_THAT(drain(*kept), ElementsAre(1));
}

TEST(EventLogTest, DestroyingLogWithLiveSubscriptionIsSafe) {
  auto log = std::make_unique<EventLog>(testOptions());
  int wakes = 0;
  auto cancelled_later = log->subscribe({}, [&] { ++wakes; });
  auto destroyed_later = log->subscribe({}, [&] { ++wakes; });
  log->append(modified("WAIT", "a"));
  log->append(modified("WAIT", "a"));
  log.reset();

  // Queued events survive the log.
  EXPECT_THAT(drain(*cancelled_later), ElementsAre(1, 2));
  EXPECT_FALSE(cancelled_later->overflowed());
  EXPECT_EQ(cancelled_later->start().incarnation(), "run-b");
  cancelled_later->cancel();
  cancelled_later.reset();
  destroyed_later.reset();
  EXPECT_EQ(wakes, 2);
}

}  // namespace
}  // namespace behaviorlib
