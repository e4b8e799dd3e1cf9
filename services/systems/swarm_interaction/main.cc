// swarm_interaction: the behavior system of INFORM_ROBOTS,
// INFORM_POSITION_TO_ROBOTS and PAY_ATTENTION_TO_ROBOT_MESSAGES.

#include <chrono>
#include <memory>

#include "behaviorlib/server/behavior_system_main.h"
#include "behaviorlib/swarm_interaction/inform_position_behavior.h"
#include "behaviorlib/swarm_interaction/inform_robots_behavior.h"
#include "behaviorlib/swarm_interaction/pay_attention_behavior.h"
#include "behaviorlib/v1/behaviors/swarm_interaction.behaviors.h"

int main(int argc, char** argv) {
  using behaviorlib::server::BeliefClient;
  return behaviorlib::server::runBehaviorSystem(
      argc, argv, "swarm_interaction", [](behaviorlib::server::BehaviorSystemBuilder& b) {
        auto* channel = b.context().channel;
        // Its own client with a short deadline: a writer thread waits on it,
        // and a coordinator that does not answer must not hold up stopping.
        const BeliefClient* beliefs =
            b.context().beliefs
                ? &b.own(std::make_unique<BeliefClient>(b.context().beliefs->address(),
                                                        std::chrono::milliseconds(500)))
                : nullptr;
        b.add<behaviorlib::swarm::InformRobotsBehavior>(channel);
        b.add<behaviorlib::swarm::InformPositionToRobotsBehavior>(channel);
        b.add<behaviorlib::swarm::PayAttentionToRobotMessagesBehavior>(channel, beliefs);
      });
}
