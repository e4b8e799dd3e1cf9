// basic_quadrotor_behaviors: the paper's behavior system of basic quadrotor
// behaviors: WAIT, TAKE_OFF, LAND, HOVER_WITH_FLIGHT_ACTION_CONTROL and the
// self-localization behaviors SELF_LOCALIZE_WITH_GROUND_TRUTH,
// ESTIMATE_POSITION_WITH_SENSOR and ESTIMATE_POSITION_WITH_LINEAR_SPEED. The
// flight behaviors command the platform through --flight-controller and read
// the pose estimate from --channel (topics in topics.h); run with --clock sim
// under the simulator.

#include "behaviorlib/basic_quadrotor_behaviors/estimate_with_linear_speed_behavior.h"
#include "behaviorlib/basic_quadrotor_behaviors/estimate_with_sensor_behavior.h"
#include "behaviorlib/basic_quadrotor_behaviors/hover_with_flight_action_behavior.h"
#include "behaviorlib/basic_quadrotor_behaviors/land_behavior.h"
#include "behaviorlib/basic_quadrotor_behaviors/self_localize_behavior.h"
#include "behaviorlib/basic_quadrotor_behaviors/take_off_behavior.h"
#include "behaviorlib/basic_quadrotor_behaviors/wait_behavior.h"
#include "behaviorlib/flight_common/remote_vehicle.h"
#include "behaviorlib/server/behavior_system_main.h"
#include "behaviorlib/v1/behaviors/basic_quadrotor_behaviors.behaviors.h"

int main(int argc, char** argv) {
  using behaviorlib::server::BehaviorSystemBuilder;
  namespace basic = behaviorlib::basic;
  namespace flight = behaviorlib::flight;
  namespace v1 = behaviorlib::v1;
  return behaviorlib::server::runBehaviorSystem(
      argc, argv, "basic_quadrotor_behaviors", [](BehaviorSystemBuilder& builder) {
        auto& vehicle = builder.own(std::make_unique<flight::RemoteVehicle>(builder.context()));
        builder.add<basic::WaitBehavior>();
        builder.add<basic::TakeOffBehavior>(vehicle);
        builder.add<basic::LandBehavior>(vehicle);
        builder.add<basic::HoverWithFlightActionControlBehavior>(vehicle);
        builder.add<basic::SelfLocalizeWithGroundTruthBehavior>(builder.context().channel);
        builder.add<basic::EstimatePositionWithSensorBehavior>(builder.context().channel);
        builder.add<basic::EstimatePositionWithLinearSpeedBehavior>(builder.context().channel);
      });
}
