#pragma once

// Types shared by the motion controllers: the vehicle as the controllers
// model it, the state estimate they read, the reference they track, and the
// command they produce for the platform (FlightController attitude + thrust,
// or thrust + body rates).
//
// Frames and units: world ENU (x east, y north, z up), body FLU, quaternions
// world <- body, yaw counter-clockwise from east; SI units.

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <vector>

namespace behaviorlib::motion {

/// What the controllers know of the vehicle (from the behavior system's
/// configuration; a real airframe's values in a real deployment).
struct VehicleModel {
  double mass_kg = 1.5;
  /// Collective thrust with every motor at full speed (thrust ratio 1).
  double max_thrust_n = 48.0;
  double gravity_m_s2 = 9.81;
  /// Largest tilt the controllers command.
  double max_tilt_rad = 0.6;
  /// Thrust ratio bounds of the commands (keeps attitude authority).
  double min_thrust_ratio = 0.08;
  double max_thrust_ratio = 0.9;
  /// Horizontal and vertical speed limits of the references they follow.
  double max_horizontal_speed_m_s = 3.0;
  double max_vertical_speed_m_s = 1.5;

  double hoverThrustRatio() const { return mass_kg * gravity_m_s2 / max_thrust_n; }
};

/// The pose estimate the controllers act on.
struct StateEstimate {
  Eigen::Vector3d position_m = Eigen::Vector3d::Zero();
  Eigen::Vector3d velocity_m_s = Eigen::Vector3d::Zero();  ///< world
  Eigen::Quaterniond orientation = Eigen::Quaterniond::Identity();
  double yawRad() const;
};

/// One point of a reference trajectory.
struct ReferencePoint {
  Eigen::Vector3d position_m = Eigen::Vector3d::Zero();
  Eigen::Vector3d velocity_m_s = Eigen::Vector3d::Zero();       ///< feed-forward
  Eigen::Vector3d acceleration_m_s2 = Eigen::Vector3d::Zero();  ///< feed-forward
  double yaw_rad = 0.0;
};

/// What a motion controller tracks.
struct MotionReference {
  enum class Mode {
    kPosition,   ///< hold/go to `point` (position + yaw)
    kVelocity,   ///< fly at point.velocity_m_s, turning at yaw_rate_rad_s
    kTrajectory  ///< follow `point` now and `horizon` ahead (every horizon_step_s)
  };
  Mode mode = Mode::kPosition;
  ReferencePoint point;
  double yaw_rate_rad_s = 0.0;  ///< kVelocity
  std::vector<ReferencePoint> horizon;
  double horizon_step_s = 0.1;
};

/// Attitude and collective thrust for the platform.
struct AttitudeThrustCommand {
  Eigen::Quaterniond orientation = Eigen::Quaterniond::Identity();
  double thrust_ratio = 0.0;
};

/// Health of one controller step (for the behaviors' checkProcesses).
struct ControllerDiagnostics {
  bool saturated = false;  ///< tilt or thrust limited this step
  bool finite = true;      ///< false when an input or output was NaN/inf
  Eigen::Vector3d acceleration_command_m_s2 = Eigen::Vector3d::Zero();
};

/// Turns a desired acceleration (world) and yaw into attitude and thrust:
/// thrust along m (a + g z), tilt limited to the model's maximum (the
/// vertical part is kept), thrust ratio clamped. Sets `saturated` when a
/// limit applied.
AttitudeThrustCommand accelerationToAttitude(const Eigen::Vector3d& acceleration_m_s2,
                                             double yaw_rad, const VehicleModel& model,
                                             bool* saturated);

/// Wraps an angle to (-pi, pi].
double wrapAngle(double rad);

}  // namespace behaviorlib::motion
