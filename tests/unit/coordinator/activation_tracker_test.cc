// Following one system's event stream: duplicates after a resume are dropped,
// every activation ends with exactly one finished event, restarts and outages
// end what was running with PROCESS_FAILURE.

#include "coordinator/events/activation_tracker.h"

#include <gtest/gtest.h>

#include <string>
#include <vector>

namespace behaviorlib::coordinator {
namespace {

using Verdict = ActivationTracker::Verdict;

class ActivationTrackerTest : public ::testing::Test {
 protected:
  v1::BehaviorEvent event(uint64_t seq, const std::string& behavior, const std::string& id,
                          v1::BehaviorEvent::KindCase kind,
                          const std::string& incarnation = "inc-1") {
    v1::BehaviorEvent e;
    e.set_seq(seq);
    e.set_incarnation(incarnation);
    e.set_robot_id("drone1");
    e.set_system("basic");
    e.set_behavior(behavior);
    e.set_activation_id(id);
    switch (kind) {
      case v1::BehaviorEvent::kActivated:
        (*e.mutable_activated()->mutable_parameters()->mutable_fields())["duration_s"]
            .set_number_value(30);
        break;
      case v1::BehaviorEvent::kFinished:
        e.mutable_finished()->set_cause(v1::TERMINATION_CAUSE_GOAL_ACHIEVED);
        break;
      case v1::BehaviorEvent::kPaused:
        e.mutable_paused();
        break;
      case v1::BehaviorEvent::kResumed:
        e.mutable_resumed();
        break;
      default:
        break;
    }
    return e;
  }

  ActivationTracker tracker_{"drone1", "basic"};
  const std::chrono::system_clock::time_point now_{std::chrono::hours(1000)};
};

TEST_F(ActivationTrackerTest, DropsWhatAResumedStreamReplaysAgain) {
  tracker_.startIncarnation("inc-1");
  EXPECT_EQ(tracker_.accept(event(1, "WAIT", "a1", v1::BehaviorEvent::kActivated)),
            Verdict::kForward);
  EXPECT_EQ(tracker_.accept(event(2, "WAIT", "a1", v1::BehaviorEvent::kFinished)),
            Verdict::kForward);
  EXPECT_EQ(tracker_.lastSeq(), 2u);
  // The stream resumed from an older point: 1 and 2 come again.
  EXPECT_EQ(tracker_.accept(event(1, "WAIT", "a1", v1::BehaviorEvent::kActivated)),
            Verdict::kDuplicate);
  EXPECT_EQ(tracker_.accept(event(2, "WAIT", "a1", v1::BehaviorEvent::kFinished)),
            Verdict::kDuplicate);
  EXPECT_EQ(tracker_.accept(event(3, "WAIT", "a2", v1::BehaviorEvent::kActivated)),
            Verdict::kForward);
  // An event of another run is never taken for one of this run.
  EXPECT_EQ(tracker_.accept(event(4, "WAIT", "x", v1::BehaviorEvent::kActivated, "inc-0")),
            Verdict::kDuplicate);
  EXPECT_EQ(tracker_.lastSeq(), 3u);
}

TEST_F(ActivationTrackerTest, TracksActivePausedAndFinishedActivations) {
  tracker_.startIncarnation("inc-1");
  tracker_.accept(event(1, "WAIT", "a1", v1::BehaviorEvent::kActivated));
  tracker_.accept(event(2, "HOVER", "h1", v1::BehaviorEvent::kActivated));
  tracker_.accept(event(3, "WAIT", "a1", v1::BehaviorEvent::kPaused));
  ASSERT_EQ(tracker_.active().size(), 2u);
  EXPECT_EQ(tracker_.active().at("WAIT").state, v1::BEHAVIOR_STATE_PAUSED);
  EXPECT_EQ(tracker_.active().at("WAIT").activation_id, "a1");
  tracker_.accept(event(4, "WAIT", "a1", v1::BehaviorEvent::kResumed));
  EXPECT_EQ(tracker_.active().at("WAIT").state, v1::BEHAVIOR_STATE_ACTIVE);
  // A finished event of an older activation does not end the current one.
  tracker_.accept(event(5, "HOVER", "h0", v1::BehaviorEvent::kFinished));
  EXPECT_TRUE(tracker_.active().contains("HOVER"));
  tracker_.accept(event(6, "HOVER", "h1", v1::BehaviorEvent::kFinished));
  EXPECT_FALSE(tracker_.active().contains("HOVER"));
  EXPECT_TRUE(tracker_.active().contains("WAIT"));
}

TEST_F(ActivationTrackerTest, FinishAllEndsEachActivationOnceWithProcessFailure) {
  tracker_.startIncarnation("inc-1");
  tracker_.accept(event(1, "WAIT", "a1", v1::BehaviorEvent::kActivated));
  tracker_.accept(event(2, "HOVER", "h1", v1::BehaviorEvent::kActivated));
  tracker_.accept(event(3, "HOVER", "h1", v1::BehaviorEvent::kFinished));

  auto finished = tracker_.finishAll("system basic of robot drone1 is down", now_, false);
  ASSERT_EQ(finished.size(), 1u) << "HOVER had already finished";
  const auto& e = finished[0];
  EXPECT_EQ(e.behavior(), "WAIT");
  EXPECT_EQ(e.activation_id(), "a1");
  EXPECT_EQ(e.incarnation(), "inc-1");
  EXPECT_EQ(e.robot_id(), "drone1");
  EXPECT_EQ(e.system(), "basic");
  EXPECT_EQ(e.seq(), 0u) << "not numbered by the system";
  ASSERT_TRUE(e.has_finished());
  EXPECT_EQ(e.finished().cause(), v1::TERMINATION_CAUSE_PROCESS_FAILURE);
  EXPECT_EQ(e.finished().message(), "system basic of robot drone1 is down");
  EXPECT_EQ(e.finished().parameters().fields().at("duration_s").number_value(), 30);
  EXPECT_EQ(e.wall_time().seconds(), 1000 * 3600);
  EXPECT_TRUE(tracker_.active().empty());
  EXPECT_TRUE(tracker_.finishAll("again", now_, false).empty()) << "only once";
}

TEST_F(ActivationTrackerTest, ANewIncarnationStartsAfresh) {
  tracker_.startIncarnation("inc-1");
  tracker_.accept(event(7, "WAIT", "a1", v1::BehaviorEvent::kActivated));
  auto ended = tracker_.finishAll("restarted", now_, false);
  ASSERT_EQ(ended.size(), 1u);
  tracker_.startIncarnation("inc-2");
  EXPECT_EQ(tracker_.incarnation(), "inc-2");
  EXPECT_EQ(tracker_.lastSeq(), 0u);
  EXPECT_TRUE(tracker_.active().empty());
  // The new run numbers from 1 again; its events are new.
  EXPECT_EQ(tracker_.accept(event(1, "WAIT", "b1", v1::BehaviorEvent::kActivated, "inc-2")),
            Verdict::kForward);
  EXPECT_EQ(tracker_.active().at("WAIT").activation_id, "b1");
}

TEST_F(ActivationTrackerTest, FencedActivationsGetNoSecondFinishedEvent) {
  tracker_.startIncarnation("inc-1");
  tracker_.accept(event(1, "WAIT", "a1", v1::BehaviorEvent::kActivated));
  tracker_.accept(event(2, "HOVER", "h1", v1::BehaviorEvent::kActivated));
  // Declared down: both reported finished by the coordinator.
  ASSERT_EQ(tracker_.finishAll("down", now_, /*fence=*/true).size(), 2u);
  ASSERT_EQ(tracker_.fencedStillRunning().size(), 2u);

  // The same run comes back: its replay shows WAIT finished during the outage.
  tracker_.startIncarnation("inc-1");
  EXPECT_EQ(tracker_.lastSeq(), 2u) << "same run: resume point kept";
  EXPECT_EQ(tracker_.accept(event(3, "WAIT", "a1", v1::BehaviorEvent::kPaused)), Verdict::kFenced);
  EXPECT_EQ(tracker_.accept(event(4, "WAIT", "a1", v1::BehaviorEvent::kFinished)),
            Verdict::kFenced);
  // HOVER is still running there: it must be deactivated.
  auto running = tracker_.fencedStillRunning();
  ASSERT_EQ(running.size(), 1u);
  EXPECT_EQ(running[0].behavior, "HOVER");
  EXPECT_EQ(running[0].activation_id, "h1");
  EXPECT_TRUE(tracker_.active().empty());
  // Its INTERRUPTED event after the deactivation is dropped too.
  EXPECT_EQ(tracker_.accept(event(5, "HOVER", "h1", v1::BehaviorEvent::kFinished)),
            Verdict::kFenced);
  EXPECT_TRUE(tracker_.fencedStillRunning().empty());
  // A new activation of the same behavior is followed normally.
  EXPECT_EQ(tracker_.accept(event(6, "HOVER", "h2", v1::BehaviorEvent::kActivated)),
            Verdict::kForward);
  EXPECT_EQ(tracker_.active().at("HOVER").activation_id, "h2");
}

}  // namespace
}  // namespace behaviorlib::coordinator
