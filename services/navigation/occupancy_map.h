#pragma once

// OccupancyMap: the OctoMap of navigation_with_lidar, built from lidar scans
// while the behavior system runs; and the collision check the planner uses.
//
//   OccupancyMap map({.resolution_m = 0.1});
//   map.insertScan(sensor_origin_m, hit_points_m, max_range_endpoints_m);
//   bool blocked = map.collides(p, 0.3);
//   map.save("/maps/building.bt");   // octovis, binvox2bt, OcTree::readBinary
//
// Unknown space counts as free for collision checks (the map grows as the
// vehicle explores; the vehicle's own lidar sees what is ahead).
// Not thread-safe: the behavior system serializes access.

#include <octomap/OcTree.h>

#include <Eigen/Core>
#include <memory>
#include <string>
#include <vector>

#include "absl/status/status.h"

namespace behaviorlib::nav {

struct MapOptions {
  double resolution_m = 0.1;
  /// Occupancy probabilities of a hit and a miss (OctoMap's sensor model).
  double probability_hit = 0.7;
  double probability_miss = 0.4;
};

class OccupancyMap {
 public:
  explicit OccupancyMap(MapOptions options = {});

  /// One scan seen from `origin_m` (world): `hits_m` are surfaces (their
  /// voxels become more occupied, the voxels along each ray more free);
  /// `misses_m` are the ends of rays that hit nothing within range (free
  /// along the ray only).
  void insertScan(const Eigen::Vector3d& origin_m, const std::vector<Eigen::Vector3d>& hits_m,
                  const std::vector<Eigen::Vector3d>& misses_m = {});
  void clear();

  /// True when an occupied voxel is within `radius_m` of `p` (distance to
  /// the voxel's cube).
  bool collides(const Eigen::Vector3d& p, double radius_m) const;
  bool occupied(const Eigen::Vector3d& p) const;
  bool known(const Eigen::Vector3d& p) const;

  /// Writes the map in OctoMap's binary format (.bt: maximum likelihood),
  /// or its full format for a ".ot" path. INVALID_ARGUMENT naming the path
  /// when it cannot be written.
  absl::Status save(const std::string& path) const;

  size_t occupiedLeafCount() const;
  /// Volume of known free space (m^3).
  double freeVolumeM3() const;
  /// Volume of known free space inside an axis-aligned box (m^3).
  double freeVolumeM3(const Eigen::Vector3d& min_m, const Eigen::Vector3d& max_m) const;
  double resolutionM() const { return tree_->getResolution(); }
  const octomap::OcTree& tree() const { return *tree_; }

 private:
  MapOptions options_;
  std::unique_ptr<octomap::OcTree> tree_;
};

}  // namespace behaviorlib::nav
