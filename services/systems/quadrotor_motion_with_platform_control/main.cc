// quadrotor_motion_with_platform_control: the paper's behavior system of motion
// through the platform's own control levels: MOVE_VERTICAL_WITH_PLATFORM_CONTROL,
// MOVE_AT_SPEED_WITH_PLATFORM_CONTROL and ROTATE_WITH_PLATFORM_CONTROL command
// the FlightController (--flight-controller) directly, holding its lease, and
// read the pose estimate from --channel. Run with --clock sim under the
// simulator.

#include "behaviorlib/flight_common/remote_vehicle.h"
#include "behaviorlib/quadrotor_motion_with_platform_control/platform_behaviors.h"
#include "behaviorlib/server/behavior_system_main.h"
#include "behaviorlib/v1/behaviors/quadrotor_motion_with_platform_control.behaviors.h"

int main(int argc, char** argv) {
  using behaviorlib::server::BehaviorSystemBuilder;
  namespace pm = behaviorlib::platform_motion;
  namespace v1 = behaviorlib::v1;
  return behaviorlib::server::runBehaviorSystem(
      argc, argv, "quadrotor_motion_with_platform_control", [](BehaviorSystemBuilder& builder) {
        auto& vehicle =
            builder.own(std::make_unique<behaviorlib::flight::RemoteVehicle>(builder.context()));
        builder.add<pm::MoveVerticalBehavior>(vehicle);
        builder.add<pm::MoveAtSpeedBehavior>(vehicle);
        builder.add<pm::RotateWithPlatformControlBehavior>(vehicle);
      });
}
