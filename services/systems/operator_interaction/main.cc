// operator_interaction: the behavior system of INFORM_OPERATOR and
// REQUEST_OPERATOR_ASSISTANCE.

#include <chrono>
#include <memory>

#include "behaviorlib/operator_interaction/inform_operator_behavior.h"
#include "behaviorlib/operator_interaction/request_assistance_behavior.h"
#include "behaviorlib/server/behavior_system_main.h"
#include "behaviorlib/v1/behaviors/operator_interaction.behaviors.h"

int main(int argc, char** argv) {
  using behaviorlib::server::BeliefClient;
  return behaviorlib::server::runBehaviorSystem(
      argc, argv, "operator_interaction", [](behaviorlib::server::BehaviorSystemBuilder& b) {
        // Its own client with a short deadline: calls made from the
        // behaviors' worker stay well inside their watchdog.
        const BeliefClient* beliefs =
            b.context().beliefs
                ? &b.own(std::make_unique<BeliefClient>(b.context().beliefs->address(),
                                                        std::chrono::milliseconds(500)))
                : nullptr;
        b.add<behaviorlib::operator_interaction::InformOperatorBehavior>(beliefs,
                                                                         b.context().channel);
        b.add<behaviorlib::operator_interaction::RequestOperatorAssistanceBehavior>(beliefs);
      });
}
