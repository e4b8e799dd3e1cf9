#pragma once

// Autopilot: the simulator's cascaded flight controller. It turns a setpoint
// at any of four levels into motor commands, running every loop below that
// level at the physics rate (it is called once per physics step):
//
//   position + yaw ──P──▶ velocity + yaw ──PI + drag feed-forward──▶
//   thrust vector ──▶ attitude + collective thrust ──P / sqrt law (quaternion
//   error, tilt before yaw)──▶ body rates ──PID (torque = I alpha + w x I w)──▶
//   torques ──mixer──▶ motors
//
//   QuadrotorParams params;
//   QuadrotorState start;
//   start.position_m = {0.0, 0.0, 10.0};                          // airborne,
//   start.motor_speeds_rad_s.fill(params.hoverMotorSpeedRadS());  // hovering
//   Quadrotor quad(params, start);
//   Autopilot autopilot(params);
//   Setpoint setpoint = VelocityYawRate{{2.0, 0.0, 0.0}, 0.0};  // 2 m/s east
//   for (int i = 0; i < 3000; ++i) {
//     quad.step(0.001, autopilot.update(quad.state(), setpoint, 0.001));
//   }
//
// Frames and units: world ENU (x east, y north, z up), body FLU (x forward,
// y left, z up), quaternions world <- body, yaw counter-clockwise from east,
// SI units. A thrust_ratio is the collective thrust as a fraction of the
// nominal maximum (QuadrotorParams::maxThrustN(), all motors at full speed
// with a full battery); hover is QuadrotorParams::hoverThrustRatio() (~0.31
// with the defaults). The autopilot compensates a sagging battery by reading
// the measured voltage, as real autopilots do, but it is not told of motor
// faults (efficiency < 1).
//
// Mixer saturation priority: roll/pitch torque first (scaled down only when
// even a zero collective cannot fit it), then collective thrust (shifted up or
// down to keep roll/pitch authority), then yaw (scaled down to what fits).
//
// Deterministic; no randomness, no clock. Not thread-safe.

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <array>
#include <variant>

#include "simulator/dynamics/quadrotor.h"
#include "simulator/dynamics/vehicle_params.h"

namespace behaviorlib::sim {

/// Motors off (disarmed). Also the autopilot's answer to a crashed vehicle.
struct Idle {};

/// Innermost level: collective thrust and body rates.
struct ThrustRates {
  double thrust_ratio = 0.0;                              ///< 0..1 of maxThrustN()
  Eigen::Vector3d rates_rad_s = Eigen::Vector3d::Zero();  ///< body FLU (roll, pitch, yaw)
};

/// Attitude and collective thrust.
struct AttitudeThrust {
  Eigen::Quaterniond orientation = Eigen::Quaterniond::Identity();  ///< world <- body
  double thrust_ratio = 0.0;                                        ///< 0..1 of maxThrustN()
};

/// Velocity in the world frame and yaw rate (the autopilot holds altitude
/// and heading when both are zero).
struct VelocityYawRate {
  Eigen::Vector3d velocity_m_s = Eigen::Vector3d::Zero();  ///< world ENU
  double yaw_rate_rad_s = 0.0;                             ///< counter-clockwise positive
};

/// Outermost level: position in the world frame and yaw.
struct PositionYaw {
  Eigen::Vector3d position_m = Eigen::Vector3d::Zero();  ///< world ENU
  double yaw_rad = 0.0;                                  ///< counter-clockwise from east (world x)
};

/// A setpoint at one of the levels.
using Setpoint = std::variant<Idle, ThrustRates, AttitudeThrust, VelocityYawRate, PositionYaw>;

/// Gains and limits of the autopilot. Gains are per axis: body (roll, pitch,
/// yaw) for the rate and attitude loops, world (x, y, z) for the velocity and
/// position loops.
struct AutopilotParams {
  /// Rate loop, per body axis: angular acceleration = P e + I integral(e) -
  /// D dw/dt (1/s, 1/s^2, dimensionless), turned into torque through the
  /// inertia plus the gyroscopic term w x I w. The integrator does not wind
  /// further into a direction the mixer could not deliver.
  Eigen::Vector3d rate_p{20.0, 20.0, 20.0};
  Eigen::Vector3d rate_i{10.0, 10.0, 1.0};
  Eigen::Vector3d rate_d{0.0, 0.0, 0.0};
  /// Bound on the integral of the rate error (rad).
  Eigen::Vector3d rate_integral_limit_rad{0.3, 0.3, 0.3};
  /// Bounds on the rate setpoint (rad/s).
  Eigen::Vector3d max_rates_rad_s{3.8, 3.8, 2.0};

  /// Attitude loop: rate = P * attitude error (1/s). The yaw error is
  /// weighted by P_yaw / P_roll so that tilt converges first (as PX4 does).
  Eigen::Vector3d attitude_p{6.5, 6.5, 3.0};
  /// Angular accelerations the attitude loop plans with (rad/s^2): beyond
  /// small errors the rate setpoint follows a square-root law, so the vehicle
  /// can stop at the target with this deceleration instead of overshooting
  /// (ArduPilot's sqrt controller). Yaw authority of a quadrotor is weak
  /// (reaction torques only: ~4 rad/s^2 at hover with the defaults).
  Eigen::Vector3d attitude_accel_limit_rad_s2{40.0, 40.0, 2.0};

  /// Velocity loop, per world axis: acceleration = P e + I integral(e)
  /// (1/s, 1/s^2); the thrust adds the drag the model predicts at the present
  /// velocity (drag_feedforward).
  Eigen::Vector3d velocity_p{2.5, 2.5, 4.0};
  Eigen::Vector3d velocity_i{0.4, 0.4, 2.0};
  /// Bound on the integral term (m/s^2).
  double velocity_integral_limit_m_s2 = 3.0;
  /// The integrator accumulates the error clamped to this (m/s), so the
  /// large errors of a step change hardly wind it up (overshoot of a 2 m/s
  /// step < 2 %) while a steady error (wind) is still integrated away.
  double velocity_integral_error_limit_m_s = 0.3;
  bool drag_feedforward = true;

  /// Position loop, per world axis: velocity = P e (1/s), then limited.
  Eigen::Vector3d position_p{1.0, 1.0, 1.5};
  double max_horizontal_speed_m_s = 5.0;
  double max_climb_rate_m_s = 3.0;
  double max_descent_rate_m_s = 2.0;

  // Thrust vector limits (velocity and position modes).
  double max_tilt_rad = 0.6;       ///< ~35 degrees
  double min_thrust_ratio = 0.08;  ///< keeps attitude authority while descending
  double max_thrust_ratio = 0.9;   ///< keeps a margin for attitude control
  /// Yaw reference of VelocityYawRate mode stays within this of the actual yaw.
  double max_yaw_error_rad = 0.5;
};

/// What the autopilot computed in its last update (telemetry, tests).
struct AutopilotStatus {
  Eigen::Vector3d velocity_setpoint_m_s = Eigen::Vector3d::Zero();        ///< world
  Eigen::Vector3d acceleration_setpoint_m_s2 = Eigen::Vector3d::Zero();   ///< world
  Eigen::Quaterniond attitude_setpoint = Eigen::Quaterniond::Identity();  ///< world <- body
  Eigen::Vector3d rate_setpoint_rad_s = Eigen::Vector3d::Zero();          ///< body
  double thrust_n = 0.0;                                                  ///< collective
  Eigen::Vector3d torque_n_m = Eigen::Vector3d::Zero();                   ///< body, requested
  std::array<double, kMotorCount> motor_thrusts_n{};                      ///< after the mixer
};

/// Allocates collective thrust and body torques to the four motors of an X
/// quadrotor, with saturation priority roll/pitch > thrust > yaw.
class Mixer {
 public:
  explicit Mixer(const QuadrotorParams& params);

  /// Per-motor thrusts (N), each within [0, max_motor_thrust_n], for a
  /// collective thrust (N) and body torques (N m).
  std::array<double, kMotorCount> allocate(double thrust_n, const Eigen::Vector3d& torque_n_m,
                                           double max_motor_thrust_n) const;

  /// Collective thrust (N) and body torques (N m) that per-motor thrusts
  /// produce: (T, tau_x, tau_y, tau_z).
  Eigen::Vector4d wrench(const std::array<double, kMotorCount>& thrusts_n) const;

 private:
  Eigen::Matrix4d allocation_;  // wrench = allocation_ * thrusts
  Eigen::Matrix4d inverse_;
};

/// Cascaded controller of one quadrotor. See the file comment.
class Autopilot {
 public:
  explicit Autopilot(const QuadrotorParams& vehicle, const AutopilotParams& params = {});

  /// One control step: motor commands that track `setpoint` from `state`,
  /// for a physics step of `dt_s` seconds. Idle, or a crashed vehicle, gives
  /// zero commands and resets the controller.
  MotorCommands update(const QuadrotorState& state, const Setpoint& setpoint, double dt_s);

  /// Clears integrators and references (e.g. after a respawn).
  void reset();

  const AutopilotStatus& status() const { return status_; }
  const AutopilotParams& params() const { return params_; }
  const QuadrotorParams& vehicle() const { return vehicle_; }

 private:
  // The outer loops; each returns what the next loop down needs.
  Eigen::Vector3d positionLoop(const QuadrotorState& state, const Eigen::Vector3d& position_m);
  void velocityLoop(const QuadrotorState& state, const Eigen::Vector3d& velocity_m_s,
                    double yaw_rad, double dt_s, Eigen::Quaterniond* attitude, double* thrust_n);
  Eigen::Vector3d attitudeLoop(const QuadrotorState& state, const Eigen::Quaterniond& attitude,
                               double yaw_rate_rad_s) const;
  Eigen::Vector3d rateLoop(const QuadrotorState& state, const Eigen::Vector3d& rates_rad_s,
                           double dt_s);
  MotorCommands mix(const QuadrotorState& state, double thrust_n, const Eigen::Vector3d& torque);

  QuadrotorParams vehicle_;
  AutopilotParams params_;
  Mixer mixer_;
  AutopilotStatus status_;

  Eigen::Vector3d attitude_gain_;  // yaw gain replaced by the roll gain, see yaw_weight_
  double yaw_weight_ = 1.0;

  std::size_t last_mode_ = 0;  // index of the last setpoint's alternative (Idle)
  double yaw_reference_rad_ = 0.0;
  Eigen::Vector3d velocity_integral_ = Eigen::Vector3d::Zero();  // of the error, m
  Eigen::Vector3d rate_integral_ = Eigen::Vector3d::Zero();      // of the error, rad
  Eigen::Vector3d last_rates_ = Eigen::Vector3d::Zero();
  bool have_last_rates_ = false;
  // Torque axes the mixer could not deliver in the last step, per direction
  // (+1 more was asked than delivered, -1 less): the rate integrator does not
  // wind up further in that direction.
  Eigen::Vector3i torque_saturation_ = Eigen::Vector3i::Zero();
};

}  // namespace behaviorlib::sim
