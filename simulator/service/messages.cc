#include "simulator/service/messages.h"

#include <google/protobuf/util/time_util.h>

namespace behaviorlib::sim {
namespace {

using google::protobuf::util::TimeUtil;

void setVector(v1::Vector3* out, const Eigen::Vector3d& v) {
  out->set_x(v.x());
  out->set_y(v.y());
  out->set_z(v.z());
}

void setHeader(v1::Header* header, const std::string& robot_id, SimTime now) {
  header->set_robot_id(robot_id);
  header->set_frame_id("world");
  *header->mutable_stamp() = TimeUtil::NanosecondsToTimestamp(now.count());
}

}  // namespace

v1::VehicleState vehicleStateMessage(const std::string& robot_id, SimTime now,
                                     const VehicleReport& report) {
  v1::VehicleState state;
  setHeader(state.mutable_header(), robot_id, now);
  const auto& s = report.snapshot;
  setVector(state.mutable_pose()->mutable_position_m(), s.position_m);
  auto* q = state.mutable_pose()->mutable_orientation();
  q->set_w(s.orientation.w());
  q->set_x(s.orientation.x());
  q->set_y(s.orientation.y());
  q->set_z(s.orientation.z());
  setVector(state.mutable_twist()->mutable_linear_m_s(), s.velocity_m_s);
  setVector(state.mutable_twist()->mutable_angular_rad_s(), s.angular_velocity_rad_s);
  state.set_flight_state(report.platform->state());
  state.set_battery_ratio(s.battery_ratio);
  state.set_crashed(s.crashed);
  return state;
}

v1::FlightStatus flightStatusMessage(const std::string& robot_id, SimTime now,
                                     const VehiclePlatform& platform, double battery_ratio) {
  v1::FlightStatus status;
  setHeader(status.mutable_header(), robot_id, now);
  status.set_state(platform.state());
  status.set_lease_holder(platform.leaseHolder());
  status.set_failsafe_active(platform.failsafeActive());
  status.set_battery_ratio(battery_ratio);
  return status;
}

}  // namespace behaviorlib::sim
