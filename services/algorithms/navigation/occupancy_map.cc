#include "behaviorlib/navigation/occupancy_map.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <functional>
#include <limits>
#include <sstream>

namespace behaviorlib::nav {
namespace {

octomap::point3d toOcto(const Eigen::Vector3d& p) {
  return octomap::point3d(static_cast<float>(p.x()), static_cast<float>(p.y()),
                          static_cast<float>(p.z()));
}

// A voxel's key as its path from the root: for each depth, from the top,
// the child index OctoMap computes (x bit, y bit << 1, z bit << 2), three
// bits per level. Sorted, the codes follow the tree (depth first), and a
// node's code at a coarser depth is the code shifted right.
uint64_t spreadBits(uint64_t v) {  // bit i to bit 3i, for 16 bits
  v &= 0xffff;
  v = (v | (v << 16)) & 0x0000ff0000ffULL;
  v = (v | (v << 8)) & 0x00f00f00f00fULL;
  v = (v | (v << 4)) & 0x0c30c30c30c3ULL;
  v = (v | (v << 2)) & 0x249249249249ULL;
  return v;
}

uint64_t packBits(uint64_t v) {  // the inverse: bit 3i to bit i
  v &= 0x249249249249ULL;
  v = (v | (v >> 2)) & 0x0c30c30c30c3ULL;
  v = (v | (v >> 4)) & 0x00f00f00f00fULL;
  v = (v | (v >> 8)) & 0x0000ff0000ffULL;
  v = (v | (v >> 16)) & 0xffff;
  return v;
}

uint64_t pathCode(const octomap::OcTreeKey& k) {
  return spreadBits(k[0]) | (spreadBits(k[1]) << 1) | (spreadBits(k[2]) << 2);
}

octomap::OcTreeKey keyOf(uint64_t code) {
  return octomap::OcTreeKey(static_cast<octomap::key_type>(packBits(code)),
                            static_cast<octomap::key_type>(packBits(code >> 1)),
                            static_cast<octomap::key_type>(packBits(code >> 2)));
}

// Sorted and unique. Large inputs (a scan has tens of thousands of ray
// voxels) by a radix sort of the 48-bit codes in three 16-bit passes, with
// the caller's buffers (reused scan after scan: the buckets are 256 KiB).
void sortUnique(std::vector<uint64_t>& codes, std::vector<uint64_t>& buffer,
                std::vector<uint32_t>& buckets) {
  constexpr int kBits = 16;
  constexpr size_t kBuckets = size_t{1} << kBits;
  if (codes.size() > 8 * 1024) {
    buckets.resize(kBuckets);
    buffer.resize(codes.size());
    for (int pass = 0; pass < 3; ++pass) {
      const int shift = pass * kBits;
      std::fill(buckets.begin(), buckets.end(), 0u);
      for (uint64_t c : codes) ++buckets[(c >> shift) & (kBuckets - 1)];
      uint32_t sum = 0;
      for (uint32_t& n : buckets) {
        const uint32_t here = n;
        n = sum;
        sum += here;
      }
      for (uint64_t c : codes) buffer[buckets[(c >> shift) & (kBuckets - 1)]++] = c;
      codes.swap(buffer);
    }
  } else {
    std::sort(codes.begin(), codes.end());
  }
  codes.erase(std::unique(codes.begin(), codes.end()), codes.end());
}

// Finds nodes as OcTree::search(key, depth) does, but starts each search
// from the deepest node the previous one shared with it: codes visited in
// order share most of their path. Valid while no node on the remembered
// path is deleted (forget() after pruning).
class PathFinder {
 public:
  explicit PathFinder(octomap::OcTree& tree) : tree_(tree) {}

  // The node at `depth` on `code`'s path; or the leaf that covers it (a
  // pruned node); or null when the path ends at a node with other children.
  octomap::OcTreeNode* find(uint64_t code, unsigned depth) {
    path_[0] = tree_.getRoot();
    if (path_[0] == nullptr) return nullptr;
    const uint64_t differ = code ^ last_;
    const unsigned common =
        differ == 0 ? kDepth : static_cast<unsigned>(__builtin_clzll(differ) - 16) / 3;
    unsigned d = std::min(common, valid_);
    octomap::OcTreeNode* node = path_[d];
    last_ = code;
    for (; d < depth; ++d) {
      const unsigned child = static_cast<unsigned>(code >> (3 * (kDepth - 1 - d))) & 7u;
      if (!tree_.nodeChildExists(node, child)) {
        valid_ = d;
        return tree_.nodeHasChildren(node) ? nullptr : node;
      }
      node = tree_.getNodeChild(node, child);
      path_[d + 1] = node;
    }
    valid_ = depth;
    return node;
  }
  // The depth the last find() reached.
  unsigned reached() const { return valid_; }
  // The tree may have changed below the root: search anew.
  void forget() { valid_ = 0; }

 private:
  static constexpr unsigned kDepth = 16;
  octomap::OcTree& tree_;
  std::array<octomap::OcTreeNode*, kDepth + 1> path_{};
  unsigned valid_ = 0;
  uint64_t last_ = 0;
};

}  // namespace

struct OccupancyMap::Scratch {
  octomap::KeyRay ray;
  std::vector<uint64_t> miss_free, ends, hit_free, occupied, changed, buffer;
  std::vector<uint32_t> buckets;  // sortUnique's
};

OccupancyMap::OccupancyMap(MapOptions options)
    : options_(options), tree_(std::make_unique<octomap::OcTree>(options.resolution_m)) {
  tree_->setProbHit(options.probability_hit);
  tree_->setProbMiss(options.probability_miss);
}

OccupancyMap::~OccupancyMap() = default;
OccupancyMap::OccupancyMap(OccupancyMap&&) noexcept = default;
OccupancyMap& OccupancyMap::operator=(OccupancyMap&&) noexcept = default;

void OccupancyMap::insertScan(const Eigen::Vector3d& origin_m,
                              const std::vector<Eigen::Vector3d>& hits_m,
                              const std::vector<Eigen::Vector3d>& misses_m) {
  if (!scratch_) scratch_ = std::make_unique<Scratch>();
  Scratch& s = *scratch_;
  octomap::OcTree& tree = *tree_;
  const octomap::point3d origin = toOcto(origin_m);
  const auto rayInto = [&](const octomap::point3d& end, std::vector<uint64_t>& codes) {
    if (!tree.computeRayKeys(origin, end, s.ray)) return;
    for (const octomap::OcTreeKey& k : s.ray) codes.push_back(pathCode(k));
  };
  // Rays that hit nothing: free space only (OctoMap's computeUpdate would
  // mark the end voxel occupied).
  s.miss_free.clear();
  for (const auto& p : misses_m) {
    if (p.allFinite()) rayInto(toOcto(p), s.miss_free);
  }
  sortUnique(s.miss_free, s.buffer, s.buckets);
  // Hits as insertPointCloud(discretize) takes them: one per voxel, at its
  // centre; free along the ray, occupied at the end, and a voxel both free
  // and occupied in this scan counts as occupied.
  s.ends.clear();
  for (const auto& p : hits_m) {
    if (p.allFinite()) s.ends.push_back(pathCode(tree.coordToKey(toOcto(p))));
  }
  sortUnique(s.ends, s.buffer, s.buckets);
  s.hit_free.clear();
  s.occupied.clear();
  for (uint64_t end : s.ends) {
    const octomap::point3d centre = tree.keyToCoord(keyOf(end));
    rayInto(centre, s.hit_free);
    octomap::OcTreeKey key;
    if (tree.coordToKeyChecked(centre, key)) s.occupied.push_back(pathCode(key));
  }
  sortUnique(s.hit_free, s.buffer, s.buckets);
  sortUnique(s.occupied, s.buffer, s.buckets);
  s.hit_free.erase(std::set_difference(s.hit_free.begin(), s.hit_free.end(), s.occupied.begin(),
                                       s.occupied.end(), s.hit_free.begin()),
                   s.hit_free.end());

  // The leaves, in OctoMap's order (the misses' free space, then the hits'),
  // without updating the inner nodes on each one's path (lazy_eval). A leaf
  // already at the clamping bound in the update's direction is left as it
  // is, as updateNode's early abort leaves it.
  const float min_log = tree.getClampingThresMinLog();
  const float max_log = tree.getClampingThresMaxLog();
  const float hit_log = tree.getProbHitLog();
  const float miss_log = tree.getProbMissLog();
  const unsigned depth_max = tree.getTreeDepth();  // 16, as PathFinder's codes
  PathFinder finder(tree);
  s.changed.clear();
  const auto update = [&](uint64_t code, bool occupied) {
    octomap::OcTreeNode* leaf = finder.find(code, depth_max);
    if (leaf != nullptr &&
        (occupied ? leaf->getLogOdds() >= max_log : leaf->getLogOdds() <= min_log)) {
      return;
    }
    s.changed.push_back(code);
    if (leaf != nullptr && finder.reached() == depth_max) {
      // The voxel's own leaf: what updateNodeRecurs does at the last level.
      tree.updateNodeLogOdds(leaf, occupied ? hit_log : miss_log);
      return;
    }
    // A pruned leaf to expand, or a path to create.
    tree.updateNode(keyOf(code), occupied, /*lazy_eval=*/true);
    finder.forget();
  };
  for (uint64_t c : s.miss_free) update(c, false);
  for (uint64_t c : s.hit_free) update(c, false);
  for (uint64_t c : s.occupied) update(c, true);

  // Then every inner node above a changed leaf, deepest first, as
  // updateNodeRecurs does on its way back up: pruned when its eight
  // children are equal leaves, otherwise given its largest child's odds.
  // Each sees its children final, so the tree ends as OctoMap's per-leaf
  // updates leave it. (Shifted, the sorted codes of one level are the sorted
  // codes of the next one up, with repeats.)
  sortUnique(s.changed, s.buffer, s.buckets);
  for (unsigned depth = depth_max; depth-- > 0;) {
    for (uint64_t& c : s.changed) c >>= 3;
    s.changed.erase(std::unique(s.changed.begin(), s.changed.end()), s.changed.end());
    finder.forget();  // pruning one level down deleted nodes
    for (uint64_t c : s.changed) {
      octomap::OcTreeNode* node = finder.find(c << (3 * (depth_max - depth)), depth);
      if (node == nullptr || !tree.nodeHasChildren(node)) continue;  // a leaf (pruned below)
      if (!tree.pruneNode(node)) node->updateOccupancyChildren();
    }
  }
  ++revision_;
}

void OccupancyMap::clear() {
  tree_->clear();
  ++revision_;
}

bool OccupancyMap::certainlyFree(const Eigen::Vector3d& p) const {
  const octomap::OcTreeNode* node = tree_->search(toOcto(p));
  return node != nullptr && node->getLogOdds() <= tree_->getClampingThresMinLog() + 1e-3f;
}

void OccupancyMap::forgetVoxel(const Eigen::Vector3d& p) {
  const octomap::OcTreeNode* node = tree_->search(toOcto(p));
  if (node == nullptr || !tree_->isNodeOccupied(node)) return;
  tree_->setNodeValue(toOcto(p), tree_->getOccupancyThresLog() - 0.01f, /*lazy_eval=*/false);
  ++revision_;
}

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

bool OccupancyMap::fullFormatFor(const std::string& path) {
  return path.size() > 3 && path.substr(path.size() - 3) == ".ot";
}

std::string OccupancyMap::serialize(bool full) const {
  std::ostringstream out;
  if (full) {
    tree_->write(out);
  } else {
    tree_->writeBinaryConst(out);
  }
  return std::move(out).str();
}

absl::Status OccupancyMap::save(const std::string& path) const {
  const bool ok = fullFormatFor(path) ? tree_->write(path) : tree_->writeBinaryConst(path);
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

namespace behaviorlib::nav {

namespace {

// One pass of the exact 1-D squared Euclidean distance transform (Felzenszwalb
// and Huttenlocher's lower envelope of parabolas) over n samples `f` spaced
// `stride` apart in `data`.
void distance1d(float* data, int n, size_t stride, std::vector<float>& f, std::vector<float>& d,
                std::vector<int>& v, std::vector<float>& z) {
  constexpr float kInf = std::numeric_limits<float>::infinity();
  for (int i = 0; i < n; ++i) f[i] = data[i * stride];
  int k = 0;
  v[0] = 0;
  z[0] = -kInf;
  z[1] = kInf;
  for (int q = 1; q < n; ++q) {
    if (f[q] == kInf) continue;
    if (f[v[k]] == kInf) {
      v[k] = q;
      continue;
    }
    float s = ((f[q] + q * q) - (f[v[k]] + v[k] * v[k])) / (2.0f * (q - v[k]));
    while (k > 0 && s <= z[k]) {
      --k;
      s = ((f[q] + q * q) - (f[v[k]] + v[k] * v[k])) / (2.0f * (q - v[k]));
    }
    ++k;
    v[k] = q;
    z[k] = s;
    z[k + 1] = kInf;
  }
  k = 0;
  for (int q = 0; q < n; ++q) {
    while (z[k + 1] < q) ++k;
    d[q] = f[v[k]] == kInf ? kInf : (q - v[k]) * (q - v[k]) + f[v[k]];
  }
  for (int i = 0; i < n; ++i) data[i * stride] = d[i];
}

}  // namespace

InflatedGrid::InflatedGrid(const OccupancyMap& map, const Eigen::Vector3d& min_m,
                           const Eigen::Vector3d& max_m, double radius_m)
    : min_(min_m), resolution_(map.resolutionM()) {
  // Occupied cells (pruned leaves cover several), padded by the radius so
  // that obstacles just outside the box still count.
  const int pad = static_cast<int>(std::ceil(radius_m / resolution_)) + 1;
  for (int i = 0; i < 3; ++i) {
    size_[i] = std::max(1, static_cast<int>(std::ceil((max_m[i] - min_m[i]) / resolution_)));
  }
  const Eigen::Vector3i full = size_ + Eigen::Vector3i::Constant(2 * pad);
  const size_t count = static_cast<size_t>(full.x()) * full.y() * full.z();
  constexpr float kInf = std::numeric_limits<float>::infinity();
  std::vector<float> dist(count, kInf);
  auto index = [&](int x, int y, int z) {
    return (static_cast<size_t>(x) * full.y() + y) * full.z() + z;
  };
  const octomap::OcTree& tree = map.tree();
  const Eigen::Vector3d origin = min_m - Eigen::Vector3d::Constant(pad * resolution_);
  const Eigen::Vector3d top = origin + full.cast<double>() * resolution_;
  auto mark = [&](const Eigen::Vector3d& c, double half) {
    Eigen::Vector3i lo, hi;
    for (int i = 0; i < 3; ++i) {
      lo[i] =
          std::max(0, static_cast<int>(std::floor((c[i] - half - origin[i]) / resolution_ + 1e-6)));
      hi[i] =
          std::min(full[i] - 1,
                   static_cast<int>(std::ceil((c[i] + half - origin[i]) / resolution_ - 1e-6)) - 1);
    }
    for (int x = lo.x(); x <= hi.x(); ++x) {
      for (int y = lo.y(); y <= hi.y(); ++y) {
        for (int z = lo.z(); z <= hi.z(); ++z) dist[index(x, y, z)] = 0.0f;
      }
    }
  };
  // Depth-first over the octree, skipping every subtree whose node is not
  // occupied: inner nodes hold the maximum of their children (the map is
  // updated without lazy evaluation), so only branches leading to occupied
  // voxels are visited, and only those that meet the box.
  const unsigned max_depth = tree.getTreeDepth();
  const octomap::OcTreeKey root_key = tree.coordToKey(octomap::point3d(0, 0, 0));
  std::function<void(const octomap::OcTreeNode*, const octomap::OcTreeKey&, unsigned)> visit =
      [&](const octomap::OcTreeNode* node, const octomap::OcTreeKey& key, unsigned depth) {
        if (!tree.isNodeOccupied(node)) return;
        const double size = resolution_ * static_cast<double>(1u << (max_depth - depth));
        const octomap::point3d pc = tree.keyToCoord(key, depth);
        const Eigen::Vector3d c(pc.x(), pc.y(), pc.z());
        for (int i = 0; i < 3; ++i) {
          if (c[i] + 0.5 * size < origin[i] || c[i] - 0.5 * size > top[i]) return;
        }
        if (depth == max_depth || !tree.nodeHasChildren(node)) {
          mark(c, 0.5 * size);
          return;
        }
        const unsigned short offset = static_cast<unsigned short>(root_key[0] >> (depth + 1));
        for (unsigned i = 0; i < 8; ++i) {
          if (!tree.nodeChildExists(node, i)) continue;
          octomap::OcTreeKey child;
          octomap::computeChildKey(i, offset, key, child);
          visit(tree.getNodeChild(node, i), child, depth + 1);
        }
      };
  if (tree.getRoot() != nullptr) visit(tree.getRoot(), root_key, 0);
  // Squared distance (in cells) to the nearest occupied cell: three passes.
  const int longest = full.maxCoeff();
  std::vector<float> f(longest), d(longest), z(longest + 1);
  std::vector<int> v(longest);
  for (int x = 0; x < full.x(); ++x) {
    for (int y = 0; y < full.y(); ++y) distance1d(&dist[index(x, y, 0)], full.z(), 1, f, d, v, z);
  }
  for (int x = 0; x < full.x(); ++x) {
    for (int z0 = 0; z0 < full.z(); ++z0)
      distance1d(&dist[index(x, 0, z0)], full.y(), full.z(), f, d, v, z);
  }
  for (int y = 0; y < full.y(); ++y) {
    for (int z0 = 0; z0 < full.z(); ++z0) {
      distance1d(&dist[index(0, y, z0)], full.x(), static_cast<size_t>(full.y()) * full.z(), f, d,
                 v, z);
    }
  }
  // Clearance of a cell: from its centre to the nearest occupied cell's
  // cube (centre distance minus half a cell); blocked within the radius.
  radius_ = static_cast<float>(radius_m);
  clearance_.assign(static_cast<size_t>(size_.x()) * size_.y() * size_.z(), kInf);
  const float half = static_cast<float>(0.5 * resolution_);
  for (int x = 0; x < size_.x(); ++x) {
    for (int y = 0; y < size_.y(); ++y) {
      for (int z0 = 0; z0 < size_.z(); ++z0) {
        const float d2 = dist[index(x + pad, y + pad, z0 + pad)];
        if (d2 == kInf) continue;
        clearance_[(static_cast<size_t>(x) * size_.y() + y) * size_.z() + z0] =
            std::max(0.0f, std::sqrt(d2) * static_cast<float>(resolution_) - half);
      }
    }
  }
}

std::optional<size_t> InflatedGrid::cellOf(const Eigen::Vector3d& p) const {
  Eigen::Vector3i cell;
  for (int i = 0; i < 3; ++i) {
    const double f = std::floor((p[i] - min_[i]) / resolution_);
    if (!(f >= 0 && f < size_[i])) return std::nullopt;
    cell[i] = static_cast<int>(f);
  }
  return (static_cast<size_t>(cell.x()) * size_.y() + cell.y()) * size_.z() + cell.z();
}

bool InflatedGrid::blocked(const Eigen::Vector3d& p) const {
  const std::optional<size_t> cell = cellOf(p);
  return !cell || clearance_[*cell] <= radius_;
}

bool InflatedGrid::blocked(const Eigen::Vector3d& p, double radius_m) const {
  const std::optional<size_t> cell = cellOf(p);
  return !cell || clearance_[*cell] <= static_cast<float>(radius_m);
}

bool InflatedGrid::connected(const Eigen::Vector3d& from, const Eigen::Vector3d& to,
                             double radius_m) const {
  const std::optional<size_t> a = cellOf(from), b = cellOf(to);
  if (!a || !b) return false;
  const float radius = static_cast<float>(radius_m);
  const size_t sy = static_cast<size_t>(size_.y()), sz = static_cast<size_t>(size_.z());
  std::vector<uint8_t> seen(clearance_.size(), 0);
  std::vector<size_t> frontier{*a};
  seen[*a] = 1;
  while (!frontier.empty()) {
    const size_t c = frontier.back();
    frontier.pop_back();
    if (c == *b) return true;
    const int x = static_cast<int>(c / (sy * sz)), y = static_cast<int>((c / sz) % sy),
              z = static_cast<int>(c % sz);
    for (int dx = -1; dx <= 1; ++dx) {
      for (int dy = -1; dy <= 1; ++dy) {
        for (int dz = -1; dz <= 1; ++dz) {
          const int nx = x + dx, ny = y + dy, nz = z + dz;
          if (nx < 0 || ny < 0 || nz < 0 || nx >= size_.x() || ny >= size_.y() || nz >= size_.z())
            continue;
          const size_t n = (static_cast<size_t>(nx) * sy + ny) * sz + nz;
          if (seen[n]) continue;
          seen[n] = 1;
          if (n != *b && clearance_[n] <= radius) continue;
          frontier.push_back(n);
        }
      }
    }
  }
  return false;
}

double InflatedGrid::clearanceM(const Eigen::Vector3d& p) const {
  const std::optional<size_t> cell = cellOf(p);
  return cell ? static_cast<double>(clearance_[*cell]) : 0.0;
}

size_t InflatedGrid::blockedCount() const {
  return static_cast<size_t>(
      std::count_if(clearance_.begin(), clearance_.end(), [&](float c) { return c <= radius_; }));
}

}  // namespace behaviorlib::nav
