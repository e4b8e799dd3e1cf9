// quadrotor_motion_with_mpc_control: the paper's behavior system of motion
// with model-predictive control. The high-level behaviors
// (FOLLOW_PATH_WITH_MPC_CONTROL, ROTATE_WITH_MPC_CONTROL,
// HOVER_WITH_MPC_CONTROL) publish motion references with a horizon on the
// data channel; QUADROTOR_MPC_MOTION_CONTROL follows them (a receding-horizon
// optimizer, attitude + thrust setpoints), commanding the platform through
// --flight-controller under its lease. Run with --clock sim under the
// simulator; topics in services/motion_behaviors/motion_topics.h.

#include "behaviorlib/flight_common/remote_vehicle.h"
#include "behaviorlib/motion_behaviors/follow_path_behavior.h"
#include "behaviorlib/motion_behaviors/hover_behavior.h"
#include "behaviorlib/motion_behaviors/motion_control_behavior.h"
#include "behaviorlib/motion_behaviors/motion_link.h"
#include "behaviorlib/motion_behaviors/rotate_behavior.h"
#include "behaviorlib/server/behavior_system_main.h"
#include "behaviorlib/v1/behaviors/quadrotor_motion_with_mpc_control.behaviors.h"

int main(int argc, char** argv) {
  using behaviorlib::server::BehaviorSystemBuilder;
  namespace mb = behaviorlib::motion_behaviors;
  namespace v1 = behaviorlib::v1;
  return behaviorlib::server::runBehaviorSystem(
      argc, argv, "quadrotor_motion_with_mpc_control", [](BehaviorSystemBuilder& builder) {
        const auto& context = builder.context();
        auto& vehicle = builder.own(std::make_unique<behaviorlib::flight::RemoteVehicle>(context));
        auto& link =
            builder.own(std::make_unique<mb::RemoteMotionLink>(context.channel, context.robot_id));
        builder.add<mb::FollowPathBehavior<v1::FollowPathWithMpcControlParameters>>(vehicle, link);
        builder.add<mb::RotateBehavior<v1::RotateWithMpcControlParameters>>(vehicle, link);
        builder.add<mb::HoverBehavior<v1::HoverWithMpcControlParameters>>(vehicle, link);
        builder.add<mb::MotionControlBehavior<v1::QuadrotorMpcMotionControlParameters,
                                              behaviorlib::config::v1::MpcMotionControlConfig>>(
            vehicle, link,
            [](const mb::ControllerConfig& config, const behaviorlib::motion::VehicleModel& model) {
              return mb::makeMpcController(model, config.mpc);
            });
      });
}
