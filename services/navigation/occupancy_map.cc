#include "navigation/occupancy_map.h"

#include <algorithm>
#include <cmath>

namespace behaviorlib::nav {
namespace {

octomap::point3d toOcto(const Eigen::Vector3d& p) {
  return octomap::point3d(static_cast<float>(p.x()), static_cast<float>(p.y()),
                          static_cast<float>(p.z()));
}

}  // namespace

OccupancyMap::OccupancyMap(MapOptions options)
    : options_(options), tree_(std::make_unique<octomap::OcTree>(options.resolution_m)) {
  tree_->setProbHit(options.probability_hit);
  tree_->setProbMiss(options.probability_miss);
}

void OccupancyMap::insertScan(const Eigen::Vector3d& origin_m,
                              const std::vector<Eigen::Vector3d>& hits_m,
                              const std::vector<Eigen::Vector3d>& misses_m) {
  const octomap::point3d origin = toOcto(origin_m);
  octomap::Pointcloud cloud;
  cloud.reserve(hits_m.size());
  for (const auto& p : hits_m) {
    if (p.allFinite()) cloud.push_back(toOcto(p));
  }
  // Rays that hit nothing: free space only. computeUpdate marks the end
  // voxel occupied, so trace them ourselves (discretised, no duplicates).
  octomap::KeySet free_cells;
  octomap::KeyRay ray;
  for (const auto& p : misses_m) {
    if (!p.allFinite()) continue;
    if (tree_->computeRayKeys(origin, toOcto(p), ray)) free_cells.insert(ray.begin(), ray.end());
  }
  for (const auto& key : free_cells) tree_->updateNode(key, false, true);
  tree_->insertPointCloud(cloud, origin, -1.0, /*lazy_eval=*/true, /*discretize=*/true);
  tree_->updateInnerOccupancy();
}

void OccupancyMap::clear() { tree_->clear(); }

bool OccupancyMap::occupied(const Eigen::Vector3d& p) const {
  const octomap::OcTreeNode* node = tree_->search(toOcto(p));
  return node != nullptr && tree_->isNodeOccupied(node);
}

bool OccupancyMap::known(const Eigen::Vector3d& p) const {
  return tree_->search(toOcto(p)) != nullptr;
}

bool OccupancyMap::collides(const Eigen::Vector3d& p, double radius_m) const {
  const octomap::point3d min = toOcto(p - Eigen::Vector3d::Constant(radius_m));
  const octomap::point3d max = toOcto(p + Eigen::Vector3d::Constant(radius_m));
  for (auto it = tree_->begin_leafs_bbx(min, max), end = tree_->end_leafs_bbx(); it != end; ++it) {
    if (!tree_->isNodeOccupied(*it)) continue;
    const double half = 0.5 * it.getSize();
    const octomap::point3d c = it.getCoordinate();
    const Eigen::Vector3d d(std::max(0.0, std::abs(p.x() - c.x()) - half),
                            std::max(0.0, std::abs(p.y() - c.y()) - half),
                            std::max(0.0, std::abs(p.z() - c.z()) - half));
    if (d.norm() <= radius_m) return true;
  }
  return false;
}

absl::Status OccupancyMap::save(const std::string& path) const {
  const bool full = path.size() > 3 && path.substr(path.size() - 3) == ".ot";
  const bool ok = full ? tree_->write(path) : tree_->writeBinaryConst(path);
  if (!ok) {
    return absl::InvalidArgumentError("cannot write the map to '" + path +
                                      "' (does its directory exist, and may it be written?)");
  }
  return absl::OkStatus();
}

size_t OccupancyMap::occupiedLeafCount() const {
  size_t n = 0;
  for (auto it = tree_->begin_leafs(), end = tree_->end_leafs(); it != end; ++it) {
    if (tree_->isNodeOccupied(*it)) ++n;
  }
  return n;
}

double OccupancyMap::freeVolumeM3() const {
  double v = 0;
  for (auto it = tree_->begin_leafs(), end = tree_->end_leafs(); it != end; ++it) {
    if (!tree_->isNodeOccupied(*it)) v += std::pow(it.getSize(), 3);
  }
  return v;
}

double OccupancyMap::freeVolumeM3(const Eigen::Vector3d& min_m,
                                  const Eigen::Vector3d& max_m) const {
  double v = 0;
  for (auto it = tree_->begin_leafs_bbx(toOcto(min_m), toOcto(max_m)), end = tree_->end_leafs_bbx();
       it != end; ++it) {
    if (tree_->isNodeOccupied(*it)) continue;
    // A pruned leaf may stick out of the box: count only its inside part.
    const double half = 0.5 * it.getSize();
    const octomap::point3d c = it.getCoordinate();
    double part = 1.0;
    for (int i = 0; i < 3; ++i) {
      const double lo = std::max(static_cast<double>(c(i)) - half, min_m[i]);
      const double hi = std::min(static_cast<double>(c(i)) + half, max_m[i]);
      part *= std::max(0.0, hi - lo);
    }
    v += part;
  }
  return v;
}

}  // namespace behaviorlib::nav
