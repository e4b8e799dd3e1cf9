#pragma once

// Conversions between the motion controllers' types (motion_control/, Eigen)
// and the data channel's messages (motion.proto, types.proto), and the small
// pieces of arithmetic on them that the motion behaviors share.
//
//   motion::StateEstimate state = stateOf(pose, twist);
//   v1::MotionReference message = toProto(reference);
//   motion::MotionReference now = advance(fromProto(message), age_s);

#include <Eigen/Core>
#include <string>

#include "behaviorlib/clock.h"
#include "behaviorlib/motion_control/motion_types.h"
#include "behaviorlib/v1/motion.pb.h"
#include "behaviorlib/v1/types.pb.h"

namespace behaviorlib::motion_behaviors {

Eigen::Vector3d toEigen(const v1::Vector3& v);
void toProto(const Eigen::Vector3d& v, v1::Vector3* out);

/// Yaw (rad, counter-clockwise from +x) of a quaternion (w, x, y, z).
double yawOf(const v1::Quaternion& q);

/// The estimate the controllers act on: pose (world) and twist (linear
/// world) estimates.
motion::StateEstimate stateOf(const v1::PoseStamped& pose, const v1::TwistStamped& twist);

v1::MotionReference toProto(const motion::MotionReference& reference);
/// MOTION_REFERENCE_MODE_UNSPECIFIED maps to a position reference.
motion::MotionReference fromProto(const v1::MotionReference& reference);

/// The reference `age_s` seconds after it was made: a trajectory moves along
/// its horizon (held at the horizon's end), the others are unchanged. Makes
/// up for the time a reference spent on the channel.
motion::MotionReference advance(const motion::MotionReference& reference, double age_s);

/// A position reference holding `position_m` with `yaw_rad`.
motion::MotionReference holdAt(const Eigen::Vector3d& position_m, double yaw_rad);

/// Fills a header: stamp `t`, frame "world", `robot_id`, `seq`.
void stampHeader(TimePoint t, const std::string& robot_id, uint64_t seq, v1::Header* header);

/// "(1.00, 2.00, 3.00)", for messages.
std::string pointText(const Eigen::Vector3d& p);

/// Seconds from a header's stamp to `now` (negative when the stamp is ahead).
double ageSeconds(const v1::Header& header, TimePoint now);

}  // namespace behaviorlib::motion_behaviors
