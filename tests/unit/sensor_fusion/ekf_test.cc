#include "behaviorlib/sensor_fusion/ekf.h"

#include <gtest/gtest.h>

#include <chrono>
#include <cmath>
#include <cstdio>
#include <random>

#include "behaviorlib/sensor_fusion/ins_feed.h"
#include "simulator/dynamics/autopilot.h"
#include "simulator/dynamics/quadrotor.h"

namespace behaviorlib::fusion {
namespace {

// A flight of the simulator's quadrotor (velocity setpoints along a circle
// with climbs) and the sensor samples a real vehicle would give.
class SyntheticFlight {
 public:
  struct Noise {
    double gyro_rad_s = 0.005 * std::sqrt(200.0);  // per sample at 200 Hz
    double accel_m_s2 = 0.05 * std::sqrt(200.0);
    Eigen::Vector3d gyro_bias{0.01, -0.02, 0.005};
    Eigen::Vector3d accel_bias{0.1, -0.05, 0.08};
    double gps_h_m = 0.3, gps_v_m = 0.5;
    double baro_m = 0.1, flow_m_s = 0.05, yaw_rad = 0.05;
    double baro_drift_m_s = 0.0;  // the barometer's offset grows this fast
  } noise;

  explicit SyntheticFlight(uint64_t seed)
      : quad_(params_, start()), autopilot_(params_), rng_(seed) {}

  /// Runs `seconds` of flight; callbacks get the samples as they happen.
  template <class OnImu, class OnGps, class OnBaro, class OnFlow, class OnYaw, class OnTruth>
  void fly(double seconds, OnImu on_imu, OnGps on_gps, OnBaro on_baro, OnFlow on_flow, OnYaw on_yaw,
           OnTruth on_truth) {
    std::normal_distribution<double> n(0.0, 1.0);
    auto noisy3 = [&](double s) {
      // One draw per statement: a defined order, the same samples everywhere.
      Eigen::Vector3d v;
      v.x() = n(rng_) * s;
      v.y() = n(rng_) * s;
      v.z() = n(rng_) * s;
      return v;
    };
    Eigen::Vector3d v_prev = quad_.state().velocity_m_s;
    const int steps = static_cast<int>(seconds * 1000.0);
    for (int k = 1; k <= steps; ++k) {
      const double t = k * 0.001;
      const sim::Setpoint sp = sim::VelocityYawRate{
          {2.0 * std::cos(0.4 * t), 2.0 * std::sin(0.4 * t), 0.3 * std::sin(0.2 * t)}, 0.2};
      quad_.step(0.001, autopilot_.update(quad_.state(), sp, 0.001));
      const auto& s = quad_.state();
      if (k % 5 == 0) {  // IMU 200 Hz
        const Eigen::Vector3d a_world = (s.velocity_m_s - v_prev) / 0.005;
        v_prev = s.velocity_m_s;
        const Eigen::Vector3d f_body =
            s.orientation.conjugate() * (a_world + Eigen::Vector3d(0, 0, 9.81));
        on_imu(s.angular_velocity_rad_s + noise.gyro_bias + noisy3(noise.gyro_rad_s),
               f_body + noise.accel_bias + noisy3(noise.accel_m_s2), 0.005);
      }
      if (k % 100 == 0) {
        Eigen::Vector3d gps = s.position_m;
        gps.x() += n(rng_) * noise.gps_h_m;
        gps.y() += n(rng_) * noise.gps_h_m;
        gps.z() += n(rng_) * noise.gps_v_m;
        on_gps(gps);
        const Eigen::Vector3d forward = s.orientation * Eigen::Vector3d::UnitX();
        on_yaw(std::atan2(forward.y(), forward.x()) + n(rng_) * noise.yaw_rad);
      }
      if (k % 40 == 0)
        on_baro(s.position_m.z() + noise.baro_drift_m_s * t + n(rng_) * noise.baro_m);
      if (k % 33 == 0) on_flow(s.orientation.conjugate() * s.velocity_m_s + noisy3(noise.flow_m_s));
      if (k % 5 == 0) on_truth(s.position_m, s.velocity_m_s);
    }
  }

  const sim::QuadrotorState& state() const { return quad_.state(); }

 private:
  sim::QuadrotorState start() const {
    sim::QuadrotorState s;
    s.position_m = {0, 0, 5};
    s.motor_speeds_rad_s.fill(params_.hoverMotorSpeedRadS());
    return s;
  }
  sim::QuadrotorParams params_;
  sim::Quadrotor quad_;
  sim::Autopilot autopilot_;
  std::mt19937_64 rng_;
};

struct Result {
  double position_rmse_m = 0;
  double velocity_rmse_m_s = 0;
  uint64_t rejected = 0;
  InsEkf ekf;
};

Result runFlight(uint64_t seed, bool gps_garbage = false, double seconds = 60.0) {
  SyntheticFlight flight(seed);
  Result r;
  InsEkf& ekf = r.ekf;
  ekf.initialize(flight.state().position_m + Eigen::Vector3d(0.5, -0.5, 0.2),
                 Eigen::Vector3d::Zero(), flight.state().orientation);
  double sum_p = 0, sum_v = 0;
  int count = 0, gps_count = 0;
  flight.fly(
      seconds, [&](auto w, auto f, double dt) { ekf.predict(w, f, dt); },
      [&](Eigen::Vector3d gps) {
        if (gps_garbage && ++gps_count % 5 == 0) gps += Eigen::Vector3d(80, -40, 30);  // garbage
        ekf.updatePosition(gps, flight.noise.gps_h_m, flight.noise.gps_v_m);
      },
      [&](double z) { ekf.updateBarometer(z, flight.noise.baro_m); },
      [&](const Eigen::Vector3d& v) { ekf.updateBodyVelocity(v, flight.noise.flow_m_s); },
      [&](double yaw) { ekf.updateYaw(yaw, flight.noise.yaw_rad); },
      [&](const Eigen::Vector3d& p, const Eigen::Vector3d& v) {
        if (count++ < 2000) return;  // after 10 s of convergence
        sum_p += (ekf.position() - p).squaredNorm();
        sum_v += (ekf.velocity() - v).squaredNorm();
      });
  const double n = static_cast<double>(count - 2000);
  r.position_rmse_m = std::sqrt(sum_p / n);
  r.velocity_rmse_m_s = std::sqrt(sum_v / n);
  r.rejected = ekf.rejectedCount();
  return r;
}

TEST(InsEkf, FusesImuGpsBaroFlowAndYawWithinTheBound) {
  for (uint64_t seed : {1u, 2u, 3u}) {
    const Result r = runFlight(seed);
    std::printf("seed %llu: position RMSE %.3f m, velocity RMSE %.3f m/s\n",
                static_cast<unsigned long long>(seed), r.position_rmse_m, r.velocity_rmse_m_s);
    EXPECT_LT(r.position_rmse_m, 0.15) << "seed " << seed;
    EXPECT_LT(r.velocity_rmse_m_s, 0.1) << "seed " << seed;
    EXPECT_TRUE(r.ekf.finite());
    // The biases are learnt.
    EXPECT_NEAR(r.ekf.gyroBias().z(), 0.005, 0.01) << "seed " << seed;
  }
}

TEST(InsEkf, GarbagePositionsAreRejectedAndCounted) {
  const Result clean = runFlight(4);
  const Result garbage = runFlight(4, /*gps_garbage=*/true);
  EXPECT_GE(garbage.rejected, 100u);  // one fix in five, 600 fixes
  EXPECT_LT(garbage.position_rmse_m, 0.2);
  EXPECT_LT(clean.rejected, 10u);
}

TEST(InsEkf, WithoutCorrectionsTheUncertaintyGrows) {
  InsEkf ekf;
  ekf.initialize({0, 0, 1}, Eigen::Vector3d::Zero(), Eigen::Quaterniond::Identity());
  const double before = ekf.horizontalStddevM();
  for (int i = 0; i < 2000; ++i) ekf.predict(Eigen::Vector3d::Zero(), {0, 0, 9.81}, 0.005);
  EXPECT_GT(ekf.horizontalStddevM(), 2.0 * before);  // a dead GPS shows in the covariance
  EXPECT_NEAR(ekf.position().z(), 1.0, 1e-9);        // a level IMU at rest: no drift
}

TEST(InsEkf, AHorizontalPositionCorrectsOnlyWhereItsCovarianceIsTight) {
  InsEkf ekf;
  ekf.initialize({0, 0, 1}, Eigen::Vector3d::Zero(), Eigen::Quaterniond::Identity());
  // A scan match in a corridor along y: sure of x, not of y.
  const Eigen::Matrix2d covariance = Eigen::Vector2d(0.02 * 0.02, 100.0).asDiagonal();
  ASSERT_TRUE(ekf.updateHorizontalPosition({0.8, 0.8}, covariance).accepted);
  EXPECT_NEAR(ekf.position().x(), 0.8, 0.01);
  EXPECT_NEAR(ekf.position().y(), 0.0, 0.01);
  EXPECT_NEAR(ekf.position().z(), 1.0, 1e-9);
  EXPECT_LT(std::sqrt(ekf.covariance()(0, 0)), 0.03);
  EXPECT_GT(std::sqrt(ekf.covariance()(1, 1)), 0.9);
}

// The altitude's error over the last 10 s of a 150 s flight whose barometer
// drifts by 0.6 m, with GPS as loose vertically as the simulator's (1 m).
struct DriftResult {
  double altitude_error_m = 0;  ///< mean |error| over the last 10 s
  double baro_offset_m = 0;     ///< the filter's estimate at the end
};

DriftResult flyWithDriftingBarometer(const EkfNoise& noise) {
  SyntheticFlight flight(11);
  flight.noise.gps_v_m = 1.0;
  flight.noise.baro_drift_m_s = 0.004;
  InsEkf ekf(noise);
  ekf.initialize(flight.state().position_m, Eigen::Vector3d::Zero(), flight.state().orientation);
  double sum = 0;
  int count = 0, samples = 0;
  flight.fly(
      150.0, [&](auto w, auto f, double dt) { ekf.predict(w, f, dt); },
      [&](const Eigen::Vector3d& gps) {
        ekf.updatePosition(gps, flight.noise.gps_h_m, flight.noise.gps_v_m);
      },
      [&](double z) { ekf.updateBarometer(z, flight.noise.baro_m); },
      [&](const Eigen::Vector3d& v) { ekf.updateBodyVelocity(v, flight.noise.flow_m_s); },
      [&](double yaw) { ekf.updateYaw(yaw, flight.noise.yaw_rad); },
      [&](const Eigen::Vector3d& p, const Eigen::Vector3d&) {
        if (samples++ < 140 * 200) return;
        sum += std::abs(ekf.position().z() - p.z());
        ++count;
      });
  return {sum / count, ekf.baroOffsetM()};
}

TEST(InsEkf, ADriftingBarometerIsCorrectedByGps) {
  const DriftResult modelled = flyWithDriftingBarometer({});
  std::printf("drift estimated: altitude error %.3f m, offset %.3f m (true 0.60)\n",
              modelled.altitude_error_m, modelled.baro_offset_m);
  EXPECT_LT(modelled.altitude_error_m, 0.15);
  EXPECT_NEAR(modelled.baro_offset_m, 0.6, 0.15);
  // A filter that takes the barometer at its word (its offset fixed at 0)
  // follows the drift.
  EkfNoise fixed;
  fixed.baro_drift_m_sqrt_s = 0.0;
  fixed.initial_baro_offset_stddev_m = 0.0;
  const DriftResult unmodelled = flyWithDriftingBarometer(fixed);
  std::printf("drift not estimated: altitude error %.3f m\n", unmodelled.altitude_error_m);
  EXPECT_GT(unmodelled.altitude_error_m, 0.3);
  EXPECT_EQ(unmodelled.baro_offset_m, 0.0);
}

TEST(InsEkf, NonFiniteMeasurementsAreRejected) {
  InsEkf ekf;
  ekf.initialize({0, 0, 1}, Eigen::Vector3d::Zero(), Eigen::Quaterniond::Identity());
  EXPECT_FALSE(ekf.updatePosition({std::nan(""), 0, 0}, 0.3, 0.5).accepted);
  EXPECT_FALSE(ekf.updateBarometer(std::nan(""), 0.1).accepted);
  EXPECT_EQ(ekf.rejectedCount(), 2u);
  EXPECT_TRUE(ekf.finite());
}

// InsFeed: the inertial navigation shared by the EKF and SLAM behaviors.
const Eigen::Vector3d kAtRest(0, 0, 9.81);  // specific force at rest, body FLU

Eigen::Quaterniond yawed(double yaw_rad) {
  return Eigen::Quaterniond(Eigen::AngleAxisd(yaw_rad, Eigen::Vector3d::UnitZ()));
}

TEST(InsFeed, PredictsOnlyOnceStartedAndFromTheSecondSampleOn) {
  InsFeed ins;
  const auto t0 = std::chrono::nanoseconds(1'700'000'000'000'000'000);  // a wall-clock stamp
  const auto dt = std::chrono::milliseconds(5);
  EXPECT_FALSE(ins.imu(t0, Eigen::Quaterniond::Identity(), Eigen::Vector3d::Zero(), kAtRest));
  EXPECT_FALSE(ins.altitude(3.0, 0.1).accepted) << "nothing before the filter starts";
  EXPECT_EQ(ins.imuCount(), 1u);
  ins.ekf().initialize({0, 0, 1}, Eigen::Vector3d::Zero(), Eigen::Quaterniond::Identity());
  // 1 m/s^2 forward over 5 ms: the stamps' difference is exact even this
  // far from their epoch.
  EXPECT_TRUE(ins.imu(t0 + dt, Eigen::Quaterniond::Identity(), Eigen::Vector3d::Zero(),
                      kAtRest + Eigen::Vector3d(1, 0, 0)));
  EXPECT_NEAR(ins.ekf().velocity().x(), 0.005, 1e-9);
  EXPECT_EQ(ins.imuCount(), 2u);
  ASSERT_TRUE(ins.imuOrientation().has_value());
  ins.reset();
  EXPECT_FALSE(ins.ekf().initialized());
  EXPECT_EQ(ins.imuCount(), 0u);
  EXPECT_FALSE(ins.imuOrientation().has_value());
}

// Fed the IMU's orientation at 0.3 rad while the filter holds 0: the yaw is
// corrected at every yaw_every-th sample only, and never without use_imu_yaw.
double yawAfter(int samples, bool use_imu_yaw) {
  InsFeedSettings settings;
  settings.use_imu_yaw = use_imu_yaw;
  settings.yaw_stddev_rad = 0.01;
  settings.yaw_every = 20;
  InsFeed ins({}, settings);
  ins.ekf().initialize({0, 0, 1}, Eigen::Vector3d::Zero(), Eigen::Quaterniond::Identity());
  for (int k = 0; k < samples; ++k) {
    ins.imu(std::chrono::milliseconds(5 * k), yawed(0.3), Eigen::Vector3d::Zero(), kAtRest);
  }
  return yawOf(ins.ekf().orientation());
}

TEST(InsFeed, CorrectsTheYawAtEveryYawEveryThSample) {
  EXPECT_NEAR(yawAfter(20, true), 0.0, 1e-6) << "samples 1..19 predict without a yaw update";
  EXPECT_GT(yawAfter(21, true), 0.1) << "sample 20 corrects the yaw";
  EXPECT_NEAR(yawAfter(21, false), 0.0, 1e-6);
}

TEST(InsFeed, TrustsTheBarometerNoMoreThanItsConfiguredDeviation) {
  const auto varianceAfterAltitude = [](double floor_m) {
    InsFeedSettings settings;
    settings.baro_stddev_m = floor_m;
    InsFeed ins({}, settings);
    ins.ekf().initialize({0, 0, 1}, Eigen::Vector3d::Zero(), Eigen::Quaterniond::Identity());
    EXPECT_TRUE(ins.altitude(1.0, 0.001).accepted);
    return ins.ekf().covariance()(2, 2);
  };
  // A barometer that claims 1 mm is taken at the configured 0.5 m.
  EXPECT_GT(varianceAfterAltitude(0.5), 10 * varianceAfterAltitude(0.001));
}

}  // namespace
}  // namespace behaviorlib::fusion
