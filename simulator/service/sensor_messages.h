#pragma once

// The sensors' samples as behaviorlib.v1 messages, and the topics they go on
// (listed in channel_publisher.h).

#include <google/protobuf/message.h>

#include <memory>
#include <string>

#include "simulator/sensors/sensor_samples.h"

namespace behaviorlib::sim {

/// "robots/{id}/imu", "robots/{id}/lidar/scan", ... for a sample.
std::string sensorTopic(const SensorSample& sample);

/// The message of a sample (Imu, PositionFix, Altitude, TwistStamped,
/// BatteryState, LaserScan or PointCloud, Image, CameraInfo) with its header:
/// stamp in simulated time, frame id, seq and robot id. Moves the image
/// bytes out of `sample`.
std::unique_ptr<google::protobuf::Message> sensorMessage(SensorSample&& sample);

/// The header frame of a sensor's samples: "base_link" (IMU, linear speed,
/// battery), "world" (GPS, barometer), "lidar", "camera".
const char* sensorFrame(SensorKind kind);

}  // namespace behaviorlib::sim
