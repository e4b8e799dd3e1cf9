#include "simulator/dynamics/gust.h"

#include <cmath>

namespace behaviorlib::sim {

std::uint64_t gustSeed(std::uint64_t world_seed, std::string_view robot_id) {
  // FNV-1a: the same on every platform, unlike std::hash.
  std::uint64_t h = 0xcbf29ce484222325ULL;
  for (const unsigned char c : robot_id) {
    h ^= c;
    h *= 0x100000001b3ULL;
  }
  return world_seed ^ h;
}

const Eigen::Vector3d& GustModel::step(double dt_s, double stddev_m_s, double time_constant_s) {
  if (stddev_m_s > 0.0 && time_constant_s > 0.0 && dt_s > 0.0) {
    // Exact discretization: the stationary standard deviation is stddev_m_s
    // whatever the step.
    const double decay = std::exp(-dt_s / time_constant_s);
    const double noise = stddev_m_s * std::sqrt(1.0 - decay * decay);
    for (int i = 0; i < 3; ++i) gust_m_s_(i) = decay * gust_m_s_(i) + noise * normal_(rng_);
  } else {
    gust_m_s_.setZero();
  }
  return gust_m_s_;
}

}  // namespace behaviorlib::sim
