#pragma once

// WindEstimator: the steady wind a multirotor is flying in, estimated from
// what the vehicle itself observes — its attitude and its velocity — as a
// real vehicle without an anemometer does.
//
// Physics: the rotors push along the body z axis only, so whatever force the
// vehicle feels along its body x and y axes is aerodynamic drag (against the
// velocity relative to the air). With a the world acceleration (from the
// velocity estimate's change), g gravity and R the attitude (world <- body),
//
//   f = R^T (a + g z)              specific force in body axes
//   D_x = m f_x,  D_y = m f_y      the body-axis drag (thrust has no x, y part)
//
// Steady wind makes the vehicle lean into it to hold its position or its
// velocity: that lean is exactly this drag. Inverting the airframe's drag
// model (per body axis: D = -(c1 v + c2 |v| v), the model the simulator
// uses) gives the velocity relative to the air u, and the wind is
//
//   w = v - R u                    (u_z, hidden in the thrust, such that w_z = 0:
//                                   no vertical wind)
//
// Horizontal wind only is reported. Drag and velocity are low-pass filtered
// (first order, time_constant_s) in the world frame so that a turn does not
// rotate the filter's memory. Samples are stamped (seconds, any epoch):
// a sample older than the last is ignored; a gap longer than max_gap_s
// restarts the estimate from the new sample with the acceleration taken as
// zero (steady flight), so a single sample already gives the estimate of a
// vehicle that holds still; the next sample, with a measured acceleration,
// replaces it and the filter runs from there.
//
//   WindEstimator wind(WindEstimatorParams{});
//   wind.add(t_s, orientation, velocity_m_s);   // every pose + velocity estimate
//   double speed = wind.speedMS();              // 0 before the first sample
//   double factor = windPerformance(speed, 2.0, 10.0);
//
// Deterministic; not thread-safe. No transport: Eigen only.

#include <Eigen/Core>
#include <Eigen/Geometry>

namespace behaviorlib::motion {

struct WindEstimatorParams {
  double mass_kg = 1.5;
  double gravity_m_s2 = 9.81;
  /// Body-axis (x and y) drag of the airframe: F = -(c1 v + c2 |v| v).
  double linear_drag_n_s_m = 0.25;
  double quadratic_drag_n_s2_m2 = 0.04;
  /// Time constant of the low-pass filter (s).
  double time_constant_s = 1.0;
  /// A longer gap between samples restarts the estimate (s).
  double max_gap_s = 0.5;
};

class WindEstimator {
 public:
  explicit WindEstimator(WindEstimatorParams params = {}) : params_(params) {}

  /// One sample of the estimate: its stamp (s), attitude (world <- body)
  /// and world velocity (m/s). Non-finite samples are ignored.
  void add(double t_s, const Eigen::Quaterniond& orientation, const Eigen::Vector3d& velocity_m_s);
  /// Forgets everything (e.g. on landing).
  void reset();
  bool hasEstimate() const { return have_; }

  /// The horizontal wind (world frame, m/s; the direction the air moves
  /// towards); zero without samples.
  Eigen::Vector2d windMS() const;
  double speedMS() const { return windMS().norm(); }
  /// The filtered drag acceleration (world frame, m/s^2).
  const Eigen::Vector3d& dragAccelerationMS2() const { return drag_m_s2_; }

  const WindEstimatorParams& params() const { return params_; }

  /// The air speed along one body axis at which the model's drag is
  /// `drag_n` (the sign of the result is that of -drag_n).
  static double airSpeedForDrag(double drag_n, double c1, double c2);

 private:
  WindEstimatorParams params_;
  bool have_ = false;
  bool steady_only_ = false;  // the estimate rests on one sample, taken as steady
  double last_t_s_ = 0.0;
  Eigen::Vector3d last_velocity_ = Eigen::Vector3d::Zero();
  Eigen::Quaterniond orientation_ = Eigen::Quaterniond::Identity();  // latest
  Eigen::Vector3d drag_m_s2_ = Eigen::Vector3d::Zero();              // filtered, world
  Eigen::Vector3d velocity_m_s_ = Eigen::Vector3d::Zero();           // filtered, world
};

/// The share of its nominal performance a flight behavior keeps in a wind of
/// `speed_m_s`: 1 up to `calm_m_s`, falling linearly to 0.2 at `max_m_s`,
/// 0.2 beyond (never 0: the wind alone does not make a behavior infeasible;
/// its progress and saturation checks judge whether it copes).
double windPerformance(double speed_m_s, double calm_m_s, double max_m_s);

}  // namespace behaviorlib::motion
