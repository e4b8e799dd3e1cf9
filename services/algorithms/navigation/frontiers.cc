#include "behaviorlib/navigation/frontiers.h"

#include <algorithm>
#include <cmath>

namespace behaviorlib::nav {

double SliceCensus::knownFraction() const {
  const size_t all = free + occupied + unknown;
  return all == 0 ? 0.0 : static_cast<double>(free + occupied) / static_cast<double>(all);
}

MapSlice::MapSlice(const OccupancyMap& map, const SliceOptions& options, size_t max_cells)
    : origin_(options.min_m), resolution_(map.resolutionM()) {
  const Eigen::Vector2d extent = (options.max_m - options.min_m).cwiseMax(0.0);
  width_ = static_cast<int>(std::ceil(extent.x() / resolution_));
  height_ = static_cast<int>(std::ceil(extent.y() / resolution_));
  if (width_ <= 0 || height_ <= 0) {
    width_ = height_ = 0;
    return;
  }
  // Clip the area (from its lowest corner) to the cell budget.
  while (static_cast<size_t>(width_) * static_cast<size_t>(height_) > max_cells) {
    if (width_ >= height_) {
      width_ /= 2;
    } else {
      height_ /= 2;
    }
  }
  cells_.assign(static_cast<size_t>(width_) * height_, Cell::kUnknown);
  const octomap::OcTree& tree = map.tree();
  // The voxel centres within the slice.
  std::vector<double> heights;
  const double first = (std::floor(options.z_min_m / resolution_) + 0.5) * resolution_;
  for (double z = first; z <= options.z_max_m + 1e-9; z += resolution_) {
    if (z >= options.z_min_m - 1e-9) heights.push_back(z);
  }
  if (heights.empty()) heights.push_back(0.5 * (options.z_min_m + options.z_max_m));
  for (int iy = 0; iy < height_; ++iy) {
    for (int ix = 0; ix < width_; ++ix) {
      const Eigen::Vector2d c = centre(ix, iy);
      Cell cell = Cell::kUnknown;
      for (double z : heights) {
        const octomap::OcTreeNode* node = tree.search(c.x(), c.y(), z);
        if (node == nullptr) continue;
        if (tree.isNodeOccupied(node)) {
          cell = Cell::kOccupied;
          break;
        }
        cell = Cell::kFree;
      }
      cells_[static_cast<size_t>(iy) * width_ + ix] = cell;
    }
  }
  // Gaps between rays: far from the sensor, adjacent beams pass more than a
  // cell apart, and rays grazing a wall miss the cells along it, leaving
  // single unknown cells inside seen space. An unknown cell at least 5/8 of
  // whose neighbours in the area are known, one of them free, is such a gap
  // (at the straight edge of an unknown region, 3 of 8 are known).
  std::vector<size_t> gaps;
  for (int iy = 0; iy < height_; ++iy) {
    for (int ix = 0; ix < width_; ++ix) {
      if (at(ix, iy) != Cell::kUnknown) continue;
      int inside = 0, known = 0, free = 0;
      for (int dy = -1; dy <= 1; ++dy) {
        for (int dx = -1; dx <= 1; ++dx) {
          const int x = ix + dx, y = iy + dy;
          if ((dx == 0 && dy == 0) || x < 0 || y < 0 || x >= width_ || y >= height_) continue;
          ++inside;
          known += at(x, y) != Cell::kUnknown;
          free += at(x, y) == Cell::kFree;
        }
      }
      if (free > 0 && 8 * known >= 5 * inside)
        gaps.push_back(static_cast<size_t>(iy) * width_ + ix);
    }
  }
  for (size_t i : gaps) cells_[i] = Cell::kFree;
}

Eigen::Vector2d MapSlice::centre(int ix, int iy) const {
  return origin_ + Eigen::Vector2d(ix + 0.5, iy + 0.5) * resolution_;
}

bool MapSlice::cellOf(const Eigen::Vector2d& p, int* ix, int* iy) const {
  const double fx = std::floor((p.x() - origin_.x()) / resolution_);
  const double fy = std::floor((p.y() - origin_.y()) / resolution_);
  if (!(fx >= 0 && fx < width_ && fy >= 0 && fy < height_)) return false;
  *ix = static_cast<int>(fx);
  *iy = static_cast<int>(fy);
  return true;
}

std::vector<Frontier> MapSlice::frontiers(size_t min_cells) const {
  const auto inside = [&](int x, int y) { return x >= 0 && y >= 0 && x < width_ && y < height_; };
  const auto is_frontier = [&](int x, int y) {
    if (at(x, y) != Cell::kFree) return false;
    constexpr int kDx[4] = {1, -1, 0, 0}, kDy[4] = {0, 0, 1, -1};
    for (int k = 0; k < 4; ++k) {
      const int nx = x + kDx[k], ny = y + kDy[k];
      if (inside(nx, ny) && at(nx, ny) == Cell::kUnknown) return true;
    }
    return false;
  };
  std::vector<uint8_t> seen(cells_.size(), 0);
  std::vector<Frontier> out;
  std::vector<std::pair<int, int>> stack;
  for (int y0 = 0; y0 < height_; ++y0) {
    for (int x0 = 0; x0 < width_; ++x0) {
      const size_t i0 = static_cast<size_t>(y0) * width_ + x0;
      if (seen[i0] || !is_frontier(x0, y0)) continue;
      Frontier f;
      seen[i0] = 1;
      stack.assign(1, {x0, y0});
      while (!stack.empty()) {
        const auto [x, y] = stack.back();
        stack.pop_back();
        f.cells_m.push_back(centre(x, y));
        for (int dy = -1; dy <= 1; ++dy) {
          for (int dx = -1; dx <= 1; ++dx) {
            const int nx = x + dx, ny = y + dy;
            if (!inside(nx, ny)) continue;
            const size_t n = static_cast<size_t>(ny) * width_ + nx;
            if (seen[n] || !is_frontier(nx, ny)) continue;
            seen[n] = 1;
            stack.emplace_back(nx, ny);
          }
        }
      }
      if (f.cells_m.size() < min_cells) continue;
      Eigen::Vector2d sum = Eigen::Vector2d::Zero();
      for (const Eigen::Vector2d& c : f.cells_m) sum += c;
      f.centroid_m = sum / static_cast<double>(f.cells_m.size());
      out.push_back(std::move(f));
    }
  }
  std::stable_sort(out.begin(), out.end(), [](const Frontier& a, const Frontier& b) {
    return a.cells_m.size() > b.cells_m.size();
  });
  return out;
}

SliceCensus MapSlice::census() const {
  SliceCensus c;
  for (Cell cell : cells_) {
    switch (cell) {
      case Cell::kFree:
        ++c.free;
        break;
      case Cell::kOccupied:
        ++c.occupied;
        break;
      case Cell::kUnknown:
        ++c.unknown;
        break;
    }
  }
  return c;
}

}  // namespace behaviorlib::nav
