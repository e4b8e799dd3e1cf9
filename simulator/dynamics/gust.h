#pragma once

// GustModel: turbulence added to the mean wind of one vehicle, an
// Ornstein-Uhlenbeck process per world axis (exact discretization), with its
// own seeded std::mt19937_64. Shared by WorldSim and the simulator's vehicles
// so that both fly the same gusts from the same seed.
//
//   GustModel gusts(gustSeed(/*world seed=*/7, "drone1"));
//   every physics step:
//     quad.setWindVelocity(mean_wind + gusts.step(dt, /*stddev=*/1.0, /*tau=*/2.0));
//
// Deterministic: the same seed and the same sequence of step() calls give
// the same gusts, bit for bit. A step with no turbulence (stddev or time
// constant <= 0) draws nothing and resets the gust to zero.

#include <Eigen/Core>
#include <cstdint>
#include <random>
#include <string_view>

namespace behaviorlib::sim {

/// Default correlation time of the turbulence (s).
inline constexpr double kDefaultGustTimeConstantS = 2.0;

/// The seed of one vehicle's gusts: the world's seed and a platform-
/// independent hash (FNV-1a) of the robot id.
std::uint64_t gustSeed(std::uint64_t world_seed, std::string_view robot_id);

class GustModel {
 public:
  explicit GustModel(std::uint64_t seed) : rng_(seed) {}

  /// Advances the turbulence by `dt_s`: stationary standard deviation
  /// `stddev_m_s` per axis, correlation time `time_constant_s`. Returns the
  /// gust (m/s, world frame) to add to the mean wind.
  const Eigen::Vector3d& step(double dt_s, double stddev_m_s, double time_constant_s);

  /// The current gust (m/s, world frame).
  const Eigen::Vector3d& gust() const { return gust_m_s_; }

 private:
  Eigen::Vector3d gust_m_s_ = Eigen::Vector3d::Zero();
  std::mt19937_64 rng_;
  std::normal_distribution<double> normal_{0.0, 1.0};
};

}  // namespace behaviorlib::sim
