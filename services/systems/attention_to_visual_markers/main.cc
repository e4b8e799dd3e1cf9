// attention_to_visual_markers: the behavior system of PAY_ATTENTION_TO_QR_CODES.

#include "behaviorlib/attention_to_visual_markers/qr_attention_behavior.h"
#include "behaviorlib/server/behavior_system_main.h"
#include "behaviorlib/v1/behaviors/attention_to_visual_markers.behaviors.h"

int main(int argc, char** argv) {
  return behaviorlib::server::runBehaviorSystem(
      argc, argv, "attention_to_visual_markers", [](behaviorlib::server::BehaviorSystemBuilder& b) {
        b.add<behaviorlib::markers::QrAttentionBehavior>(b.context().channel, b.context().beliefs);
      });
}
