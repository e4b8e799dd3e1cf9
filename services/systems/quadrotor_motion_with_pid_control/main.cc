// quadrotor_motion_with_pid_control: the paper's behavior system of motion
// with PID control. The high-level behaviors (FOLLOW_PATH,
// ROTATE_WITH_PID_CONTROL, KEEP_HOVERING_WITH_PID_CONTROL,
// KEEP_MOVING_WITH_PID_CONTROL) publish motion references on the data channel;
// the motion controllers (QUADROTOR_PID_MOTION_CONTROL: attitude + thrust;
// QUADROTOR_PID_THRUST_CONTROL: thrust + body rates) follow them, commanding
// the platform through --flight-controller under its lease. Run with
// --clock sim under the simulator; topics in
// services/motion_behaviors/motion_topics.h.

#include "behaviorlib/flight_common/remote_vehicle.h"
#include "behaviorlib/motion_behaviors/follow_path_behavior.h"
#include "behaviorlib/motion_behaviors/hover_behavior.h"
#include "behaviorlib/motion_behaviors/motion_control_behavior.h"
#include "behaviorlib/motion_behaviors/motion_link.h"
#include "behaviorlib/motion_behaviors/rotate_behavior.h"
#include "behaviorlib/quadrotor_motion_with_pid_control/keep_moving_behavior.h"
#include "behaviorlib/server/behavior_system_main.h"
#include "behaviorlib/v1/behaviors/quadrotor_motion_with_pid_control.behaviors.h"

int main(int argc, char** argv) {
  using behaviorlib::server::BehaviorSystemBuilder;
  namespace mb = behaviorlib::motion_behaviors;
  namespace v1 = behaviorlib::v1;
  return behaviorlib::server::runBehaviorSystem(
      argc, argv, "quadrotor_motion_with_pid_control", [](BehaviorSystemBuilder& builder) {
        const auto& context = builder.context();
        auto& vehicle = builder.own(std::make_unique<behaviorlib::flight::RemoteVehicle>(context));
        auto& link =
            builder.own(std::make_unique<mb::RemoteMotionLink>(context.channel, context.robot_id));
        builder.add<mb::FollowPathBehavior<v1::FollowPathParameters>>(vehicle, link);
        builder.add<mb::RotateBehavior<v1::RotateWithPidControlParameters>>(vehicle, link);
        builder.add<mb::HoverBehavior<v1::KeepHoveringWithPidControlParameters>>(vehicle, link);
        builder.add<mb::KeepMovingWithPidControlBehavior>(vehicle, link);
        builder.add<mb::MotionControlBehavior<v1::QuadrotorPidMotionControlParameters,
                                              behaviorlib::config::v1::PidMotionControlConfig>>(
            vehicle, link,
            [](const mb::ControllerConfig& config, const behaviorlib::motion::VehicleModel& model) {
              return mb::makePidAttitudeController(model, config.pid);
            });
        builder.add<mb::MotionControlBehavior<v1::QuadrotorPidThrustControlParameters,
                                              behaviorlib::config::v1::PidMotionControlConfig>>(
            vehicle, link,
            [](const mb::ControllerConfig& config, const behaviorlib::motion::VehicleModel& model) {
              return mb::makePidThrustRatesController(model, config.pid, config.attitude_p,
                                                      config.max_rate_rad_s);
            });
      });
}
