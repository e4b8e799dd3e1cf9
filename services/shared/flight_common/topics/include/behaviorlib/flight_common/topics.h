#pragma once

// Data-channel topics of the robot's pose estimate, shared by the flight
// behavior systems (basic_quadrotor_behaviors, the motion systems).
//
// Read:
//   robots/{id}/ground_truth/pose       PoseStamped   simulator, 100 Hz (world frame)
//   robots/{id}/ground_truth/twist      TwistStamped  simulator, 100 Hz (linear world,
//                                                     angular body)
//   robots/{id}/flight_state            FlightStatus  simulator (the platform's state,
//                                                     lease and battery ratio)
// Written by SELF_LOCALIZE_WITH_GROUND_TRUTH, read by the flight behaviors:
//   robots/{id}/self_localization/pose  PoseStamped   the pose estimate (world frame)
//   robots/{id}/self_localization/twist TwistStamped  the velocity estimate (linear
//                                                     world, angular body)

#include <string>

namespace behaviorlib::flight {

inline std::string groundTruthPoseTopic(const std::string& robot_id) {
  return "robots/" + robot_id + "/ground_truth/pose";
}
inline std::string groundTruthTwistTopic(const std::string& robot_id) {
  return "robots/" + robot_id + "/ground_truth/twist";
}
inline std::string flightStateTopic(const std::string& robot_id) {
  return "robots/" + robot_id + "/flight_state";
}
inline std::string poseEstimateTopic(const std::string& robot_id) {
  return "robots/" + robot_id + "/self_localization/pose";
}
inline std::string twistEstimateTopic(const std::string& robot_id) {
  return "robots/" + robot_id + "/self_localization/twist";
}

}  // namespace behaviorlib::flight
