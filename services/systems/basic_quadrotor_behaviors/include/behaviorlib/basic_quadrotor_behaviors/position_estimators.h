#pragma once

// The estimation cores of ESTIMATE_POSITION_WITH_SENSOR (SensorPositionFilter)
// and ESTIMATE_POSITION_WITH_LINEAR_SPEED (LinearSpeedDeadReckoning), and the
// FrozenDetector both behaviors use on their inputs. No I/O and no clock:
// samples come with their stamps (seconds), so unit tests drive them
// directly.
//
//   SensorPositionFilter filter(SensorFilterNoise{});
//   filter.predict(imu_orientation, specific_force, dt);      // every IMU sample
//   auto r = filter.updateFix(position, 0.5, 1.0, t_fix, t_imu, 5.0);  // every fix
//   if (!r.accepted) -> the fix is more than 5 m from the prediction
//
//   LinearSpeedDeadReckoning dr(initial_position, t0);
//   dr.add(t, body_velocity, imu_orientation);                 // every speed sample
//   dr.position(), dr.distanceM()
//
// Frames: world ENU, body FLU, quaternions world <- body (the simulator's).

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <optional>

namespace behaviorlib::basic {

/// Standard gravity, as the simulated accelerometer measures it at rest.
inline constexpr double kGravityM_S2 = 9.80665;

/// Noise model of the SensorPositionFilter.
struct SensorFilterNoise {
  /// White noise of the world-frame acceleration derived from the IMU, per
  /// sqrt(Hz): accelerometer noise plus the attitude error times gravity.
  double accel_noise_m_s2 = 0.05;
  /// Random walk of the accelerometer bias (per world axis), per sqrt(s).
  double accel_bias_walk_m_s2 = 0.002;
  /// Random walk of the barometer's offset from the world z, per sqrt(s).
  double baro_drift_m = 0.02;
  /// Uncertainty of the barometer's offset when the filter starts.
  double initial_baro_offset_stddev_m = 0.3;
  /// Uncertainty of the accelerometer bias when the filter starts.
  double initial_accel_bias_stddev_m_s2 = 0.05;
  /// Uncertainty of the velocity when the filter starts (it starts at rest).
  double initial_velocity_stddev_m_s = 0.5;
};

/// A linear Kalman filter of one world axis. State: position, velocity,
/// accelerometer bias along the axis, and the offset of an auxiliary
/// position sensor (the barometer on the vertical axis; unused elsewhere).
class AxisFilter {
 public:
  using Vector4 = Eigen::Vector4d;
  using Matrix4 = Eigen::Matrix4d;

  void reset(double position_m, double position_stddev_m, const SensorFilterNoise& noise);
  /// Advances by `dt` s with the measured acceleration along the axis (bias
  /// not removed).
  void predict(double accel_m_s2, double dt, const SensorFilterNoise& noise);
  /// The measurement's innovation: `z` minus the predicted measurement, for
  /// a direct position measurement (with_offset false) or the auxiliary
  /// sensor's (position + offset).
  double innovation(double z, bool with_offset) const;
  /// The innovation's standard deviation for a measurement of `stddev`.
  double innovationStddev(double stddev, bool with_offset) const;
  /// Kalman update with measurement `z` of standard deviation `stddev`.
  void update(double z, double stddev, bool with_offset);

  double position() const { return x_(0); }
  double velocity() const { return x_(1); }
  double accelBias() const { return x_(2); }
  double offset() const { return x_(3); }
  double positionStddev() const { return std::sqrt(std::max(P_(0, 0), 0.0)); }
  bool finite() const { return x_.allFinite() && P_.allFinite(); }

 private:
  Vector4 x_ = Vector4::Zero();
  Matrix4 P_ = Matrix4::Identity();
};

/// ESTIMATE_POSITION_WITH_SENSOR's fusion: one AxisFilter per world axis,
/// predicted with the IMU's specific force rotated into the world frame by
/// the IMU's own attitude, corrected with GPS-like fixes (x, y, z) and the
/// barometric altitude (z, with its offset). Starts at the first fix.
/// Deterministic; not thread-safe.
class SensorPositionFilter {
 public:
  /// Outcome of one measurement.
  struct Update {
    bool accepted = false;
    /// Distance between the measurement and the prediction, metres (3-D for
    /// a fix, vertical for an altitude).
    double innovation_m = 0.0;
  };

  explicit SensorPositionFilter(SensorFilterNoise noise = {}) : noise_(noise) {}

  bool initialized() const { return initialized_; }
  /// Prediction with one IMU sample: orientation (world <- body) and
  /// specific force (body), over `dt` s since the previous sample. Ignored
  /// before the first fix or for dt outside (0, 1] s.
  void predict(const Eigen::Quaterniond& orientation, const Eigen::Vector3d& specific_force_m_s2,
               double dt);
  /// A position fix stamped `fix_time_s`; the filter's state is at
  /// `filter_time_s` (the last IMU sample; the fix is moved there along the
  /// velocity estimate). Rejected, without changing the state, when it is
  /// further than `gate_m` from the prediction. The fix's z is always
  /// fused: with a barometer it anchors the barometer's offset (the
  /// barometer gives the short-term height). The first fix initialises the
  /// filter (and is accepted).
  Update updateFix(const Eigen::Vector3d& position_m, double horizontal_stddev_m,
                   double vertical_stddev_m, double fix_time_s, double filter_time_s,
                   double gate_m);
  /// A barometric altitude; gated on the vertical innovation like a fix.
  Update updateAltitude(double altitude_m, double stddev_m, double gate_m);

  Eigen::Vector3d position() const;
  Eigen::Vector3d velocity() const;
  /// The largest of the three position standard deviations, metres.
  double positionStddevM() const;
  bool finite() const;

 private:
  SensorFilterNoise noise_;
  bool initialized_ = false;
  AxisFilter axes_[3];
};

/// ESTIMATE_POSITION_WITH_LINEAR_SPEED's core: integrates body-frame linear
/// speed samples, rotated into the world frame by the IMU's orientation,
/// from an initial position at a start time (trapezoidal rule between
/// samples). Not thread-safe.
class LinearSpeedDeadReckoning {
 public:
  LinearSpeedDeadReckoning(const Eigen::Vector3d& initial_position_m, double start_time_s)
      : position_(initial_position_m), last_time_s_(start_time_s) {}

  /// Adds a speed sample stamped `time_s`. Samples stamped at or before the
  /// previous one (or the start time) are ignored (false). A gap longer than
  /// `max_gap_s` is integrated as if it were `max_gap_s` long (the caller
  /// reports the stale stream).
  bool add(double time_s, const Eigen::Vector3d& body_velocity_m_s,
           const Eigen::Quaterniond& orientation, double max_gap_s);

  const Eigen::Vector3d& position() const { return position_; }
  /// The latest world-frame velocity (zero before the first sample).
  const Eigen::Vector3d& velocity() const { return velocity_; }
  /// Length of the integrated path, metres.
  double distanceM() const { return distance_m_; }
  /// Stamp of the latest integrated sample (the start time before any).
  double lastTimeS() const { return last_time_s_; }

 private:
  Eigen::Vector3d position_;
  Eigen::Vector3d velocity_ = Eigen::Vector3d::Zero();
  std::optional<Eigen::Vector3d> previous_velocity_;
  double last_time_s_;
  double distance_m_ = 0.0;
};

/// Tells a live noisy sensor from a frozen one: a real sample always differs
/// from the previous one in some bit (the noise), a stuck sensor repeats its
/// value with new stamps. Tracks since when the value has not changed.
class FrozenDetector {
 public:
  /// Feeds a sample's value stamped `time_s`.
  void add(double time_s, const Eigen::VectorXd& value);
  /// Seconds between the first and the latest sample of the current value:
  /// 0 while every sample differs from the one before.
  double frozenForS() const { return value_ ? last_s_ - since_s_ : 0.0; }
  void reset() { value_.reset(); }

 private:
  std::optional<Eigen::VectorXd> value_;
  double since_s_ = 0.0;  // stamp of the first sample with the current value
  double last_s_ = 0.0;   // stamp of the latest sample
};

}  // namespace behaviorlib::basic
