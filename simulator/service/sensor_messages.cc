#include "simulator/service/sensor_messages.h"

#include <google/protobuf/util/time_util.h>

#include <type_traits>

#include "behaviorlib/v1/types.pb.h"

namespace behaviorlib::sim {
namespace {

using google::protobuf::util::TimeUtil;

void setVector(v1::Vector3* out, const Eigen::Vector3d& v) {
  out->set_x(v.x());
  out->set_y(v.y());
  out->set_z(v.z());
}

void setQuaternion(v1::Quaternion* out, const Eigen::Quaterniond& q) {
  out->set_w(q.w());
  out->set_x(q.x());
  out->set_y(q.y());
  out->set_z(q.z());
}

void setHeader(v1::Header* header, const SensorSample& sample) {
  *header->mutable_stamp() = TimeUtil::NanosecondsToTimestamp(sample.stamp.count());
  header->set_frame_id(sensorFrame(sample.kind));
  header->set_seq(sample.seq);
  header->set_robot_id(sample.robot_id);
}

std::unique_ptr<google::protobuf::Message> toMessage(const SensorSample& s, ImuData& d) {
  auto m = std::make_unique<v1::Imu>();
  setHeader(m->mutable_header(), s);
  setQuaternion(m->mutable_orientation(), d.orientation);
  setVector(m->mutable_angular_velocity_rad_s(), d.angular_velocity_rad_s);
  setVector(m->mutable_linear_acceleration_m_s2(), d.specific_force_m_s2);
  return m;
}

std::unique_ptr<google::protobuf::Message> toMessage(const SensorSample& s, PositionFixData& d) {
  auto m = std::make_unique<v1::PositionFix>();
  setHeader(m->mutable_header(), s);
  setVector(m->mutable_position_m(), d.position_m);
  m->set_horizontal_stddev_m(d.horizontal_stddev_m);
  m->set_vertical_stddev_m(d.vertical_stddev_m);
  return m;
}

std::unique_ptr<google::protobuf::Message> toMessage(const SensorSample& s, AltitudeData& d) {
  auto m = std::make_unique<v1::Altitude>();
  setHeader(m->mutable_header(), s);
  m->set_altitude_m(d.altitude_m);
  m->set_stddev_m(d.stddev_m);
  return m;
}

std::unique_ptr<google::protobuf::Message> toMessage(const SensorSample& s, LinearSpeedData& d) {
  auto m = std::make_unique<v1::TwistStamped>();
  setHeader(m->mutable_header(), s);
  setVector(m->mutable_twist()->mutable_linear_m_s(), d.velocity_m_s);
  return m;
}

std::unique_ptr<google::protobuf::Message> toMessage(const SensorSample& s, BatteryData& d) {
  auto m = std::make_unique<v1::BatteryState>();
  setHeader(m->mutable_header(), s);
  m->set_charge_ratio(d.charge_ratio);
  m->set_voltage_v(d.voltage_v);
  m->set_current_a(d.current_a);
  return m;
}

std::unique_ptr<google::protobuf::Message> toMessage(const SensorSample& s, LidarData& d) {
  if (d.three_d) {
    auto m = std::make_unique<v1::PointCloud>();
    setHeader(m->mutable_header(), s);
    m->mutable_points_m()->Reserve(static_cast<int>(d.points_m.size()));
    for (const Eigen::Vector3f& p : d.points_m) setVector(m->add_points_m(), p.cast<double>());
    return m;
  }
  auto m = std::make_unique<v1::LaserScan>();
  setHeader(m->mutable_header(), s);
  m->set_angle_min_rad(d.angle_min_rad);
  m->set_angle_max_rad(d.angle_max_rad);
  m->set_angle_increment_rad(d.angle_increment_rad);
  m->set_range_min_m(d.range_min_m);
  m->set_range_max_m(d.range_max_m);
  m->mutable_ranges_m()->Add(d.ranges_m.begin(), d.ranges_m.end());
  return m;
}

std::unique_ptr<google::protobuf::Message> toMessage(const SensorSample& s, CameraImageData& d) {
  auto m = std::make_unique<v1::Image>();
  setHeader(m->mutable_header(), s);
  m->set_width_px(static_cast<uint32_t>(d.width_px));
  m->set_height_px(static_cast<uint32_t>(d.height_px));
  m->set_encoding(d.encoding);
  m->set_step_bytes(0);
  m->set_data(std::move(d.data));
  return m;
}

std::unique_ptr<google::protobuf::Message> toMessage(const SensorSample& s, CameraInfoData& d) {
  auto m = std::make_unique<v1::CameraInfo>();
  setHeader(m->mutable_header(), s);
  m->set_width_px(static_cast<uint32_t>(d.width_px));
  m->set_height_px(static_cast<uint32_t>(d.height_px));
  m->set_fx_px(d.fx_px);
  m->set_fy_px(d.fy_px);
  m->set_cx_px(d.cx_px);
  m->set_cy_px(d.cy_px);
  setVector(m->mutable_pose_in_body()->mutable_position_m(), d.position_in_body_m);
  setQuaternion(m->mutable_pose_in_body()->mutable_orientation(), d.body_from_camera);
  return m;
}

}  // namespace

const char* sensorFrame(SensorKind kind) {
  switch (kind) {
    case SensorKind::kGps:
    case SensorKind::kBaro:
      return "world";
    case SensorKind::kLidar:
      return "lidar";
    case SensorKind::kCamera:
    case SensorKind::kCameraInfo:
      return "camera";
    case SensorKind::kImu:
    case SensorKind::kLinearSpeed:
    case SensorKind::kBattery:
      break;
  }
  return "base_link";
}

std::string sensorTopic(const SensorSample& sample) {
  std::string topic = "robots/" + sample.robot_id + "/";
  switch (sample.kind) {
    case SensorKind::kLidar: {
      const auto* lidar = std::get_if<LidarData>(&sample.data);
      return topic + (lidar != nullptr && lidar->three_d ? "lidar/points" : "lidar/scan");
    }
    case SensorKind::kCamera:
      return topic + "camera/image";
    case SensorKind::kCameraInfo:
      return topic + "camera/info";
    default:
      return topic + std::string(sensorName(sample.kind));
  }
}

std::unique_ptr<google::protobuf::Message> sensorMessage(SensorSample&& sample) {
  return std::visit([&sample](auto& data) { return toMessage(sample, data); }, sample.data);
}

}  // namespace behaviorlib::sim
