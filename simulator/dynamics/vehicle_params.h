#pragma once

// QuadrotorParams: the airframe, propulsion, drag, battery and contact
// parameters of one simulated quadrotor. Defaults describe a ~1.5 kg,
// 450 mm X quadrotor on a 4S 5 Ah battery that hovers at ~56 % motor command
// (31 % of its maximum collective thrust, thrust-to-weight ~3.3).
//
//   QuadrotorParams params;                 // the defaults above
//   params.mass_kg = 2.0;                   // a heavier payload
//   double u = params.hoverMotorCommand();  // ~0.64 (full battery)
//
// Frames and units (docs: /work/shared/ARCHITECTURE.md): world ENU (x east,
// y north, z up), body FLU (x forward, y left, z up), SI units throughout.
//
// Motor layout (X configuration, seen from above, x forward, y left):
//
//            x (forward)
//            ^
//     2 (CW) |  0 (CCW)
//   y <------+-------
//    1 (CCW) |  3 (CW)
//
//   index  position     spin (seen from above)
//   0      front-right  counter-clockwise
//   1      rear-left    counter-clockwise
//   2      front-left   clockwise
//   3      rear-right   clockwise
//
// (The PX4/ArduPilot quad-X numbering, zero-based.) A counter-clockwise
// propeller pushes the body clockwise: its reaction torque is -k_m w^2 about
// body z; a clockwise one gives +k_m w^2.

#include <Eigen/Core>
#include <array>
#include <cmath>

namespace behaviorlib::sim {

/// Number of motors of a quadrotor.
inline constexpr int kMotorCount = 4;

/// Sign of each motor's body x coordinate (forward positive), in motor order.
inline constexpr std::array<double, kMotorCount> kMotorXSign = {+1.0, -1.0, +1.0, -1.0};
/// Sign of each motor's body y coordinate (left positive), in motor order.
inline constexpr std::array<double, kMotorCount> kMotorYSign = {-1.0, +1.0, +1.0, -1.0};
/// Spin direction of each propeller seen from above: +1 counter-clockwise,
/// -1 clockwise.
inline constexpr std::array<double, kMotorCount> kMotorSpin = {+1.0, +1.0, -1.0, -1.0};

/// Standard gravity, m/s^2.
inline constexpr double kStandardGravity = 9.80665;

/// Physical parameters of one quadrotor. All SI units; body quantities in FLU.
struct QuadrotorParams {
  // --- Rigid body -----------------------------------------------------------
  double mass_kg = 1.5;
  /// Principal moments of inertia about body x, y, z (kg m^2). The body axes
  /// are taken as principal axes.
  Eigen::Vector3d inertia_kg_m2{0.029, 0.029, 0.055};
  /// Distance from the centre of mass to each motor axis (m). Motors sit on
  /// the diagonals: (+-L/sqrt2, +-L/sqrt2).
  double arm_length_m = 0.225;
  double gravity_m_s2 = kStandardGravity;

  // --- Propulsion -----------------------------------------------------------
  /// First-order time constant of a motor's speed response (s).
  double motor_time_constant_s = 0.03;
  /// Thrust of one propeller: T = k_f w^2 (N per (rad/s)^2).
  double thrust_coefficient_n_s2 = 1.2e-5;
  /// Reaction torque of one propeller: Q = k_m w^2 (N m per (rad/s)^2).
  double torque_coefficient_n_m_s2 = 1.9e-7;
  /// Motor speed at command 1.0 with a full battery (rad/s). The speed a
  /// command asks for scales with the battery voltage (see below).
  double max_motor_speed_rad_s = 1000.0;

  // --- Aerodynamic drag (body axes, on the velocity relative to the air) ----
  /// Linear drag per body axis: F = -c1 * v (N per m/s).
  Eigen::Vector3d linear_drag_n_s_m{0.25, 0.25, 0.30};
  /// Quadratic drag per body axis: F = -c2 * |v| * v (N per (m/s)^2).
  Eigen::Vector3d quadratic_drag_n_s2_m2{0.04, 0.04, 0.05};
  /// Rotational damping: torque = -c * w (N m per rad/s).
  double angular_drag_n_m_s_rad = 2e-3;

  // --- Battery --------------------------------------------------------------
  /// When false the supply is ideal: full voltage, never drains.
  bool simulate_battery = true;
  double battery_capacity_wh = 74.0;  ///< 4S 5000 mAh
  /// Open-circuit voltage is linear in the state of charge between these.
  double battery_full_voltage_v = 16.8;
  double battery_empty_voltage_v = 13.2;
  /// Internal resistance: the terminal voltage sags by I * R under load.
  double battery_internal_resistance_ohm = 0.02;
  /// Electrical to aerodynamic (shaft) power efficiency of motors + ESCs.
  double propulsion_efficiency = 0.7;
  /// Constant draw of the flight controller, radios, sensors (W).
  double avionics_power_w = 5.0;

  // --- Contact --------------------------------------------------------------
  /// Height of the ground plane in the world frame (m).
  double ground_z_m = 0.0;
  /// Vertical touchdown speed above which the vehicle crashes (m/s).
  double crash_speed_m_s = 3.0;
  /// Tilt at touchdown above which the vehicle tips over and crashes (rad).
  double crash_tilt_rad = 1.0;
  /// Radius of the sphere used for collisions with the world (m).
  double collision_radius_m = 0.35;

  /// Maximum thrust of one motor at full battery voltage (N).
  double maxMotorThrustN() const {
    return thrust_coefficient_n_s2 * max_motor_speed_rad_s * max_motor_speed_rad_s;
  }
  /// Maximum collective thrust at full battery voltage (N): what a
  /// thrust_ratio of 1 means.
  double maxThrustN() const { return kMotorCount * maxMotorThrustN(); }
  /// Collective thrust ratio that balances gravity.
  double hoverThrustRatio() const { return mass_kg * gravity_m_s2 / maxThrustN(); }
  /// Motor speed that balances gravity with all four motors equal (rad/s).
  double hoverMotorSpeedRadS() const {
    return std::sqrt(mass_kg * gravity_m_s2 / (kMotorCount * thrust_coefficient_n_s2));
  }
  /// Motor command that hovers at full battery voltage: sqrt(m g / 4 k_f) / w_max.
  double hoverMotorCommand() const { return hoverMotorSpeedRadS() / max_motor_speed_rad_s; }
  /// Position of motor `i` in the body frame (m).
  Eigen::Vector3d motorPositionM(int i) const {
    const double d = arm_length_m / std::sqrt(2.0);
    return {kMotorXSign[i] * d, kMotorYSign[i] * d, 0.0};
  }
};

}  // namespace behaviorlib::sim
