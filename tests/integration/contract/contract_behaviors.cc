// contract_behaviors: the C++ system of the lifecycle contract suite
// (behavior_system_test), hosting WAIT and CONTRACT_PROBE. Its twin in
// Python, contract_behaviors.py, hosts the same two behaviors; the suite runs
// against both. Flags as every behavior system's (run with --help).

#include "behaviorlib/basic_quadrotor_behaviors/wait_behavior.h"
#include "behaviorlib/server/behavior_system_main.h"
#include "behaviorlib/tests/v1/contract_probe.behaviors.h"
#include "behaviorlib/v1/behaviors/basic_quadrotor_behaviors.behaviors.h"
#include "contract_probe_behavior.h"

int main(int argc, char** argv) {
  return behaviorlib::server::runBehaviorSystem(
      argc, argv, "contract_behaviors", [](behaviorlib::server::BehaviorSystemBuilder& builder) {
        builder.add<behaviorlib::basic::WaitBehavior>();
        builder.add<behaviorlib::contract::ContractProbeBehavior>();
      });
}
