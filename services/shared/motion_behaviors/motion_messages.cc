#include "behaviorlib/motion_behaviors/motion_messages.h"

#include <algorithm>
#include <cmath>
#include <cstdio>

namespace behaviorlib::motion_behaviors {
namespace {

void pointToProto(const motion::ReferencePoint& p, v1::MotionReferencePoint* out) {
  toProto(p.position_m, out->mutable_position_m());
  toProto(p.velocity_m_s, out->mutable_velocity_m_s());
  toProto(p.acceleration_m_s2, out->mutable_acceleration_m_s2());
  out->set_yaw_rad(p.yaw_rad);
}

motion::ReferencePoint pointFromProto(const v1::MotionReferencePoint& p) {
  motion::ReferencePoint out;
  out.position_m = toEigen(p.position_m());
  out.velocity_m_s = toEigen(p.velocity_m_s());
  out.acceleration_m_s2 = toEigen(p.acceleration_m_s2());
  out.yaw_rad = p.yaw_rad();
  return out;
}

motion::ReferencePoint blend(const motion::ReferencePoint& a, const motion::ReferencePoint& b,
                             double w) {
  motion::ReferencePoint out;
  out.position_m = (1.0 - w) * a.position_m + w * b.position_m;
  out.velocity_m_s = (1.0 - w) * a.velocity_m_s + w * b.velocity_m_s;
  out.acceleration_m_s2 = (1.0 - w) * a.acceleration_m_s2 + w * b.acceleration_m_s2;
  out.yaw_rad = motion::wrapAngle(a.yaw_rad + w * motion::wrapAngle(b.yaw_rad - a.yaw_rad));
  return out;
}

// The trajectory at `t` seconds after the reference's stamp.
motion::ReferencePoint sampleTrajectory(const motion::MotionReference& r, double t) {
  if (r.horizon.empty() || !(r.horizon_step_s > 0.0) || t <= 0.0) return r.point;
  // horizon[i] is at (i + 1) * step; the point itself at 0.
  const double index = t / r.horizon_step_s - 1.0;
  const int last = static_cast<int>(r.horizon.size()) - 1;
  if (index >= last) return r.horizon.back();
  const int i0 = static_cast<int>(std::floor(index));
  const double w = index - i0;
  const motion::ReferencePoint& a = i0 < 0 ? r.point : r.horizon[i0];
  return blend(a, r.horizon[i0 + 1], w);
}

}  // namespace

Eigen::Vector3d toEigen(const v1::Vector3& v) { return {v.x(), v.y(), v.z()}; }

void toProto(const Eigen::Vector3d& v, v1::Vector3* out) {
  out->set_x(v.x());
  out->set_y(v.y());
  out->set_z(v.z());
}

double yawOf(const v1::Quaternion& q) {
  return std::atan2(2.0 * (q.w() * q.z() + q.x() * q.y()),
                    1.0 - 2.0 * (q.y() * q.y() + q.z() * q.z()));
}

motion::StateEstimate stateOf(const v1::PoseStamped& pose, const v1::TwistStamped& twist) {
  motion::StateEstimate state;
  state.position_m = toEigen(pose.pose().position_m());
  state.velocity_m_s = toEigen(twist.twist().linear_m_s());
  const auto& q = pose.pose().orientation();
  Eigen::Quaterniond orientation(q.w(), q.x(), q.y(), q.z());
  // An unset orientation (all zero) reads as level.
  state.orientation =
      orientation.norm() > 1e-9 ? orientation.normalized() : Eigen::Quaterniond::Identity();
  return state;
}

v1::MotionReference toProto(const motion::MotionReference& reference) {
  v1::MotionReference out;
  switch (reference.mode) {
    case motion::MotionReference::Mode::kPosition:
      out.set_mode(v1::MOTION_REFERENCE_MODE_POSITION);
      break;
    case motion::MotionReference::Mode::kVelocity:
      out.set_mode(v1::MOTION_REFERENCE_MODE_VELOCITY);
      break;
    case motion::MotionReference::Mode::kTrajectory:
      out.set_mode(v1::MOTION_REFERENCE_MODE_TRAJECTORY);
      break;
  }
  pointToProto(reference.point, out.mutable_point());
  out.set_yaw_rate_rad_s(reference.yaw_rate_rad_s);
  for (const auto& p : reference.horizon) pointToProto(p, out.add_horizon());
  out.set_horizon_step_s(reference.horizon_step_s);
  return out;
}

motion::MotionReference fromProto(const v1::MotionReference& reference) {
  motion::MotionReference out;
  switch (reference.mode()) {
    case v1::MOTION_REFERENCE_MODE_VELOCITY:
      out.mode = motion::MotionReference::Mode::kVelocity;
      break;
    case v1::MOTION_REFERENCE_MODE_TRAJECTORY:
      out.mode = motion::MotionReference::Mode::kTrajectory;
      break;
    default:
      out.mode = motion::MotionReference::Mode::kPosition;
      break;
  }
  out.point = pointFromProto(reference.point());
  out.yaw_rate_rad_s = reference.yaw_rate_rad_s();
  out.horizon.reserve(reference.horizon_size());
  for (const auto& p : reference.horizon()) out.horizon.push_back(pointFromProto(p));
  out.horizon_step_s = reference.horizon_step_s();
  return out;
}

motion::MotionReference advance(const motion::MotionReference& reference, double age_s) {
  if (reference.mode != motion::MotionReference::Mode::kTrajectory || !(age_s > 0.0)) {
    return reference;
  }
  motion::MotionReference out = reference;
  out.point = sampleTrajectory(reference, age_s);
  for (size_t i = 0; i < out.horizon.size(); ++i) {
    out.horizon[i] =
        sampleTrajectory(reference, age_s + static_cast<double>(i + 1) * reference.horizon_step_s);
  }
  return out;
}

motion::MotionReference holdAt(const Eigen::Vector3d& position_m, double yaw_rad) {
  motion::MotionReference out;
  out.mode = motion::MotionReference::Mode::kPosition;
  out.point.position_m = position_m;
  out.point.yaw_rad = yaw_rad;
  return out;
}

void stampHeader(TimePoint t, const std::string& robot_id, uint64_t seq, v1::Header* header) {
  const int64_t ns = t.time_since_epoch().count();
  header->mutable_stamp()->set_seconds(ns / 1000000000);
  header->mutable_stamp()->set_nanos(static_cast<int32_t>(ns % 1000000000));
  header->set_frame_id("world");
  header->set_robot_id(robot_id);
  header->set_seq(seq);
}

std::string pointText(const Eigen::Vector3d& p) {
  char text[96];
  std::snprintf(text, sizeof(text), "(%.2f, %.2f, %.2f)", p.x(), p.y(), p.z());
  return text;
}

double ageSeconds(const v1::Header& header, TimePoint now) {
  const int64_t stamp_ns =
      header.stamp().seconds() * 1000000000 + static_cast<int64_t>(header.stamp().nanos());
  return static_cast<double>(now.time_since_epoch().count() - stamp_ns) * 1e-9;
}

}  // namespace behaviorlib::motion_behaviors
