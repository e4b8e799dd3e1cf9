#pragma once

// MpcMotionController: the receding-horizon controller of
// QUADROTOR_MPC_MOTION_CONTROL.
//
// Model, per world axis (the axes are decoupled at the acceleration level):
// position, velocity and the achieved acceleration, which follows the
// commanded one with a first-order lag (the attitude loops of the autopilot
// take time to tilt the vehicle):
//
//   p+ = p + h v + h^2/2 a,   v+ = v + h a,   a+ = alpha a + (1 - alpha) u,
//   alpha = exp(-h / tau)
//
// Every step it minimises, over the commanded accelerations u_0..u_{N-1},
//
//   sum_k q_p (p_k - p_ref,k)^2 + q_v (v_k - v_ref,k)^2
//       + r (u_k - a_ref,k)^2 + r_d (u_k - u_{k-1})^2
//
// subject to box limits on u (tilt and thrust limits of the vehicle), as a
// condensed QP (states eliminated: x = Phi x0 + Gamma U) with a constant
// Hessian, solved by accelerated projected gradient (FISTA; projection onto a
// box is exact) warm-started from the previous solution shifted by one step.
// Only u_0 is applied (receding horizon); it becomes attitude and thrust.
// Offset-free: a constant acceleration disturbance per axis (wind drag, a
// weak motor, a model error) is estimated from the velocity the model
// mispredicted, and enters the predictions, so steady wind leaves no
// steady tracking error.
//
// Deterministic; not thread-safe.

#include <Eigen/Dense>
#include <array>

#include "behaviorlib/motion_control/motion_types.h"

namespace behaviorlib::motion {

struct MpcParams {
  int horizon_steps = 20;            ///< N
  double step_s = 0.1;               ///< h: N h = 2 s of look-ahead
  double acceleration_lag_s = 0.12;  ///< tau of the achieved acceleration
  double position_weight = 10.0;     ///< q_p (1/m^2)
  double velocity_weight = 2.0;      ///< q_v (s^2/m^2)
  double input_weight = 0.2;         ///< r   (s^4/m^2)
  double input_rate_weight = 0.5;    ///< r_d
  int max_iterations = 200;
  /// Disturbance observer gain per control step (0 turns it off) and bound.
  double disturbance_gain = 0.03;
  double max_disturbance_m_s2 = 4.0;
  double tolerance = 1e-4;  ///< stop when an iteration changes U less than this (m/s^2)
};

struct MpcSolveInfo {
  int iterations = 0;
  bool converged = false;
  std::array<bool, 3> at_bound{};  ///< u_0 on its box limit, per axis
};

class MpcMotionController {
 public:
  MpcMotionController(VehicleModel model, MpcParams params = {});

  AttitudeThrustCommand update(const StateEstimate& state, const MotionReference& reference,
                               double dt_s, ControllerDiagnostics* diagnostics = nullptr);
  void reset();

  const MpcSolveInfo& lastSolve() const { return info_; }
  /// Box of the commanded acceleration per axis (m/s^2): {lower, upper}.
  std::pair<Eigen::Vector3d, Eigen::Vector3d> inputBounds() const { return {lower_, upper_}; }
  /// Estimated acceleration disturbance per axis (m/s^2).
  Eigen::Vector3d disturbance() const {
    return {axes_[0].disturbance, axes_[1].disturbance, axes_[2].disturbance};
  }
  /// Predicted positions of the last solution (N x 3).
  Eigen::MatrixXd predictedPositions() const;
  const MpcParams& params() const { return params_; }

 private:
  struct Axis {
    Eigen::VectorXd u;      // solution, warm start
    Eigen::Vector3d state;  // p, v, a (achieved acceleration estimate)
    double last_u = 0.0;
    double disturbance = 0.0;  // estimated constant acceleration (m/s^2)
    double predicted_v = 0.0;  // velocity the model predicted for now
    bool have_prediction = false;
  };
  void buildCondensedModel();
  // Reference of axis `i` at horizon step k (1..N): position, velocity, acceleration.
  Eigen::Vector3d referenceAt(const StateEstimate& state, const MotionReference& reference,
                              int axis, int k) const;
  int solveAxis(Axis& axis, const Eigen::VectorXd& p_ref, const Eigen::VectorXd& v_ref,
                const Eigen::VectorXd& a_ref, double lower, double upper, bool* converged);

  VehicleModel model_;
  MpcParams params_;
  Eigen::Matrix3d a_;  // one-step model
  Eigen::Vector3d b_;
  Eigen::MatrixXd phi_p_, phi_v_;      // N x 3: predicted p, v from x0
  Eigen::VectorXd dist_p_, dist_v_;    // N: predicted p, v per unit disturbance
  Eigen::MatrixXd gamma_p_, gamma_v_;  // N x N: predicted p, v from U
  Eigen::MatrixXd hessian_;            // N x N
  double step_size_ = 0.0;             // 1 / L
  Eigen::Vector3d lower_, upper_;
  std::array<Axis, 3> axes_;
  MpcSolveInfo info_;
  double yaw_hold_rad_ = 0.0;
  bool yaw_hold_set_ = false;
};

}  // namespace behaviorlib::motion
