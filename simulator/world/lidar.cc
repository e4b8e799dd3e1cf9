#include "simulator/world/lidar.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <numbers>
#include <string>

#include "formats/world/str_cat.h"

namespace behaviorlib::sim {
namespace {

using world::internal::strCat;

constexpr double kTwoPi = 2.0 * std::numbers::pi;

/// Uniform in (0, 1], from the top 53 bits.
double uniformOpenZero(std::mt19937_64& rng) {
  return (static_cast<double>(rng() >> 11) + 1.0) * 0x1.0p-53;
}

}  // namespace

double standardNormal(std::mt19937_64& rng) {
  const double u1 = uniformOpenZero(rng);
  const double u2 = uniformOpenZero(rng);
  return std::sqrt(-2.0 * std::log(u1)) * std::cos(kTwoPi * u2);
}

absl::Status LidarConfig::validate() const {
  auto bad = [](const std::string& what) {
    return absl::InvalidArgumentError(strCat("lidar: ", what));
  };
  if (beams < 1) return bad("beams must be at least 1");
  if (channels < 1) return bad("channels must be at least 1");
  if (!(angle_max_rad >= angle_min_rad)) return bad("angle_max_rad must be >= angle_min_rad");
  if (!(elevation_max_rad >= elevation_min_rad)) {
    return bad("elevation_max_rad must be >= elevation_min_rad");
  }
  if (elevation_min_rad < -std::numbers::pi / 2 || elevation_max_rad > std::numbers::pi / 2) {
    return bad("elevations must be within [-pi/2, pi/2]");
  }
  if (!(range_min_m >= 0.0)) return bad("range_min_m must be >= 0");
  if (!(range_max_m > range_min_m)) return bad("range_max_m must be > range_min_m");
  if (!(noise_stddev_m >= 0.0)) return bad("noise_stddev_m must be >= 0");
  if (!mount_position_m.allFinite()) return bad("mount_position_m must be finite");
  return absl::OkStatus();
}

absl::StatusOr<Lidar> Lidar::create(const world::World& world, LidarConfig config) {
  if (absl::Status status = config.validate(); !status.ok()) return status;
  return Lidar(world, std::move(config));
}

Lidar::Lidar(const world::World& world, LidarConfig config)
    : world_(&world), config_(std::move(config)), rng_(config_.seed) {
  const double span = config_.angle_max_rad - config_.angle_min_rad;
  const bool full_turn = span >= kTwoPi - 1e-9;
  const int steps = full_turn ? config_.beams : std::max(1, config_.beams - 1);
  for (int i = 0; i < config_.beams; ++i) {
    azimuths_.push_back(config_.beams == 1 ? config_.angle_min_rad
                                           : config_.angle_min_rad + span * i / steps);
  }
  const double vspan = config_.elevation_max_rad - config_.elevation_min_rad;
  for (int c = 0; c < config_.channels; ++c) {
    elevations_.push_back(config_.channels == 1
                              ? config_.elevation_min_rad
                              : config_.elevation_min_rad + vspan * c / (config_.channels - 1));
  }
  directions_.reserve(static_cast<std::size_t>(config_.beams) * config_.channels);
  for (double elevation : elevations_) {
    for (double azimuth : azimuths_) {
      directions_.emplace_back(std::cos(elevation) * std::cos(azimuth),
                               std::cos(elevation) * std::sin(azimuth), std::sin(elevation));
    }
  }
}

int Lidar::beamNearestAzimuth(double azimuth_rad) const {
  int best = 0;
  double best_error = std::numeric_limits<double>::infinity();
  for (int i = 0; i < config_.beams; ++i) {
    const double error = std::abs(std::remainder(azimuths_[i] - azimuth_rad, kTwoPi));
    if (error < best_error) {
      best_error = error;
      best = i;
    }
  }
  return best;
}

LidarScan Lidar::scan(const Eigen::Vector3d& position_m,
                      const Eigen::Quaterniond& world_from_body) {
  return static_cast<const Lidar&>(*this).scan(position_m, world_from_body, rng_);
}

LidarScan Lidar::scan(const Eigen::Vector3d& position_m, const Eigen::Quaterniond& world_from_body,
                      std::mt19937_64& rng) const {
  const Eigen::Matrix3d rotation = world_from_body.normalized().toRotationMatrix();
  const Eigen::Vector3d origin = position_m + rotation * config_.mount_position_m;
  LidarScan scan;
  scan.beams = config_.beams;
  scan.channels = config_.channels;
  scan.ranges_m.resize(directions_.size());
  constexpr float kInf = std::numeric_limits<float>::infinity();
  for (std::size_t i = 0; i < directions_.size(); ++i) {
    const double range = world_->castRay(origin, rotation * directions_[i], config_.range_max_m);
    // One draw per beam whatever the outcome, so that a scene change does not
    // shift the noise of the other beams.
    const double noise =
        config_.noise_stddev_m > 0.0 ? config_.noise_stddev_m * standardNormal(rng) : 0.0;
    if (!std::isfinite(range)) {
      scan.ranges_m[i] = kInf;
    } else if (range < config_.range_min_m) {
      scan.ranges_m[i] = -kInf;
    } else {
      scan.ranges_m[i] =
          static_cast<float>(std::clamp(range + noise, config_.range_min_m, config_.range_max_m));
    }
  }
  return scan;
}

}  // namespace behaviorlib::sim
