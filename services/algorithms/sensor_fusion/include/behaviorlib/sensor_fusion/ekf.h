#pragma once

// InsEkf: the error-state extended Kalman filter of
// SELF_LOCALIZE_WITH_EKF_SENSOR_FUSION. The IMU drives the prediction at its
// own rate (every sample); GPS-like position, barometric altitude, body
// linear speed (optical flow) and the IMU's orientation (yaw) correct it.
//
// Nominal state: position p and velocity v (world ENU), orientation q (world
// <- body), accelerometer bias b_a and gyro bias b_g (body), and the
// barometer's offset b_baro (m). Error state (16): dp, dv, dtheta
// (body-frame rotation error), db_a, db_g, db_baro; the nominal state absorbs
// the error after every update (standard ESKF reset).
//
//   p+ = p + v dt + 1/2 a dt^2,  v+ = v + a dt,  a = R (f - b_a) + g
//   q+ = q * exp((w - b_g) dt),  b_baro+ = b_baro + random walk
//
// A barometer reads p_z + b_baro. Its offset starts near zero (the barometer
// is zeroed on the ground) and drifts with the weather and its temperature;
// an absolute altitude (GPS) makes it observable, so the altitude follows
// the barometer's low noise without its drift. Without one (the lidar SLAM
// indoors), the offset stays at its last estimate and its uncertainty grows.
//
// Every update is gated: an innovation whose normalised squared size (NIS)
// exceeds the chi-square bound of its dimension is rejected and counted, so
// a sensor publishing garbage cannot drag the estimate away; the counts and
// the NIS history are what the behavior's monitoring reads to tell a dead or
// lying sensor and a diverging filter apart.
//
// Deterministic; not thread-safe.

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cstdint>

namespace behaviorlib::fusion {

struct EkfNoise {
  double gyro_noise_rad_s = 0.005;      ///< per sqrt(Hz)
  double accel_noise_m_s2 = 0.05;       ///< per sqrt(Hz)
  double gyro_bias_walk_rad_s2 = 1e-4;  ///< per sqrt(Hz)
  double accel_bias_walk_m_s3 = 1e-3;   ///< per sqrt(Hz)
  double initial_position_stddev_m = 1.0;
  double initial_velocity_stddev_m_s = 0.5;
  double initial_attitude_stddev_rad = 0.1;
  double initial_accel_bias_stddev_m_s2 = 0.2;
  double initial_gyro_bias_stddev_rad_s = 0.02;
  double baro_drift_m_sqrt_s = 0.02;  ///< random walk of the barometer's offset
  double initial_baro_offset_stddev_m = 0.1;
};

/// Outcome of one measurement update.
struct UpdateResult {
  bool accepted = false;
  double nis = 0.0;  ///< normalised innovation squared
};

class InsEkf {
 public:
  static constexpr int kErrorStates = 16;
  using ErrorVector = Eigen::Matrix<double, kErrorStates, 1>;
  using ErrorMatrix = Eigen::Matrix<double, kErrorStates, kErrorStates>;

  explicit InsEkf(EkfNoise noise = {});

  /// Starts from a known pose (the first GPS fix, the IMU's orientation).
  void initialize(const Eigen::Vector3d& position_m, const Eigen::Vector3d& velocity_m_s,
                  const Eigen::Quaterniond& orientation);
  bool initialized() const { return initialized_; }

  /// Prediction with one IMU sample: body rates (rad/s) and specific force
  /// (m/s^2, body FLU; +9.81 up at rest) over `dt_s`.
  void predict(const Eigen::Vector3d& gyro_rad_s, const Eigen::Vector3d& specific_force_m_s2,
               double dt_s);

  UpdateResult updatePosition(const Eigen::Vector3d& position_m, double stddev_horizontal_m,
                              double stddev_vertical_m);
  /// Horizontal position (x, y) with its full covariance (a scan match:
  /// tight across a wall, loose along a corridor).
  UpdateResult updateHorizontalPosition(const Eigen::Vector2d& position_m,
                                        const Eigen::Matrix2d& covariance_m2);
  /// A barometric altitude (m): the altitude plus the barometer's offset,
  /// which the filter estimates.
  UpdateResult updateBarometer(double altitude_m, double stddev_m);
  /// Velocity measured in the body frame (optical flow + range).
  UpdateResult updateBodyVelocity(const Eigen::Vector3d& velocity_body_m_s, double stddev_m_s);
  /// Yaw from an attitude sensor (the IMU's orientation output).
  UpdateResult updateYaw(double yaw_rad, double stddev_rad);

  const Eigen::Vector3d& position() const { return p_; }
  const Eigen::Vector3d& velocity() const { return v_; }
  const Eigen::Quaterniond& orientation() const { return q_; }
  const Eigen::Vector3d& accelBias() const { return ba_; }
  const Eigen::Vector3d& gyroBias() const { return bg_; }
  /// The barometer's offset: what it reads above the true altitude (m).
  double baroOffsetM() const { return baro_offset_m_; }
  const ErrorMatrix& covariance() const { return P_; }
  /// Standard deviation of the horizontal position (m).
  double horizontalStddevM() const;
  bool finite() const;

  /// Chi-square gate at 99.9 % per measurement dimension (1..3).
  static double gate(int dimension);
  uint64_t rejectedCount() const { return rejected_; }

 private:
  template <int M>
  UpdateResult update(const Eigen::Matrix<double, M, 1>& innovation,
                      const Eigen::Matrix<double, M, kErrorStates>& H,
                      const Eigen::Matrix<double, M, M>& R);
  void inject(const ErrorVector& dx);

  EkfNoise noise_;
  bool initialized_ = false;
  Eigen::Vector3d p_ = Eigen::Vector3d::Zero(), v_ = Eigen::Vector3d::Zero();
  Eigen::Quaterniond q_ = Eigen::Quaterniond::Identity();
  Eigen::Vector3d ba_ = Eigen::Vector3d::Zero(), bg_ = Eigen::Vector3d::Zero();
  double baro_offset_m_ = 0.0;
  ErrorMatrix P_ = ErrorMatrix::Identity();
  uint64_t rejected_ = 0;
};

/// [v]x, the cross-product matrix.
Eigen::Matrix3d skew(const Eigen::Vector3d& v);

}  // namespace behaviorlib::fusion
