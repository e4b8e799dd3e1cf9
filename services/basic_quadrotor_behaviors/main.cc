// basic_quadrotor_behaviors: the paper's behavior system of basic quadrotor
// behaviors. For now it hosts WAIT; TAKE_OFF, LAND, HOVER and the localization
// behaviors join it with the flight behaviors.

#include "basic_quadrotor_behaviors/wait_behavior.h"
#include "behaviorlib/server/behavior_system_main.h"
#include "behaviorlib/v1/behaviors/basic_quadrotor_behaviors.grpc.pb.h"

int main(int argc, char** argv) {
  using behaviorlib::server::BehaviorSystemBuilder;
  return behaviorlib::server::runBehaviorSystem(
      argc, argv, "basic_quadrotor_behaviors", [](BehaviorSystemBuilder& builder) {
        builder.add<behaviorlib::basic::WaitBehavior, behaviorlib::v1::Wait>();
      });
}
