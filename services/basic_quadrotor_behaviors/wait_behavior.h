#pragma once

// WAIT: stays active for duration_s seconds of the behavior's clock, then
// finishes with GOAL_ACHIEVED. Paused time does not count; Modify may change
// duration_s while it waits (time already waited still counts).

#include "behaviorlib/behavior_execution_manager.h"
#include "behaviorlib/v1/behaviors/basic_quadrotor_behaviors.pb.h"

namespace behaviorlib::basic {

class WaitBehavior final : public Behavior<v1::WaitParameters> {
 public:
  WaitBehavior() : Behavior("WAIT") {}

 protected:
  Verdict checkGoal() override;
};

}  // namespace behaviorlib::basic
