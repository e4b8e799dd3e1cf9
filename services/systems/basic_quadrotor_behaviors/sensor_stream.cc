#include "behaviorlib/basic_quadrotor_behaviors/sensor_stream.h"

#include "behaviorlib/flight_common/flight_monitoring.h"

namespace behaviorlib::basic {

namespace {

void setVector(v1::Vector3* out, const Eigen::Vector3d& v) {
  out->set_x(v.x());
  out->set_y(v.y());
  out->set_z(v.z());
}

}  // namespace

void fillEstimate(const google::protobuf::Timestamp& stamp, const std::string& robot_id,
                  uint64_t seq, const Eigen::Vector3d& position_m,
                  const Eigen::Quaterniond& orientation, const Eigen::Vector3d& velocity_m_s,
                  const Eigen::Vector3d& body_rates_rad_s, v1::PoseStamped* pose,
                  v1::TwistStamped* twist) {
  v1::Header header;
  *header.mutable_stamp() = stamp;
  header.set_frame_id("world");
  header.set_seq(seq);
  header.set_robot_id(robot_id);
  *pose->mutable_header() = header;
  setVector(pose->mutable_pose()->mutable_position_m(), position_m);
  auto* q = pose->mutable_pose()->mutable_orientation();
  q->set_w(orientation.w());
  q->set_x(orientation.x());
  q->set_y(orientation.y());
  q->set_z(orientation.z());
  *twist->mutable_header() = header;
  setVector(twist->mutable_twist()->mutable_linear_m_s(), velocity_m_s);
  setVector(twist->mutable_twist()->mutable_angular_rad_s(), body_rates_rad_s);
}

std::optional<std::string> SensorStream::problem(TimePoint now, TimePoint activated_at) const {
  if (!last_) {
    if (now - activated_at > timeout_) {
      return "no sample on " + topic_ + " within " + flight::secondsText(timeout_) +
             " of the activation";
    }
    return std::nullopt;
  }
  if (now - *last_ > timeout_) {
    return "the sensor on " + topic_ + " is silent: last sample " +
           flight::secondsText(now - *last_) + " ago (limit " + flight::secondsText(timeout_) + ")";
  }
  if (frozen_timeout_ > Duration::zero()) {
    const auto frozen = seconds(frozen_.frozenForS());
    if (frozen > frozen_timeout_) {
      return "the sensor on " + topic_ + " is frozen: the same value for " +
             flight::secondsText(frozen) + " (limit " + flight::secondsText(frozen_timeout_) + ")";
    }
  }
  return std::nullopt;
}

}  // namespace behaviorlib::basic
