// multi_sensor_fusion: the behavior system of SELF_LOCALIZE_WITH_EKF_SENSOR_FUSION.

#include "behaviorlib/multi_sensor_fusion/ekf_behavior.h"
#include "behaviorlib/server/behavior_system_main.h"
#include "behaviorlib/v1/behaviors/multi_sensor_fusion.behaviors.h"

int main(int argc, char** argv) {
  return behaviorlib::server::runBehaviorSystem(
      argc, argv, "multi_sensor_fusion", [](behaviorlib::server::BehaviorSystemBuilder& b) {
        b.add<behaviorlib::fusion::EkfSelfLocalizationBehavior>(b.context().channel);
      });
}
