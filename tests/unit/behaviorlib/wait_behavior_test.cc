#include "behaviorlib/basic_quadrotor_behaviors/wait_behavior.h"

#include <gtest/gtest.h>

#include "behaviorlib/behavior_host.h"
#include "test_behaviors.h"

namespace behaviorlib {
namespace {

using std::chrono::milliseconds;
using testing::EventCollector;
using testing::eventually;
using testing::waitParams;

class WaitBehaviorTest : public ::testing::Test {
 protected:
  void SetUp() override {
    host_.add(std::make_unique<basic::WaitBehavior>());
    ASSERT_TRUE(host_.start().ok());
    wait_ = host_.find("WAIT");
  }
  FakeClock clock_;
  BehaviorHost host_{testing::hostOptions("drone1", "basic_quadrotor_behaviors"), clock_};
  EventCollector events_{host_.events()};
  BehaviorExecutionManager* wait_ = nullptr;
};

TEST_F(WaitBehaviorTest, FinishesGoalAchievedWhenDurationElapsesOnTheBehaviorClock) {
  ASSERT_TRUE(wait_->activateAndWait(waitParams(2.0)).ok());
  clock_.advance(milliseconds(1990));
  std::this_thread::sleep_for(milliseconds(20));
  EXPECT_EQ(wait_->state(), v1::BEHAVIOR_STATE_ACTIVE);
  clock_.advance(milliseconds(20));
  const auto finished = events_.waitFinished();
  ASSERT_TRUE(finished.has_finished());
  EXPECT_EQ(finished.finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED);
  EXPECT_EQ(finished.behavior(), "WAIT");
}

TEST_F(WaitBehaviorTest, ZeroDurationFinishesOnTheFirstTick) {
  ASSERT_TRUE(wait_->activateAndWait(waitParams(0.0)).ok());
  EXPECT_EQ(events_.waitFinished().finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED);
}

TEST_F(WaitBehaviorTest, PausedTimeDoesNotCountAndModifyExtendsTheWait) {
  ASSERT_TRUE(wait_->activateAndWait(waitParams(1.0)).ok());
  clock_.advance(milliseconds(500));
  ASSERT_TRUE(wait_->pauseAndWait().ok());
  clock_.advance(milliseconds(5000));
  ASSERT_TRUE(wait_->resumeAndWait().ok());
  ASSERT_TRUE(wait_->modifyAndWait(waitParams(2.0)).ok());
  clock_.advance(milliseconds(1000));
  std::this_thread::sleep_for(milliseconds(20));
  EXPECT_EQ(wait_->state(), v1::BEHAVIOR_STATE_ACTIVE) << "1.5 s of 2 s waited";
  clock_.advance(milliseconds(600));
  const auto finished = events_.waitFinished();
  EXPECT_EQ(finished.finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED);
}

}  // namespace
}  // namespace behaviorlib
