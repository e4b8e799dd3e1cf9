// greeter: a behavior system of two behaviors, built against an installed
// behaviorlib. Flags as every behavior system's (--robot-id, --listen,
// --coordinator, ...; run with --help).

#include "acme/v1/greeter.behaviors.h"
#include "behaviorlib/server/behavior_system_main.h"
#include "greeter_behaviors.h"

int main(int argc, char** argv) {
  return behaviorlib::server::runBehaviorSystem(
      argc, argv, "greeter", [](behaviorlib::server::BehaviorSystemBuilder& builder) {
        builder.add<acme::SayHelloBehavior>();
        builder.add<acme::KeepCountingBehavior>();
      });
}
