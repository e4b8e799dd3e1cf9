#pragma once

// WAIT: stays active for duration_s seconds of the behavior's clock, then
// finishes with GOAL_ACHIEVED. Paused time does not count; Modify may change
// duration_s while it waits (time already waited still counts).

#include "absl/strings/str_cat.h"
#include "behaviorlib/behavior_execution_manager.h"
#include "behaviorlib/v1/behaviors/basic_quadrotor_behaviors.pb.h"

namespace behaviorlib::basic {

class WaitBehavior final : public Behavior<v1::WaitParameters> {
 protected:
  Verdict checkGoal() override {
    if (activeTime() < seconds(parameters().duration_s())) return Verdict::keepGoing();
    return Verdict::finish(absl::StrCat("waited ", parameters().duration_s(), " s"));
  }
};

}  // namespace behaviorlib::basic
