#pragma once

// The samples the simulated sensors produce, before any transport: plain
// structs in SI units, frames as in the rest of the simulator (world ENU,
// body FLU, quaternions world <- body). The simulator service turns them into
// behaviorlib.v1 messages (simulator/service/sensor_messages.h).

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <array>
#include <cstdint>
#include <string>
#include <string_view>
#include <variant>
#include <vector>

#include "simulator/platform/vehicle_platform.h"  // SimTime

namespace behaviorlib::sim {

/// Which sensor a sample comes from.
enum class SensorKind {
  kImu,
  kGps,
  kBaro,
  kLinearSpeed,
  kBattery,
  kLidar,
  kCamera,
  kCameraInfo,
};
inline constexpr int kSensorKindCount = 8;

/// "imu", "gps", "baro", "linear_speed", "battery", "lidar", "camera",
/// "camera_info": the names used in configuration, seeds and statistics.
std::string_view sensorName(SensorKind kind);

/// Inertial measurement (frame base_link).
struct ImuData {
  Eigen::Quaterniond orientation = Eigen::Quaterniond::Identity();   ///< world <- body, with error
  Eigen::Vector3d angular_velocity_rad_s = Eigen::Vector3d::Zero();  ///< body, bias + noise
  /// Specific force (what an accelerometer measures: acceleration minus
  /// gravity), body frame; (0, 0, +9.81) at rest.
  Eigen::Vector3d specific_force_m_s2 = Eigen::Vector3d::Zero();
};

/// GPS-like position of the body origin (frame world).
struct PositionFixData {
  Eigen::Vector3d position_m = Eigen::Vector3d::Zero();
  double horizontal_stddev_m = 0.0;
  double vertical_stddev_m = 0.0;
};

/// Barometric altitude (world z plus noise and drift).
struct AltitudeData {
  double altitude_m = 0.0;
  double stddev_m = 0.0;
};

/// Body-frame linear velocity (frame base_link), optical-flow like.
struct LinearSpeedData {
  Eigen::Vector3d velocity_m_s = Eigen::Vector3d::Zero();
};

/// Battery state.
struct BatteryData {
  double charge_ratio = 0.0;  ///< 0..1
  double voltage_v = 0.0;
  double current_a = 0.0;
};

/// One lidar frame (frame "lidar": at the mount position, axes of the body).
struct LidarData {
  bool three_d = false;
  // 2-D: ranges_m[beam], ROS REP 117 (+inf: nothing within range_max_m;
  // -inf: closer than range_min_m).
  double angle_min_rad = 0.0;        ///< azimuth of the first beam
  double angle_max_rad = 0.0;        ///< azimuth of the last beam
  double angle_increment_rad = 0.0;  ///< between beams
  double range_min_m = 0.0;
  double range_max_m = 0.0;
  std::vector<float> ranges_m;
  // 3-D: the points that hit something within range.
  std::vector<Eigen::Vector3f> points_m;
};

/// One encoded camera frame (frame "camera", the optical frame).
struct CameraImageData {
  int width_px = 0;
  int height_px = 0;
  std::string encoding;  ///< "jpeg" or "png"
  std::string data;      ///< the encoded bytes
};

/// Intrinsics and mounting of the camera.
struct CameraInfoData {
  int width_px = 0;
  int height_px = 0;
  double fx_px = 0.0;
  double fy_px = 0.0;
  double cx_px = 0.0;
  double cy_px = 0.0;
  /// Pose of the optical frame (x right, y down, z forward) in the body frame.
  Eigen::Vector3d position_in_body_m = Eigen::Vector3d::Zero();
  Eigen::Quaterniond body_from_camera = Eigen::Quaterniond::Identity();
};

using SampleData = std::variant<ImuData, PositionFixData, AltitudeData, LinearSpeedData,
                                BatteryData, LidarData, CameraImageData, CameraInfoData>;

/// One sample of one sensor of one vehicle.
struct SensorSample {
  std::string robot_id;
  SensorKind kind = SensorKind::kImu;
  SimTime stamp{0};  ///< simulated time at which the state was sampled
  uint64_t seq = 0;  ///< per vehicle and sensor, from 0 (again after each reset)
  SampleData data;
};

}  // namespace behaviorlib::sim
