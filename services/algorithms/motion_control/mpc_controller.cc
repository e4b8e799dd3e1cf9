#include "behaviorlib/motion_control/mpc_controller.h"

#include <algorithm>
#include <cmath>

namespace behaviorlib::motion {

MpcMotionController::MpcMotionController(VehicleModel model, MpcParams params)
    : model_(model), params_(params) {
  params_.horizon_steps = std::clamp(params_.horizon_steps, 2, 200);
  buildCondensedModel();
  // Input box: per-axis horizontal limit that keeps the combined tilt within
  // the maximum; vertical limits from the thrust range.
  const double g = model_.gravity_m_s2;
  const double horizontal = g * std::tan(model_.max_tilt_rad) / std::sqrt(2.0);
  const double thrust_accel = model_.max_thrust_n / model_.mass_kg;
  lower_ = {-horizontal, -horizontal, model_.min_thrust_ratio * thrust_accel - g};
  upper_ = {horizontal, horizontal,
            model_.max_thrust_ratio * thrust_accel * std::cos(model_.max_tilt_rad) - g};
  reset();
}

void MpcMotionController::reset() {
  for (auto& axis : axes_) {
    axis.u = Eigen::VectorXd::Zero(params_.horizon_steps);
    axis.state.setZero();
    axis.last_u = 0.0;
    axis.disturbance = 0.0;
    axis.have_prediction = false;
  }
  yaw_hold_set_ = false;
  info_ = {};
}

void MpcMotionController::buildCondensedModel() {
  const int n = params_.horizon_steps;
  const double h = params_.step_s;
  const double alpha = std::exp(-h / std::max(params_.acceleration_lag_s, 1e-3));
  a_ << 1.0, h, 0.5 * h * h, 0.0, 1.0, h, 0.0, 0.0, alpha;
  b_ << 0.0, 0.0, 1.0 - alpha;

  // x_k = A^k x0 + sum_{j<k} A^{k-1-j} B u_j, k = 1..N.
  phi_p_ = Eigen::MatrixXd::Zero(n, 3);
  phi_v_ = Eigen::MatrixXd::Zero(n, 3);
  gamma_p_ = Eigen::MatrixXd::Zero(n, n);
  gamma_v_ = Eigen::MatrixXd::Zero(n, n);
  // A constant disturbance d adds h^2/2 d to p and h d to v every step.
  dist_p_ = Eigen::VectorXd::Zero(n);
  dist_v_ = Eigen::VectorXd::Zero(n);
  {
    double p = 0, v = 0;
    for (int k = 0; k < n; ++k) {
      p += h * v + 0.5 * h * h;
      v += h;
      dist_p_(k) = p;
      dist_v_(k) = v;
    }
  }
  std::vector<Eigen::Matrix3d> powers(n + 1);
  powers[0] = Eigen::Matrix3d::Identity();
  for (int k = 1; k <= n; ++k) powers[k] = a_ * powers[k - 1];
  for (int k = 1; k <= n; ++k) {
    phi_p_.row(k - 1) = powers[k].row(0);
    phi_v_.row(k - 1) = powers[k].row(1);
    for (int j = 0; j < k; ++j) {
      const Eigen::Vector3d effect = powers[k - 1 - j] * b_;
      gamma_p_(k - 1, j) = effect(0);
      gamma_v_(k - 1, j) = effect(1);
    }
  }
  // Hessian (the cost is 1/2 U' H U + f' U up to a constant).
  Eigen::MatrixXd difference = Eigen::MatrixXd::Identity(n, n);  // D U = (u_k - u_{k-1})
  for (int k = 1; k < n; ++k) difference(k, k - 1) = -1.0;
  hessian_ = 2.0 * (params_.position_weight * gamma_p_.transpose() * gamma_p_ +
                    params_.velocity_weight * gamma_v_.transpose() * gamma_v_ +
                    params_.input_weight * Eigen::MatrixXd::Identity(n, n) +
                    params_.input_rate_weight * difference.transpose() * difference);
  const double lipschitz =
      Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd>(hessian_, Eigen::EigenvaluesOnly)
          .eigenvalues()
          .maxCoeff();
  step_size_ = 1.0 / lipschitz;
}

Eigen::Vector3d MpcMotionController::referenceAt(const StateEstimate& state,
                                                 const MotionReference& reference, int axis,
                                                 int k) const {
  const double t = k * params_.step_s;
  const ReferencePoint& now = reference.point;
  switch (reference.mode) {
    case MotionReference::Mode::kPosition:
      return {now.position_m[axis], 0.0, 0.0};
    case MotionReference::Mode::kVelocity:
      return {state.position_m[axis] + now.velocity_m_s[axis] * t, now.velocity_m_s[axis], 0.0};
    case MotionReference::Mode::kTrajectory: {
      if (reference.horizon.empty() || !(reference.horizon_step_s > 0.0)) {
        // Extrapolate the current point with its velocity.
        return {now.position_m[axis] + now.velocity_m_s[axis] * t, now.velocity_m_s[axis],
                now.acceleration_m_s2[axis]};
      }
      // horizon[i] is the reference at (i + 1) * horizon_step_s from now.
      const double index = t / reference.horizon_step_s - 1.0;
      const int last = static_cast<int>(reference.horizon.size()) - 1;
      auto sample = [&](int i) -> Eigen::Vector3d {
        const ReferencePoint& p = i < 0 ? now : reference.horizon[std::min(i, last)];
        return {p.position_m[axis], p.velocity_m_s[axis], p.acceleration_m_s2[axis]};
      };
      if (index >= last) return sample(last);
      const int i0 = static_cast<int>(std::floor(index));
      const double w = index - i0;
      return (1.0 - w) * sample(i0) + w * sample(i0 + 1);
    }
  }
  return Eigen::Vector3d::Zero();
}

int MpcMotionController::solveAxis(Axis& axis, const Eigen::VectorXd& p_ref,
                                   const Eigen::VectorXd& v_ref, const Eigen::VectorXd& a_ref,
                                   double lower, double upper, bool* converged) {
  const int n = params_.horizon_steps;
  // Gradient at U: H U + f.
  const Eigen::VectorXd p_free = phi_p_ * axis.state + dist_p_ * axis.disturbance;
  const Eigen::VectorXd v_free = phi_v_ * axis.state + dist_v_ * axis.disturbance;
  Eigen::VectorXd f = 2.0 * (params_.position_weight * gamma_p_.transpose() * (p_free - p_ref) +
                             params_.velocity_weight * gamma_v_.transpose() * (v_free - v_ref) -
                             params_.input_weight * a_ref);
  f(0) -= 2.0 * params_.input_rate_weight * axis.last_u;  // (u_0 - u_prev)^2

  // Warm start: the previous plan shifted by one step.
  Eigen::VectorXd u(n);
  u.head(n - 1) = axis.u.tail(n - 1);
  u(n - 1) = axis.u(n - 1);
  u = u.cwiseMax(lower).cwiseMin(upper);
  Eigen::VectorXd y = u, u_prev = u;
  double t = 1.0;
  int iteration = 0;
  *converged = false;
  for (; iteration < params_.max_iterations; ++iteration) {
    const Eigen::VectorXd gradient = hessian_ * y + f;
    u = (y - step_size_ * gradient).cwiseMax(lower).cwiseMin(upper);
    const double t_next = 0.5 * (1.0 + std::sqrt(1.0 + 4.0 * t * t));
    y = u + ((t - 1.0) / t_next) * (u - u_prev);
    t = t_next;
    const double change = (u - u_prev).lpNorm<Eigen::Infinity>();
    u_prev = u;
    if (change < params_.tolerance) {
      *converged = true;
      ++iteration;
      break;
    }
  }
  axis.u = u;
  return iteration;
}

AttitudeThrustCommand MpcMotionController::update(const StateEstimate& state,
                                                  const MotionReference& reference, double dt_s,
                                                  ControllerDiagnostics* diagnostics) {
  ControllerDiagnostics diag;
  if (!state.position_m.allFinite() || !state.velocity_m_s.allFinite() ||
      !reference.point.position_m.allFinite() || !reference.point.velocity_m_s.allFinite() ||
      !std::isfinite(reference.point.yaw_rad) || !(dt_s > 0.0)) {
    diag.finite = false;
    if (diagnostics) *diagnostics = diag;
    AttitudeThrustCommand hover;
    hover.orientation = Eigen::AngleAxisd(state.yawRad(), Eigen::Vector3d::UnitZ());
    hover.thrust_ratio = model_.hoverThrustRatio();
    return hover;
  }
  const int n = params_.horizon_steps;
  info_ = {};
  info_.converged = true;
  Eigen::Vector3d acceleration;
  for (int i = 0; i < 3; ++i) {
    Axis& axis = axes_[i];
    // The achieved acceleration is not measured: propagate the model's lag
    // from the command applied last step.
    const double alpha = std::exp(-dt_s / std::max(params_.acceleration_lag_s, 1e-3));
    // Disturbance observer: what the model did not predict of the velocity.
    if (axis.have_prediction && params_.disturbance_gain > 0.0) {
      const double error = state.velocity_m_s[i] - axis.predicted_v;
      axis.disturbance = std::clamp(axis.disturbance + params_.disturbance_gain * error / dt_s,
                                    -params_.max_disturbance_m_s2, params_.max_disturbance_m_s2);
    }
    axis.state = {state.position_m[i], state.velocity_m_s[i],
                  alpha * axis.state(2) + (1.0 - alpha) * axis.last_u};
    Eigen::VectorXd p_ref(n), v_ref(n), a_ref(n);
    for (int k = 1; k <= n; ++k) {
      const Eigen::Vector3d r = referenceAt(state, reference, i, k);
      p_ref(k - 1) = r(0);
      v_ref(k - 1) = r(1);
      a_ref(k - 1) = r(2);
    }
    bool converged = false;
    info_.iterations = std::max(
        info_.iterations, solveAxis(axis, p_ref, v_ref, a_ref, lower_[i], upper_[i], &converged));
    info_.converged = info_.converged && converged;
    acceleration[i] = axis.u(0);
    info_.at_bound[i] = axis.u(0) <= lower_[i] + 1e-9 || axis.u(0) >= upper_[i] - 1e-9;
    axis.last_u = axis.u(0);
    axis.predicted_v = state.velocity_m_s[i] + dt_s * (axis.state(2) + axis.disturbance);
    axis.have_prediction = true;
  }

  double yaw = reference.point.yaw_rad;
  if (reference.mode == MotionReference::Mode::kVelocity) {
    if (!yaw_hold_set_) {
      yaw_hold_rad_ = state.yawRad();
      yaw_hold_set_ = true;
    }
    yaw_hold_rad_ = wrapAngle(yaw_hold_rad_ + reference.yaw_rate_rad_s * dt_s);
    yaw = yaw_hold_rad_;
  } else {
    yaw_hold_set_ = false;
  }
  bool saturated = false;
  AttitudeThrustCommand command = accelerationToAttitude(acceleration, yaw, model_, &saturated);
  diag.saturated = saturated || info_.at_bound[0] || info_.at_bound[1] || info_.at_bound[2];
  diag.acceleration_command_m_s2 = acceleration;
  diag.finite = acceleration.allFinite() && std::isfinite(command.thrust_ratio);
  if (diagnostics) *diagnostics = diag;
  return command;
}

Eigen::MatrixXd MpcMotionController::predictedPositions() const {
  Eigen::MatrixXd out(params_.horizon_steps, 3);
  for (int i = 0; i < 3; ++i) {
    out.col(i) = phi_p_ * axes_[i].state + dist_p_ * axes_[i].disturbance + gamma_p_ * axes_[i].u;
  }
  return out;
}

}  // namespace behaviorlib::motion
