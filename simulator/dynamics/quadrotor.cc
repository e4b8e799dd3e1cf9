#include "simulator/dynamics/quadrotor.h"

#include <algorithm>
#include <cmath>
#include <utility>

namespace behaviorlib::sim {
namespace {

// Rotation by the rotation vector `theta` (rad) as a unit quaternion.
Eigen::Quaterniond expMap(const Eigen::Vector3d& theta) {
  const double angle = theta.norm();
  if (angle < 1e-9) {
    // Second-order accurate; renormalised by the caller.
    return Eigen::Quaterniond(1.0, 0.5 * theta.x(), 0.5 * theta.y(), 0.5 * theta.z());
  }
  const double half = 0.5 * angle;
  const Eigen::Vector3d axis_sin = theta * (std::sin(half) / angle);
  return Eigen::Quaterniond(std::cos(half), axis_sin.x(), axis_sin.y(), axis_sin.z());
}

}  // namespace

double yawOf(const Eigen::Quaterniond& q) {
  return std::atan2(2.0 * (q.w() * q.z() + q.x() * q.y()),
                    1.0 - 2.0 * (q.y() * q.y() + q.z() * q.z()));
}

Eigen::Quaterniond yawOnly(double yaw_rad) {
  return Eigen::Quaterniond(std::cos(0.5 * yaw_rad), 0.0, 0.0, std::sin(0.5 * yaw_rad));
}

Quadrotor::Quadrotor(QuadrotorParams params, const QuadrotorState& initial)
    : params_(std::move(params)), state_(initial) {
  inverse_inertia_ = params_.inertia_kg_m2.cwiseInverse();
  deriveContactAndBattery();
}

void Quadrotor::reset(const QuadrotorState& state) {
  state_ = state;
  deriveContactAndBattery();
}

void Quadrotor::deriveContactAndBattery() {
  state_.orientation.normalize();
  state_.battery_soc = std::clamp(state_.battery_soc, 0.0, 1.0);
  if (!params_.simulate_battery) state_.battery_soc = 1.0;
  state_.battery_voltage_v = openCircuitVoltage(state_.battery_soc);
  state_.battery_power_w = 0.0;
  state_.crashed = state_.crash_cause != CrashCause::kNone;
  state_.landed = false;
  if (!state_.crashed && state_.position_m.z() <= params_.ground_z_m &&
      state_.velocity_m_s.z() <= 0.0) {
    state_.landed = true;
    state_.position_m.z() = params_.ground_z_m;
    state_.velocity_m_s.setZero();
    state_.angular_velocity_rad_s.setZero();
    state_.orientation = yawOnly(yawOf(state_.orientation));
  }
  state_.acceleration_m_s2.setZero();
}

double Quadrotor::openCircuitVoltage(double soc) const {
  if (!params_.simulate_battery) return params_.battery_full_voltage_v;
  return params_.battery_empty_voltage_v +
         (params_.battery_full_voltage_v - params_.battery_empty_voltage_v) * soc;
}

void Quadrotor::setMotorEfficiency(int motor, double efficiency) {
  if (motor < 0 || motor >= kMotorCount) return;
  efficiency_[motor] = std::clamp(efficiency, 0.0, 1.0);
}

void Quadrotor::setBatteryStateOfCharge(double soc) {
  state_.battery_soc = params_.simulate_battery ? std::clamp(soc, 0.0, 1.0) : 1.0;
  state_.battery_voltage_v = openCircuitVoltage(state_.battery_soc);
}

double Quadrotor::collectiveThrustN() const {
  double thrust = 0.0;
  for (int i = 0; i < kMotorCount; ++i) {
    const double w = state_.motor_speeds_rad_s[i];
    thrust += efficiency_[i] * params_.thrust_coefficient_n_s2 * w * w;
  }
  return thrust;
}

Eigen::Vector3d Quadrotor::specificForceBody() const {
  const Eigen::Vector3d f =
      state_.acceleration_m_s2 + Eigen::Vector3d(0.0, 0.0, params_.gravity_m_s2);
  return state_.orientation.conjugate() * f;
}

void Quadrotor::updateMotors(double dt_s, const MotorCommands& commands) {
  if (dt_s != cached_dt_s_) {
    cached_dt_s_ = dt_s;
    motor_alpha_ = params_.motor_time_constant_s > 0.0
                       ? 1.0 - std::exp(-dt_s / params_.motor_time_constant_s)
                       : 1.0;
  }
  // The speed a full command reaches scales with the battery's terminal
  // voltage; an empty battery (ESC cut-off) or a crash stops the motors.
  const bool powered = !state_.crashed && state_.battery_soc > 0.0;
  const double speed_scale =
      params_.max_motor_speed_rad_s * state_.battery_voltage_v / params_.battery_full_voltage_v;
  for (int i = 0; i < kMotorCount; ++i) {
    double target = 0.0;
    if (powered && efficiency_[i] > 0.0) {
      target = std::clamp(commands[i], 0.0, 1.0) * speed_scale;
    }
    double& w = state_.motor_speeds_rad_s[i];
    w += (target - w) * motor_alpha_;
  }
}

void Quadrotor::updateBattery(double dt_s) {
  // Shaft power of a propeller is its torque times its speed: k_m w^3.
  double shaft_power_w = 0.0;
  for (int i = 0; i < kMotorCount; ++i) {
    const double w = state_.motor_speeds_rad_s[i];
    shaft_power_w += efficiency_[i] * params_.torque_coefficient_n_m_s2 * w * w * w;
  }
  const double power_w = shaft_power_w / params_.propulsion_efficiency + params_.avionics_power_w;
  state_.battery_power_w = power_w;
  if (!params_.simulate_battery) {
    state_.battery_voltage_v = params_.battery_full_voltage_v;
    return;
  }
  const double capacity_j = params_.battery_capacity_wh * 3600.0;
  state_.battery_soc =
      capacity_j > 0.0 ? std::max(0.0, state_.battery_soc - power_w * dt_s / capacity_j) : 0.0;
  const double open_circuit_v = openCircuitVoltage(state_.battery_soc);
  const double current_a = power_w / open_circuit_v;
  state_.battery_voltage_v =
      std::max(0.0, open_circuit_v - current_a * params_.battery_internal_resistance_ohm);
}

void Quadrotor::crash(CrashCause cause) {
  state_.crashed = true;
  state_.crash_cause = cause;
  state_.landed = false;
  state_.velocity_m_s.setZero();
  state_.angular_velocity_rad_s.setZero();
  state_.acceleration_m_s2.setZero();
}

void Quadrotor::step(double dt_s, const MotorCommands& commands) {
  if (dt_s <= 0.0) return;
  updateMotors(dt_s, commands);
  if (state_.crashed) {
    // Stays put; the motors spin down and the avionics keep drawing.
    updateBattery(dt_s);
    return;
  }

  // Forces and torques with the motor speeds at the end of the step
  // (semi-implicit: the new speeds act over the step).
  const double kf = params_.thrust_coefficient_n_s2;
  const double km = params_.torque_coefficient_n_m_s2;
  const double d = params_.arm_length_m / std::sqrt(2.0);
  double thrust_n = 0.0;
  Eigen::Vector3d torque_n_m = -params_.angular_drag_n_m_s_rad * state_.angular_velocity_rad_s;
  for (int i = 0; i < kMotorCount; ++i) {
    const double w2 = state_.motor_speeds_rad_s[i] * state_.motor_speeds_rad_s[i];
    const double t = efficiency_[i] * kf * w2;
    thrust_n += t;
    // r x (0, 0, T) = (r_y T, -r_x T, 0); reaction torque opposes the spin.
    torque_n_m.x() += kMotorYSign[i] * d * t;
    torque_n_m.y() -= kMotorXSign[i] * d * t;
    torque_n_m.z() -= kMotorSpin[i] * efficiency_[i] * km * w2;
  }

  const Eigen::Matrix3d rotation = state_.orientation.toRotationMatrix();  // world <- body
  const Eigen::Vector3d air_body = rotation.transpose() * (state_.velocity_m_s - wind_m_s_);
  const Eigen::Vector3d drag_body =
      -(params_.linear_drag_n_s_m.cwiseProduct(air_body) +
        params_.quadratic_drag_n_s2_m2.cwiseProduct(air_body.cwiseAbs().cwiseProduct(air_body)));
  Eigen::Vector3d force_world =
      rotation * (drag_body + Eigen::Vector3d(0.0, 0.0, thrust_n)) + external_force_n_;
  force_world.z() -= params_.mass_kg * params_.gravity_m_s2;

  if (state_.landed) {
    if (force_world.z() <= 0.0) {
      // The ground carries the rest: no sinking, no sliding, no tilting.
      state_.velocity_m_s.setZero();
      state_.angular_velocity_rad_s.setZero();
      state_.acceleration_m_s2.setZero();
      updateBattery(dt_s);
      return;
    }
    state_.landed = false;  // lift-off
  }

  // Translation: semi-implicit Euler.
  const Eigen::Vector3d acceleration = force_world / params_.mass_kg;
  state_.acceleration_m_s2 = acceleration;
  state_.velocity_m_s += acceleration * dt_s;
  state_.position_m += state_.velocity_m_s * dt_s;

  // Rotation: Euler's equations, then the exponential map with the new rate.
  Eigen::Vector3d& w = state_.angular_velocity_rad_s;
  const Eigen::Vector3d angular_momentum = params_.inertia_kg_m2.cwiseProduct(w);
  w += inverse_inertia_.cwiseProduct(torque_n_m - w.cross(angular_momentum)) * dt_s;
  state_.orientation = state_.orientation * expMap(w * dt_s);
  state_.orientation.normalize();

  // Ground contact.
  if (state_.position_m.z() <= params_.ground_z_m && state_.velocity_m_s.z() <= 0.0) {
    const double impact_speed = -state_.velocity_m_s.z();
    const Eigen::Vector3d body_z = state_.orientation * Eigen::Vector3d::UnitZ();
    const double tilt = std::acos(std::clamp(body_z.z(), -1.0, 1.0));
    state_.position_m.z() = params_.ground_z_m;
    if (impact_speed > params_.crash_speed_m_s) {
      crash(CrashCause::kHardImpact);
    } else if (tilt > params_.crash_tilt_rad) {
      crash(CrashCause::kTipOver);
    } else {
      state_.landed = true;
      state_.velocity_m_s.setZero();
      state_.angular_velocity_rad_s.setZero();
      state_.acceleration_m_s2.setZero();
      state_.orientation = yawOnly(yawOf(state_.orientation));
    }
  }

  if (!state_.crashed && collision_world_ != nullptr &&
      collision_world_->collides(state_.position_m, params_.collision_radius_m)) {
    crash(CrashCause::kCollision);
  }
  updateBattery(dt_s);
}

}  // namespace behaviorlib::sim
