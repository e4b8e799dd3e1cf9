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
#include <cstdint>
#include <memory>
#include <optional>
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
  ~OccupancyMap();
  OccupancyMap(OccupancyMap&&) noexcept;
  OccupancyMap& operator=(OccupancyMap&&) noexcept;

  /// One scan seen from `origin_m` (world): `hits_m` are surfaces (their
  /// voxels become more occupied, the voxels along each ray more free);
  /// `misses_m` are the ends of rays that hit nothing within range (free
  /// along the ray only). The result is OctoMap's own: the misses' rays as
  /// free-space updates, then `insertPointCloud(hits, origin, -1, lazy_eval
  /// false, discretize true)`. But the scan's keys are collected in sorted
  /// vectors instead of hash sets, and the inner nodes above the updated
  /// leaves are brought up to date (max child, pruning) once per scan,
  /// bottom up, instead of along the path of every leaf update: the same
  /// tree for a fraction of the work (navigation_test compares the two).
  void insertScan(const Eigen::Vector3d& origin_m, const std::vector<Eigen::Vector3d>& hits_m,
                  const std::vector<Eigen::Vector3d>& misses_m = {});
  void clear();
  /// True when `p`'s voxel is free at OctoMap's clamping bound: many more
  /// rays crossed it than anything hit it.
  bool certainlyFree(const Eigen::Vector3d& p) const;
  /// Takes back what made a voxel occupied: its odds go to just below the
  /// occupancy threshold (not occupied, as uncertain as a voxel can be;
  /// nothing for a free or unknown one). OctoMap's deleteNode, which would
  /// make it unknown, trips an OctoMap assertion on a tree updated without
  /// lazy evaluation.
  void forgetVoxel(const Eigen::Vector3d& p);

  /// True when an occupied voxel is within `radius_m` of `p` (distance to
  /// the voxel's cube).
  bool collides(const Eigen::Vector3d& p, double radius_m) const;
  bool occupied(const Eigen::Vector3d& p) const;
  bool known(const Eigen::Vector3d& p) const;

  /// Writes the map in OctoMap's binary format (.bt: maximum likelihood),
  /// or its full format for a ".ot" path. INVALID_ARGUMENT naming the path
  /// when it cannot be written.
  absl::Status save(const std::string& path) const;
  /// The bytes save() would write: OctoMap's full format when `full` (.ot),
  /// else its binary format (.bt).
  std::string serialize(bool full) const;
  /// Whether save() writes the full format to `path` (it ends in ".ot").
  static bool fullFormatFor(const std::string& path);

  size_t occupiedLeafCount() const;
  /// Volume of known free space (m^3).
  double freeVolumeM3() const;
  /// Volume of known free space inside an axis-aligned box (m^3).
  double freeVolumeM3(const Eigen::Vector3d& min_m, const Eigen::Vector3d& max_m) const;
  double resolutionM() const { return tree_->getResolution(); }
  /// Increases with every change of the map (insertScan, clear).
  uint64_t revision() const { return revision_; }
  const octomap::OcTree& tree() const { return *tree_; }

 private:
  struct Scratch;  // reused by insertScan: the scan's keys and a ray
  MapOptions options_;
  std::unique_ptr<octomap::OcTree> tree_;
  std::unique_ptr<Scratch> scratch_;
  uint64_t revision_ = 0;
};

/// The map inflated by a vehicle radius over a box, as a dense grid of the
/// map's resolution: a cell is blocked when an occupied cell lies within the
/// radius of its centre, found with an exact Euclidean distance transform
/// (three 1-D passes, linear in the cells). Built once per plan in a few
/// milliseconds; each check is then one lookup (the planner makes
/// thousands). A point is judged by the centre of its cell, so the radius
/// given should include a margin of half a cell diagonal (0.09 m at 0.1 m).
class InflatedGrid {
 public:
  InflatedGrid(const OccupancyMap& map, const Eigen::Vector3d& min_m, const Eigen::Vector3d& max_m,
               double radius_m);
  /// True when `p` is blocked or outside the box.
  bool blocked(const Eigen::Vector3d& p) const;
  /// The same for another radius (up to the grid's: obstacles outside the
  /// box are counted within that reach only).
  bool blocked(const Eigen::Vector3d& p, double radius_m) const;
  /// Whether a 26-connected chain of cells not blocked at `radius_m` joins
  /// the cell of `from` to the cell of `to` (either may be blocked itself:
  /// the vehicle's own cell, the goal's; false when either is outside).
  bool connected(const Eigen::Vector3d& from, const Eigen::Vector3d& to, double radius_m) const;
  /// Distance from the centre of `p`'s cell to the nearest occupied voxel's
  /// cube (m; infinity with none in reach, 0 outside the box).
  double clearanceM(const Eigen::Vector3d& p) const;
  /// The radius the grid was inflated by (m).
  double radiusM() const { return radius_; }
  double resolutionM() const { return resolution_; }
  size_t blockedCount() const;

 private:
  std::optional<size_t> cellOf(const Eigen::Vector3d& p) const;

  Eigen::Vector3d min_;
  double resolution_;
  Eigen::Vector3i size_;
  float radius_ = 0.0f;
  std::vector<float> clearance_;
};

}  // namespace behaviorlib::nav
