#pragma once

// Quadrotor: 6-DoF rigid-body dynamics of one quadrotor with four motors of
// first-order response, drag against the air (with wind), gravity, ground
// contact, collisions with the world and a battery that drains with thrust.
//
//   Quadrotor quad(QuadrotorParams{});        // resting on the ground at the origin
//   quad.setCollisionWorld(&world);           // optional, not owned
//   MotorCommands u{0.6, 0.6, 0.6, 0.6};
//   for (int i = 0; i < 1000; ++i) quad.step(0.001, u);  // one simulated second
//   const QuadrotorState& s = quad.state();   // s.position_m.z() > 0: climbing
//
// Frames: position and velocity in the world frame (ENU: x east, y north,
// z up); orientation is world <- body; angular velocity in the body frame
// (FLU: x forward, y left, z up). SI units. Motor order and spin directions:
// see vehicle_params.h.
//
// Integrator (one fixed step `dt`, 1 ms by default in WorldSim):
//  - motors: the exact solution of the first-order lag over the step,
//    w += (w_target - w) (1 - exp(-dt / tau)): unconditionally stable for any
//    tau, so fast motors (tau 20-50 ms, or smaller) never limit the step;
//  - translation: semi-implicit (symplectic) Euler, v += a dt, then
//    p += v_new dt;
//  - rotation: w += I^-1 (tau - w x I w) dt, then q = q * exp(w_new dt / 2)
//    (the exact rotation for a constant body rate over the step, so the
//    quaternion stays a rotation; it is renormalised against round-off).
// Why: semi-implicit Euler is symplectic, so undamped oscillations keep their
// amplitude instead of growing as with explicit Euler (stable for w dt < 2);
// at 1 kHz every mode here is far inside that: the closed-loop rate loop
// (~20 rad/s) gives w dt ~ 0.02, drag time constants are ~0.5 s and longer.
// One force evaluation per step keeps a step in the hundreds of nanoseconds.
// RK4 would cost four evaluations for accuracy that is not there to be had:
// the autopilot's commands are held constant over the step (zero-order hold)
// and ground contact and saturation are non-smooth, which removes RK4's order
// anyway. The known error is O(dt): e.g. free fall from rest gives
// z_n = -g dt^2 n (n + 1) / 2, i.e. -g t^2 / 2 - g t dt / 2 (5 mm after 1 s).
//
// Ground contact (plane z = ground_z_m): reaching it with a vertical speed
// above crash_speed_m_s or tilted more than crash_tilt_rad crashes the
// vehicle; otherwise it touches down: it is then *landed*, resting level on
// its landing gear at z = ground_z_m with zero velocity (friction, no sliding,
// no sinking) until the net vertical force (thrust, drag, external force,
// gravity) points up, when it lifts off. A collision with the world
// (CollisionWorld::collides) crashes it too. A crashed vehicle stays put with
// its motors off until reset().
//
// Not thread-safe; deterministic (no randomness, no clock).

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <array>

#include "formats/world/collision_world.h"
#include "simulator/dynamics/vehicle_params.h"

namespace behaviorlib::sim {

/// Normalized motor commands in motor order, each in [0, 1] (clamped): the
/// fraction of the speed the battery's present voltage allows.
using MotorCommands = std::array<double, kMotorCount>;

/// Why a vehicle crashed.
enum class CrashCause {
  kNone,        ///< Not crashed.
  kHardImpact,  ///< Hit the ground faster than crash_speed_m_s.
  kTipOver,     ///< Touched the ground tilted more than crash_tilt_rad.
  kCollision,   ///< Collided with the world (CollisionWorld).
};

/// The full state of one quadrotor.
struct QuadrotorState {
  Eigen::Vector3d position_m = Eigen::Vector3d::Zero();    ///< world ENU
  Eigen::Vector3d velocity_m_s = Eigen::Vector3d::Zero();  ///< world ENU
  /// Acceleration over the last step, world ENU (m/s^2); zero when landed.
  Eigen::Vector3d acceleration_m_s2 = Eigen::Vector3d::Zero();
  Eigen::Quaterniond orientation = Eigen::Quaterniond::Identity();   ///< world <- body
  Eigen::Vector3d angular_velocity_rad_s = Eigen::Vector3d::Zero();  ///< body FLU
  std::array<double, kMotorCount> motor_speeds_rad_s{};              ///< motor order
  double battery_soc = 1.0;                                          ///< state of charge, 0..1
  double battery_voltage_v = 0.0;  ///< terminal voltage; set by the constructor
  double battery_power_w = 0.0;    ///< electrical power drawn over the last step
  bool landed = false;             ///< resting on the ground
  bool crashed = false;
  CrashCause crash_cause = CrashCause::kNone;
};

/// Yaw of an orientation (world <- body): the heading of body x, counter-
/// clockwise from world x (east), in (-pi, pi].
double yawOf(const Eigen::Quaterniond& orientation);

/// The level orientation with the given yaw.
Eigen::Quaterniond yawOnly(double yaw_rad);

/// 6-DoF rigid-body quadrotor. See the file comment for the model.
class Quadrotor {
 public:
  /// Starts at the given state. A vehicle placed at or below the ground with
  /// no upward velocity starts landed (on the ground, level); the battery
  /// voltage is derived from the state of charge.
  explicit Quadrotor(QuadrotorParams params = {}, const QuadrotorState& initial = {});

  /// Advances the state by `dt_s` seconds under the given motor commands
  /// (held constant over the step).
  void step(double dt_s, const MotorCommands& commands);

  const QuadrotorState& state() const { return state_; }
  const QuadrotorParams& params() const { return params_; }

  /// Replaces the state (teleport, respawn). `crashed` follows
  /// `state.crash_cause` (a default state is not crashed); the landed flag and
  /// the voltage are derived as in the constructor.
  void reset(const QuadrotorState& state);

  /// Velocity of the air in the world frame (m/s); drag acts on the velocity
  /// relative to it.
  void setWindVelocity(const Eigen::Vector3d& wind_m_s) { wind_m_s_ = wind_m_s; }
  const Eigen::Vector3d& windVelocity() const { return wind_m_s_; }

  /// A force in the world frame applied at the centre of mass until changed
  /// (N): gusts, a tether, a push.
  void setExternalForce(const Eigen::Vector3d& force_n) { external_force_n_ = force_n; }

  /// Fault injection: the fraction of its nominal thrust and torque that
  /// motor `motor` produces, clamped to [0, 1]; 0 is a dead motor (stops
  /// spinning). The autopilot is not told.
  void setMotorEfficiency(int motor, double efficiency);
  double motorEfficiency(int motor) const { return efficiency_[motor]; }

  /// Fault injection / scenario setup: sets the battery's state of charge.
  void setBatteryStateOfCharge(double soc);

  /// Static geometry the vehicle crashes into (not owned; may be null).
  void setCollisionWorld(const world::CollisionWorld* world) { collision_world_ = world; }

  /// Specific force measured by an ideal accelerometer, body frame (m/s^2):
  /// R^T (a + g z). (0, 0, g) when resting level.
  Eigen::Vector3d specificForceBody() const;

  /// Thrust currently produced by all motors along body z (N).
  double collectiveThrustN() const;

  /// Open-circuit voltage of the battery at a state of charge (V).
  double openCircuitVoltage(double soc) const;

 private:
  void updateMotors(double dt_s, const MotorCommands& commands);
  void updateBattery(double dt_s);
  void crash(CrashCause cause);
  void deriveContactAndBattery();

  QuadrotorParams params_;
  QuadrotorState state_;
  Eigen::Vector3d wind_m_s_ = Eigen::Vector3d::Zero();
  Eigen::Vector3d external_force_n_ = Eigen::Vector3d::Zero();
  std::array<double, kMotorCount> efficiency_{1.0, 1.0, 1.0, 1.0};
  const world::CollisionWorld* collision_world_ = nullptr;

  // Cached per-step constants.
  Eigen::Vector3d inverse_inertia_;
  double cached_dt_s_ = -1.0;
  double motor_alpha_ = 0.0;  // 1 - exp(-dt / tau)
};

}  // namespace behaviorlib::sim
