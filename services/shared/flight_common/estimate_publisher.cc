#include "behaviorlib/flight_common/estimate_publisher.h"

#include "behaviorlib/flight_common/topics.h"

namespace behaviorlib::flight {
namespace {

void setVector(v1::Vector3* out, const Eigen::Vector3d& v) {
  out->set_x(v.x());
  out->set_y(v.y());
  out->set_z(v.z());
}

}  // namespace

void estimateMessages(const google::protobuf::Timestamp& stamp, const std::string& robot_id,
                      uint64_t seq, const Estimate& estimate, v1::PoseStamped* pose,
                      v1::TwistStamped* twist) {
  v1::Header header;
  *header.mutable_stamp() = stamp;
  header.set_frame_id("world");
  header.set_seq(seq);
  header.set_robot_id(robot_id);
  *pose->mutable_header() = header;
  setVector(pose->mutable_pose()->mutable_position_m(), estimate.position_m);
  auto* q = pose->mutable_pose()->mutable_orientation();
  q->set_w(estimate.orientation.w());
  q->set_x(estimate.orientation.x());
  q->set_y(estimate.orientation.y());
  q->set_z(estimate.orientation.z());
  if (estimate.horizontal_stddev_m) pose->set_horizontal_stddev_m(*estimate.horizontal_stddev_m);
  *twist->mutable_header() = std::move(header);
  setVector(twist->mutable_twist()->mutable_linear_m_s(), estimate.velocity_m_s);
  setVector(twist->mutable_twist()->mutable_angular_rad_s(), estimate.body_rates_rad_s);
}

void EstimatePublisher::publish(const google::protobuf::Timestamp& stamp,
                                const std::string& robot_id, const Estimate& estimate) {
  if (channel_ == nullptr) {
    if (error_.ok()) error_ = absl::FailedPreconditionError("no data channel configured");
    return;
  }
  v1::PoseStamped pose;
  v1::TwistStamped twist;
  estimateMessages(stamp, robot_id, ++seq_, estimate, &pose, &twist);
  absl::Status s = channel_->publish(poseEstimateTopic(robot_id), pose);
  if (s.ok()) s = channel_->publish(twistEstimateTopic(robot_id), twist);
  if (!s.ok() && error_.ok()) error_ = std::move(s);
}

}  // namespace behaviorlib::flight
