#include "basic_quadrotor_behaviors/wait_behavior.h"

#include <cstdio>

namespace behaviorlib::basic {

Verdict WaitBehavior::checkGoal() {
  const auto wanted = seconds(parameters().duration_s());
  if (activeTime() >= wanted) {
    char message[64];
    std::snprintf(message, sizeof(message), "waited %g s", parameters().duration_s());
    return Verdict::finish(message);
  }
  return Verdict::keepGoing();
}

}  // namespace behaviorlib::basic
