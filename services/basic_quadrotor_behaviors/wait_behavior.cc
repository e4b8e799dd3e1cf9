#include "basic_quadrotor_behaviors/wait_behavior.h"

#include <cmath>

namespace behaviorlib::basic {

Verdict WaitBehavior::checkGoal() {
  const auto wanted = std::chrono::duration_cast<Duration>(
      std::chrono::duration<double>(parameters().duration_s()));
  if (activeTime() >= wanted) {
    return Verdict::finish("waited " + std::to_string(parameters().duration_s()) + " s");
  }
  return Verdict::keepGoing();
}

}  // namespace behaviorlib::basic
