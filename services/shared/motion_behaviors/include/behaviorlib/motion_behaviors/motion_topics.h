#pragma once

// Data-channel topics between the high-level motion behaviors and the active
// motion controller (messages in proto/behaviorlib/v1/motion.proto):
//
//   robots/{id}/motion_reference       MotionReference      written by the active
//                                                           high-level motion behavior
//   robots/{id}/motion_control/status  MotionControlStatus  written by the active
//                                                           motion controller

#include <string>

namespace behaviorlib::motion_behaviors {

inline std::string motionReferenceTopic(const std::string& robot_id) {
  return "robots/" + robot_id + "/motion_reference";
}
inline std::string motionControlStatusTopic(const std::string& robot_id) {
  return "robots/" + robot_id + "/motion_control/status";
}

}  // namespace behaviorlib::motion_behaviors
