// The console's live feed without a server: the cursor that resumes the
// coordinator's event stream without gaps or duplicates, and the hub that
// broadcasts to browsers and replays for Last-Event-ID.

#include <gtest/gtest.h>

#include <chrono>
#include <string>
#include <thread>
#include <vector>

#include "behaviorlib/console/event_hub.h"
#include "behaviorlib/follower/event_cursor.h"

namespace behaviorlib::console {
namespace {

using follower::EventCursor;
using std::chrono::milliseconds;

v1::WatchFleetEventsResponse start(const std::string& incarnation) {
  v1::WatchFleetEventsResponse response;
  response.mutable_start()->set_incarnation(incarnation);
  return response;
}

// A behavior event relayed by a coordinator: the coordinator's (incarnation,
// seq) around the system's own.
v1::FleetEvent event(const std::string& coordinator, uint64_t seq, const std::string& system,
                     uint64_t system_seq) {
  v1::FleetEvent e;
  e.set_incarnation(coordinator);
  e.set_seq(seq);
  e.mutable_behavior_event()->set_incarnation(system);
  e.mutable_behavior_event()->set_seq(system_seq);
  e.mutable_behavior_event()->set_activation_id("a" + std::to_string(system_seq));
  return e;
}

v1::WatchFleetEventsResponse batch(std::initializer_list<v1::FleetEvent> events) {
  v1::WatchFleetEventsResponse response;
  for (const auto& e : events) *response.mutable_events()->add_events() = e;
  return response;
}

TEST(EventCursor, ResumesAfterTheLastSeqOfTheSameIncarnation) {
  EventCursor cursor;
  EXPECT_EQ(cursor.request().since_seq(), 0u);
  EXPECT_TRUE(cursor.accept(start("c1")).empty());
  EXPECT_EQ(cursor.accept(batch({event("c1", 1, "s1", 1), event("c1", 2, "s1", 2)})).size(), 2u);
  const auto request = cursor.request();
  EXPECT_EQ(request.since_seq(), 2u);
  EXPECT_EQ(request.incarnation(), "c1");
  EXPECT_GT(request.max_events_per_message(), 1u);
  EXPECT_EQ(cursor.restartsSeen(), 0u);
}

TEST(EventCursor, ARestartedCoordinatorsReplayIsNotDeliveredTwice) {
  EventCursor cursor;
  cursor.accept(start("c1"));
  cursor.accept(batch({event("c1", 1, "s1", 1), event("c1", 2, "s1", 2)}));
  // The restarted coordinator replays what it read again from the system,
  // under its own new seqs, then a new event.
  cursor.accept(start("c2"));
  EXPECT_EQ(cursor.restartsSeen(), 1u);
  const auto fresh = cursor.accept(
      batch({event("c2", 1, "s1", 1), event("c2", 2, "s1", 2), event("c2", 3, "s1", 3)}));
  ASSERT_EQ(fresh.size(), 1u);
  EXPECT_EQ(fresh[0].behavior_event().seq(), 3u);
  EXPECT_EQ(cursor.request().since_seq(), 3u);
  EXPECT_EQ(cursor.request().incarnation(), "c2");
}

TEST(EventCursor, SynthesizedEventsAreRecognisedByTheirActivation) {
  EventCursor cursor;
  auto synthesized = event("c1", 5, "s1", 0);
  synthesized.set_synthesized(true);
  EXPECT_EQ(cursor.accept(batch({synthesized})).size(), 1u);
  synthesized.set_seq(9);
  EXPECT_TRUE(cursor.accept(batch({synthesized})).empty());
  // A system state change has no identity: always delivered.
  v1::FleetEvent change;
  change.set_seq(10);
  change.mutable_system_state_changed()->mutable_system()->set_system("s1");
  v1::WatchFleetEventsResponse single;
  *single.mutable_event() = change;
  EXPECT_EQ(cursor.accept(single).size(), 1u);
  EXPECT_EQ(cursor.accept(single).size(), 1u);
}

TEST(EventCursor, RemembersABoundedNumberOfEvents) {
  EventCursor cursor;
  for (uint64_t i = 1; i <= EventCursor::kRemembered + 10; ++i) {
    cursor.accept(batch({event("c1", i, "s1", i)}));
  }
  // The oldest are forgotten (and would be delivered again), the newest not.
  EXPECT_EQ(cursor.accept(batch({event("c2", 1, "s1", 1)})).size(), 1u);
  EXPECT_TRUE(cursor.accept(batch({event("c2", 2, "s1", EventCursor::kRemembered + 10)})).empty());
}

TEST(EventHub, KeepsTheLastMessagesForThoseWhoReconnect) {
  EventHub hub(3);
  for (int i = 1; i <= 5; ++i) EXPECT_EQ(hub.publish("fleet", std::to_string(i)), uint64_t(i));
  auto all = hub.after(0, milliseconds(0));
  ASSERT_EQ(all.size(), 3u);
  EXPECT_EQ(all.front().id, 3u);
  EXPECT_EQ(all.back().data, "5");
  auto missed = hub.after(4, milliseconds(0));
  ASSERT_EQ(missed.size(), 1u);
  EXPECT_EQ(missed[0].id, 5u);
  EXPECT_TRUE(hub.after(5, milliseconds(0)).empty());
  EXPECT_EQ(EventHub::format(missed[0]), "id: 5\nevent: fleet\ndata: 5\n\n");
}

TEST(EventHub, StatesKeepTheirLatestMessageAndNeverPushEventsOut) {
  EventHub hub(2);
  hub.publish("fleet", "a");
  for (int i = 0; i < 100; ++i) hub.publishLatest("robots/d1/pose", "vehicle", std::to_string(i));
  hub.publishLatest("gateway", "gateway", "up");
  hub.publish("fleet", "b");
  const auto all = hub.after(0, milliseconds(0));
  ASSERT_EQ(all.size(), 4u);
  EXPECT_EQ(all[0].data, "a");
  EXPECT_EQ(all[1].data, "99");
  EXPECT_EQ(all[2].data, "up");
  EXPECT_EQ(all[3].data, "b");
  // In id order, and a state older than the resume point is not sent again.
  const auto resumed = hub.after(all[2].id, milliseconds(0));
  ASSERT_EQ(resumed.size(), 1u);
  EXPECT_EQ(resumed[0].data, "b");
}

TEST(EventHub, KeepsABoundedNumberOfStatesTheOldestGoingFirst) {
  EventHub hub(10, 2);
  hub.publishLatest("a", "belief", "1");
  hub.publishLatest("b", "belief", "2");
  hub.publishLatest("a", "belief", "3");  // a is now the newest
  hub.publishLatest("c", "belief", "4");  // b goes
  std::vector<std::string> kept;
  for (const auto& m : hub.after(0, milliseconds(0))) kept.push_back(m.data);
  EXPECT_EQ(kept, (std::vector<std::string>{"3", "4"}));
}

TEST(EventHub, AWaiterWakesForANewMessageAndForClose) {
  EventHub hub(10);
  std::thread publisher([&] { hub.publish("mission", "{}"); });
  // Waits as long as it takes (an hour), never a measure of speed.
  const auto got = hub.after(0, std::chrono::hours(1));
  publisher.join();
  ASSERT_EQ(got.size(), 1u);
  EXPECT_EQ(got[0].event, "mission");
  std::thread closer([&] { hub.close(); });
  EXPECT_TRUE(hub.after(1, std::chrono::hours(1)).empty());
  closer.join();
  EXPECT_TRUE(hub.closed());
}

}  // namespace
}  // namespace behaviorlib::console
