#include "simulator/dynamics/autopilot.h"

#include <algorithm>
#include <cmath>
#include <numbers>
#include <type_traits>

namespace behaviorlib::sim {
namespace {

constexpr std::size_t kVelocityMode = 3;
constexpr std::size_t kPositionMode = 4;
static_assert(std::is_same_v<std::variant_alternative_t<kVelocityMode, Setpoint>, VelocityYawRate>);
static_assert(std::is_same_v<std::variant_alternative_t<kPositionMode, Setpoint>, PositionYaw>);

double wrapAngle(double a) { return std::remainder(a, 2.0 * std::numbers::pi); }

// P control of an angle error that turns into a square-root law beyond the
// error at which P would ask for more than `accel` to stop: the rate from
// which a deceleration of `accel` stops exactly at the target.
double sqrtController(double error, double gain, double accel) {
  if (gain <= 0.0) return 0.0;
  if (accel <= 0.0) return gain * error;
  const double linear = accel / (gain * gain);
  if (std::abs(error) <= linear) return gain * error;
  return std::copysign(std::sqrt(2.0 * accel * (std::abs(error) - 0.5 * linear)), error);
}

// The rotation (world <- body) whose body z is `body_z` (unit) and whose body
// x points as close to the heading `yaw_rad` as the tilt allows.
Eigen::Quaterniond attitudeFromThrustAndYaw(const Eigen::Vector3d& body_z, double yaw_rad) {
  const Eigen::Vector3d heading(std::cos(yaw_rad), std::sin(yaw_rad), 0.0);
  Eigen::Vector3d body_y = body_z.cross(heading);
  if (body_y.squaredNorm() < 1e-12) {
    // Thrust horizontal and along the heading: any body y will do.
    body_y = body_z.cross(Eigen::Vector3d::UnitZ());
    if (body_y.squaredNorm() < 1e-12) body_y = Eigen::Vector3d::UnitY();
  }
  body_y.normalize();
  const Eigen::Vector3d body_x = body_y.cross(body_z);
  Eigen::Matrix3d r;
  r.col(0) = body_x;
  r.col(1) = body_y;
  r.col(2) = body_z;
  return Eigen::Quaterniond(r).normalized();
}

// Drag force the model predicts (world frame, N) at a velocity relative to
// the air, with the vehicle at `rotation` (world <- body).
Eigen::Vector3d predictedDrag(const QuadrotorParams& p, const Eigen::Matrix3d& rotation,
                              const Eigen::Vector3d& velocity_world) {
  const Eigen::Vector3d v = rotation.transpose() * velocity_world;
  const Eigen::Vector3d drag =
      -(p.linear_drag_n_s_m.cwiseProduct(v) +
        p.quadratic_drag_n_s2_m2.cwiseProduct(v.cwiseAbs().cwiseProduct(v)));
  return rotation * drag;
}

}  // namespace

// --- Mixer -------------------------------------------------------------------

Mixer::Mixer(const QuadrotorParams& params) {
  const double d = params.arm_length_m / std::sqrt(2.0);
  const double yaw_per_thrust = params.torque_coefficient_n_m_s2 / params.thrust_coefficient_n_s2;
  for (int i = 0; i < kMotorCount; ++i) {
    allocation_(0, i) = 1.0;
    allocation_(1, i) = kMotorYSign[i] * d;   // roll: r_y T
    allocation_(2, i) = -kMotorXSign[i] * d;  // pitch: -r_x T
    allocation_(3, i) = -kMotorSpin[i] * yaw_per_thrust;
  }
  inverse_ = allocation_.inverse();
}

std::array<double, kMotorCount> Mixer::allocate(double thrust_n, const Eigen::Vector3d& torque_n_m,
                                                double max_motor_thrust_n) const {
  const double t_max = std::max(0.0, max_motor_thrust_n);
  const Eigen::Vector4d roll_pitch =
      inverse_.col(1) * torque_n_m.x() + inverse_.col(2) * torque_n_m.y();
  const Eigen::Vector4d yaw = inverse_.col(3) * torque_n_m.z();
  const Eigen::Vector4d collective = inverse_.col(0) * std::max(0.0, thrust_n);

  // 1. Roll and pitch: scaled down only if their spread exceeds the range.
  Eigen::Vector4d rp = roll_pitch;
  double spread = rp.maxCoeff() - rp.minCoeff();
  if (spread > t_max) {
    rp *= spread > 0.0 ? t_max / spread : 0.0;
  }
  // 2. Collective: shifted as little as possible to fit every motor.
  // (All entries of `collective` are equal for the symmetric X layout.)
  const double wanted = collective(0);
  const double low = -rp.minCoeff();
  const double high = t_max - rp.maxCoeff();
  const double shift = std::clamp(wanted, low, std::max(low, high));
  Eigen::Vector4d base = rp.array() + shift;
  // 3. Yaw: the largest fraction that fits.
  double k = 1.0;
  for (int i = 0; i < kMotorCount; ++i) {
    if (yaw(i) > 1e-12) {
      k = std::min(k, (t_max - base(i)) / yaw(i));
    } else if (yaw(i) < -1e-12) {
      k = std::min(k, -base(i) / yaw(i));
    }
  }
  k = std::clamp(k, 0.0, 1.0);
  std::array<double, kMotorCount> out{};
  for (int i = 0; i < kMotorCount; ++i) {
    out[i] = std::clamp(base(i) + k * yaw(i), 0.0, t_max);
  }
  return out;
}

Eigen::Vector4d Mixer::wrench(const std::array<double, kMotorCount>& thrusts_n) const {
  return allocation_ * Eigen::Vector4d(thrusts_n[0], thrusts_n[1], thrusts_n[2], thrusts_n[3]);
}

// --- Autopilot ---------------------------------------------------------------

Autopilot::Autopilot(const QuadrotorParams& vehicle, const AutopilotParams& params)
    : vehicle_(vehicle), params_(params), mixer_(vehicle) {
  attitude_gain_ = params_.attitude_p;
  yaw_weight_ = params_.attitude_p.x() > 0.0
                    ? std::clamp(params_.attitude_p.z() / params_.attitude_p.x(), 0.0, 1.0)
                    : 1.0;
  attitude_gain_.z() = params_.attitude_p.x();
}

void Autopilot::reset() {
  status_ = AutopilotStatus{};
  last_mode_ = 0;
  yaw_reference_rad_ = 0.0;
  velocity_integral_.setZero();
  rate_integral_.setZero();
  have_last_rates_ = false;
  torque_saturation_.setZero();
}

MotorCommands Autopilot::update(const QuadrotorState& state, const Setpoint& setpoint,
                                double dt_s) {
  const std::size_t mode = setpoint.index();
  if (state.crashed || std::holds_alternative<Idle>(setpoint) || dt_s <= 0.0) {
    reset();
    return MotorCommands{};
  }
  if (mode != last_mode_) {
    // Position and velocity modes share the velocity loop and its integrator.
    const bool from_velocity_level = last_mode_ == kVelocityMode || last_mode_ == kPositionMode;
    if (!from_velocity_level) velocity_integral_.setZero();
    yaw_reference_rad_ = yawOf(state.orientation);
    last_mode_ = mode;
  }

  const double max_thrust = vehicle_.maxThrustN();
  double thrust_n = 0.0;
  Eigen::Vector3d rates = Eigen::Vector3d::Zero();
  if (const auto* s = std::get_if<ThrustRates>(&setpoint)) {
    thrust_n = std::clamp(s->thrust_ratio, 0.0, 1.0) * max_thrust;
    rates = s->rates_rad_s.cwiseMax(-params_.max_rates_rad_s).cwiseMin(params_.max_rates_rad_s);
    status_.velocity_setpoint_m_s.setZero();
    status_.attitude_setpoint = state.orientation;
  } else if (const auto* s = std::get_if<AttitudeThrust>(&setpoint)) {
    thrust_n = std::clamp(s->thrust_ratio, 0.0, 1.0) * max_thrust;
    status_.attitude_setpoint = s->orientation.normalized();
    rates = attitudeLoop(state, status_.attitude_setpoint, 0.0);
  } else if (const auto* s = std::get_if<VelocityYawRate>(&setpoint)) {
    const double yaw = yawOf(state.orientation);
    if (state.landed) {
      yaw_reference_rad_ = yaw;
    } else {
      yaw_reference_rad_ = wrapAngle(yaw_reference_rad_ + s->yaw_rate_rad_s * dt_s);
      const double error = wrapAngle(yaw_reference_rad_ - yaw);
      if (std::abs(error) > params_.max_yaw_error_rad) {
        yaw_reference_rad_ = wrapAngle(yaw + std::copysign(params_.max_yaw_error_rad, error));
      }
    }
    status_.velocity_setpoint_m_s = s->velocity_m_s;
    velocityLoop(state, s->velocity_m_s, yaw_reference_rad_, dt_s, &status_.attitude_setpoint,
                 &thrust_n);
    rates = attitudeLoop(state, status_.attitude_setpoint, s->yaw_rate_rad_s);
  } else if (const auto* s = std::get_if<PositionYaw>(&setpoint)) {
    status_.velocity_setpoint_m_s = positionLoop(state, s->position_m);
    velocityLoop(state, status_.velocity_setpoint_m_s, s->yaw_rad, dt_s, &status_.attitude_setpoint,
                 &thrust_n);
    rates = attitudeLoop(state, status_.attitude_setpoint, 0.0);
  }
  status_.rate_setpoint_rad_s = rates;
  status_.thrust_n = thrust_n;
  status_.torque_n_m = rateLoop(state, rates, dt_s);
  return mix(state, thrust_n, status_.torque_n_m);
}

Eigen::Vector3d Autopilot::positionLoop(const QuadrotorState& state,
                                        const Eigen::Vector3d& position_m) {
  Eigen::Vector3d v = params_.position_p.cwiseProduct(position_m - state.position_m);
  const double horizontal = v.head<2>().norm();
  if (horizontal > params_.max_horizontal_speed_m_s) {
    v.head<2>() *= params_.max_horizontal_speed_m_s / horizontal;
  }
  v.z() = std::clamp(v.z(), -params_.max_descent_rate_m_s, params_.max_climb_rate_m_s);
  return v;
}

void Autopilot::velocityLoop(const QuadrotorState& state, const Eigen::Vector3d& velocity_m_s,
                             double yaw_rad, double dt_s, Eigen::Quaterniond* attitude,
                             double* thrust_n) {
  const Eigen::Vector3d error = velocity_m_s - state.velocity_m_s;
  const Eigen::Vector3d acceleration =
      params_.velocity_p.cwiseProduct(error) + params_.velocity_i.cwiseProduct(velocity_integral_);
  status_.acceleration_setpoint_m_s2 = acceleration;

  // The force the thrust must supply: m (a + g z) minus the drag the model
  // predicts (the wind is unknown to the autopilot; the integrator takes it).
  const double m = vehicle_.mass_kg;
  Eigen::Vector3d force = m * (acceleration + Eigen::Vector3d(0.0, 0.0, vehicle_.gravity_m_s2));
  const Eigen::Matrix3d rotation = state.orientation.toRotationMatrix();
  if (params_.drag_feedforward) force -= predictedDrag(vehicle_, rotation, state.velocity_m_s);

  // Limits: vertical thrust within [min, max], tilt within max_tilt, the
  // whole vector within max.
  const double min_thrust = params_.min_thrust_ratio * vehicle_.maxThrustN();
  const double max_thrust = params_.max_thrust_ratio * vehicle_.maxThrustN();
  bool vertical_saturated = false;
  bool horizontal_saturated = false;
  if (force.z() < min_thrust || force.z() > max_thrust) {
    force.z() = std::clamp(force.z(), min_thrust, max_thrust);
    vertical_saturated = true;
  }
  const double max_horizontal =
      std::min(force.z() * std::tan(params_.max_tilt_rad),
               std::sqrt(std::max(0.0, max_thrust * max_thrust - force.z() * force.z())));
  const double horizontal = force.head<2>().norm();
  if (horizontal > max_horizontal) {
    force.head<2>() *= max_horizontal / horizontal;
    horizontal_saturated = true;
  }

  // Integrate (conditionally: not on the ground, not while saturated).
  if (!state.landed) {
    const double band = params_.velocity_integral_error_limit_m_s;
    Eigen::Vector3d step = error.cwiseMax(-band).cwiseMin(band) * dt_s;
    if (horizontal_saturated) step.head<2>().setZero();
    if (vertical_saturated) step.z() = 0.0;
    velocity_integral_ += step;
    for (int i = 0; i < 3; ++i) {
      if (params_.velocity_i(i) > 0.0) {
        const double limit = params_.velocity_integral_limit_m_s2 / params_.velocity_i(i);
        velocity_integral_(i) = std::clamp(velocity_integral_(i), -limit, limit);
      }
    }
  }

  const Eigen::Vector3d body_z = force.normalized();
  *attitude = attitudeFromThrustAndYaw(body_z, yaw_rad);
  // Thrust along the present body z, so that a vehicle still tilting does not
  // climb or sink on its way to the new attitude.
  *thrust_n = std::clamp(force.dot(rotation.col(2)), min_thrust, max_thrust);
}

Eigen::Vector3d Autopilot::attitudeLoop(const QuadrotorState& state,
                                        const Eigen::Quaterniond& attitude,
                                        double yaw_rate_rad_s) const {
  // Tilt first, then yaw weighted by yaw_weight_ (PX4's AttitudeControl).
  const Eigen::Quaterniond& q = state.orientation;
  Eigen::Quaterniond qd = attitude;
  const Eigen::Vector3d e_z = q * Eigen::Vector3d::UnitZ();
  const Eigen::Vector3d e_z_d = qd * Eigen::Vector3d::UnitZ();
  Eigen::Quaterniond qd_red = Eigen::Quaterniond::FromTwoVectors(e_z, e_z_d) * q;
  if (std::abs(qd_red.x()) > 1.0 - 1e-5 || std::abs(qd_red.y()) > 1.0 - 1e-5) {
    // Thrust exactly opposite: full attitude control (no reduced attitude).
    qd_red = qd;
  } else {
    Eigen::Quaterniond q_mix = qd_red.conjugate() * qd;
    if (q_mix.w() < 0.0) q_mix.coeffs() = -q_mix.coeffs();
    const double w = std::clamp(q_mix.w(), -1.0, 1.0);
    const double z = std::clamp(q_mix.z(), -1.0, 1.0);
    qd = qd_red * Eigen::Quaterniond(std::cos(yaw_weight_ * std::acos(w)), 0.0, 0.0,
                                     std::sin(yaw_weight_ * std::asin(z)));
  }
  Eigen::Quaterniond qe = q.conjugate() * qd;
  if (qe.w() < 0.0) qe.coeffs() = -qe.coeffs();
  // Small-angle rotation vector of the error; the yaw part is weighted by
  // yaw_weight_ (the weight is taken out again for the square-root law).
  const Eigen::Vector3d error = 2.0 * qe.vec();
  const Eigen::Vector3d& accel = params_.attitude_accel_limit_rad_s2;
  Eigen::Vector3d rates(sqrtController(error.x(), attitude_gain_.x(), accel.x()),
                        sqrtController(error.y(), attitude_gain_.y(), accel.y()),
                        yaw_weight_ > 1e-6 ? sqrtController(error.z() / yaw_weight_,
                                                            params_.attitude_p.z(), accel.z())
                                           : 0.0);
  // Yaw-rate feed-forward: a world-z rate seen in the body frame.
  rates += yaw_rate_rad_s * (q.conjugate() * Eigen::Vector3d::UnitZ());
  return rates.cwiseMax(-params_.max_rates_rad_s).cwiseMin(params_.max_rates_rad_s);
}

Eigen::Vector3d Autopilot::rateLoop(const QuadrotorState& state, const Eigen::Vector3d& rates_rad_s,
                                    double dt_s) {
  const Eigen::Vector3d& w = state.angular_velocity_rad_s;
  const Eigen::Vector3d error = rates_rad_s - w;
  if (state.landed) {
    rate_integral_.setZero();
  } else {
    for (int i = 0; i < 3; ++i) {
      // Conditional integration: not further into a saturated direction.
      if ((error(i) > 0.0 && torque_saturation_(i) > 0) ||
          (error(i) < 0.0 && torque_saturation_(i) < 0)) {
        continue;
      }
      rate_integral_(i) += error(i) * dt_s;
    }
    rate_integral_ = rate_integral_.cwiseMax(-params_.rate_integral_limit_rad)
                         .cwiseMin(params_.rate_integral_limit_rad);
  }
  // Derivative on the measurement (no kick on setpoint steps).
  const Eigen::Vector3d derivative =
      have_last_rates_ ? Eigen::Vector3d((w - last_rates_) / dt_s) : Eigen::Vector3d::Zero();
  last_rates_ = w;
  have_last_rates_ = true;
  const Eigen::Vector3d angular_acceleration = params_.rate_p.cwiseProduct(error) +
                                               params_.rate_i.cwiseProduct(rate_integral_) -
                                               params_.rate_d.cwiseProduct(derivative);
  const Eigen::Vector3d& inertia = vehicle_.inertia_kg_m2;
  return inertia.cwiseProduct(angular_acceleration) + w.cross(inertia.cwiseProduct(w));
}

MotorCommands Autopilot::mix(const QuadrotorState& state, double thrust_n,
                             const Eigen::Vector3d& torque) {
  // The speed a full command reaches at the measured battery voltage.
  const double voltage_ratio =
      std::clamp(state.battery_voltage_v / vehicle_.battery_full_voltage_v, 1e-3, 2.0);
  const double full_speed = vehicle_.max_motor_speed_rad_s * voltage_ratio;
  const double kf = vehicle_.thrust_coefficient_n_s2;
  status_.motor_thrusts_n = mixer_.allocate(thrust_n, torque, kf * full_speed * full_speed);
  const Eigen::Vector4d delivered = mixer_.wrench(status_.motor_thrusts_n);
  for (int i = 0; i < 3; ++i) {
    const double shortfall = torque(i) - delivered(i + 1);
    const double tolerance = 1e-9 + 1e-6 * std::abs(torque(i));
    torque_saturation_(i) = shortfall > tolerance ? 1 : (shortfall < -tolerance ? -1 : 0);
  }
  MotorCommands commands{};
  for (int i = 0; i < kMotorCount; ++i) {
    commands[i] = std::clamp(std::sqrt(status_.motor_thrusts_n[i] / kf) / full_speed, 0.0, 1.0);
  }
  return commands;
}

}  // namespace behaviorlib::sim
