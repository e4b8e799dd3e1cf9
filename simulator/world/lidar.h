#pragma once

// Lidar: a 2-D or 3-D scanning range finder simulated by ray casting against
// a World, with Gaussian range noise.
//
//   LidarConfig config;              // 2-D: 360 beams over a full turn
//   config.range_max_m = 30.0;
//   config.noise_stddev_m = 0.02;
//   config.seed = 7;
//   absl::StatusOr<Lidar> lidar = Lidar::create(world, config);
//   LidarScan scan = lidar->scan(position_m, world_from_body);
//   float ahead_m = scan.at(0, lidar->beamNearestAzimuth(0.0));
//
// Conventions: the lidar sits at `mount_position_m` in the body frame (FLU:
// x forward, y left, z up) with its axes along the body's. Beam azimuth 0 is
// +x (forward), counter-clockwise (towards +y, left) positive; elevation
// positive is up. Ranges follow ROS REP 117: +inf when nothing is within
// range_max_m, -inf when the surface is closer than range_min_m; measured
// ranges are clamped to [range_min_m, range_max_m].
//
// Determinism: the noise comes from std::mt19937_64 and a Box-Muller
// transform written here (std::normal_distribution differs between standard
// libraries), so a seed gives the same scans on every platform.

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cstdint>
#include <numbers>
#include <random>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "formats/world/world.h"

namespace behaviorlib::sim {

struct LidarConfig {
  /// Beams per channel, spread evenly from angle_min_rad to angle_max_rad
  /// inclusive; when the span is a full turn (>= 2 pi) the last beam does not
  /// repeat the first.
  int beams = 360;
  double angle_min_rad = -std::numbers::pi;
  double angle_max_rad = std::numbers::pi;
  /// Vertical channels, spread evenly from elevation_min_rad to
  /// elevation_max_rad inclusive. 1 channel (at elevation_min_rad) is a 2-D lidar.
  int channels = 1;
  double elevation_min_rad = 0.0;
  double elevation_max_rad = 0.0;
  double range_min_m = 0.1;
  double range_max_m = 30.0;
  /// Standard deviation of the Gaussian noise added to each range.
  double noise_stddev_m = 0.01;
  /// Seed of the Lidar's own random generator.
  std::uint64_t seed = 1;
  /// Position of the lidar in the body frame (FLU).
  Eigen::Vector3d mount_position_m = Eigen::Vector3d::Zero();

  /// OK, or kInvalidArgument naming the first bad field.
  absl::Status validate() const;
};

/// One scan: ranges_m[channel * beams + beam], metres, in the body frame.
struct LidarScan {
  int beams = 0;
  int channels = 0;
  std::vector<float> ranges_m;

  float at(int channel, int beam) const { return ranges_m[channel * beams + beam]; }
};

class Lidar {
 public:
  /// `world` must outlive the Lidar.
  static absl::StatusOr<Lidar> create(const world::World& world, LidarConfig config);

  const LidarConfig& config() const { return config_; }
  double azimuthRad(int beam) const { return azimuths_[beam]; }
  double elevationRad(int channel) const { return elevations_[channel]; }
  /// The beam whose azimuth is closest to `azimuth_rad` (modulo a full turn).
  int beamNearestAzimuth(double azimuth_rad) const;
  /// Unit direction of a beam in the body frame.
  const Eigen::Vector3d& direction(int channel, int beam) const {
    return directions_[channel * config_.beams + beam];
  }

  /// Scans from the body pose (position in the world, orientation world <-
  /// body) using the Lidar's own generator, seeded with config().seed.
  LidarScan scan(const Eigen::Vector3d& position_m, const Eigen::Quaterniond& world_from_body);
  /// Same, drawing the noise from `rng`.
  LidarScan scan(const Eigen::Vector3d& position_m, const Eigen::Quaterniond& world_from_body,
                 std::mt19937_64& rng) const;
  /// Restarts the Lidar's own generator.
  void reseed(std::uint64_t seed) { rng_.seed(seed); }

 private:
  Lidar(const world::World& world, LidarConfig config);

  const world::World* world_;
  LidarConfig config_;
  std::vector<double> azimuths_;
  std::vector<double> elevations_;
  std::vector<Eigen::Vector3d> directions_;  ///< body frame, [channel * beams + beam]
  std::mt19937_64 rng_;
};

/// A standard normal sample from `rng` (Box-Muller), the same on every platform.
double standardNormal(std::mt19937_64& rng);

}  // namespace behaviorlib::sim
