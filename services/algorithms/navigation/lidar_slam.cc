#include "behaviorlib/navigation/lidar_slam.h"

#include <Eigen/Eigenvalues>
#include <algorithm>
#include <cmath>
#include <limits>
#include <numbers>

namespace behaviorlib::nav {
namespace {

// "Far from every occupied cell" in squared cells: larger than any squared
// distance in a grid of max_extent_m, small enough that adding a squared
// index keeps its precision in a double.
constexpr double kFar = 1e12;
constexpr double kInfinity = std::numeric_limits<double>::infinity();
// Floor of a point's likelihood in the search's score: a point on no mapped
// surface (a new wall, a person) costs log(kFloor), not minus infinity.
constexpr double kFloor = 0.05;
const double kLogFloor = std::log(kFloor);
// The points' errors are not independent (one wall, one noise draw per ray),
// so the search's log-likelihood is tempered by the number of points: a mean
// change of this many nats per point counts as one nat.
constexpr double kTemperaturePerPoint = 0.05;
// A cell whose hits' rays have a mean direction at least this long (of unit
// vectors) was seen from one side: a wall's face seen from its room, whose
// rays spread over a half-plane, gives about 0.64.
constexpr double kOneSidedRay = 0.4;
// A ray whose direction has more than this component along a surface's
// facing would hit that surface from behind (head-on is -1, grazing 0).
constexpr double kBackside = 0.3;

// Felzenszwalb and Huttenlocher's 1-D squared distance transform of f[0..n)
// (0 on occupied cells, kFar elsewhere), in place, and in arg the index of
// the parabola each value comes from; v, z and d are scratch.
void distance1d(std::vector<double>& f, int n, std::vector<int>& v, std::vector<double>& z,
                std::vector<double>& d, std::vector<int>& arg) {
  const auto at = [](auto& a, int i) -> auto& { return a[static_cast<size_t>(i)]; };
  const auto intersection = [&](int q, int p) {
    return ((at(f, q) + double(q) * q) - (at(f, p) + double(p) * p)) / (2.0 * (q - p));
  };
  int k = 0;
  at(v, 0) = 0;
  at(z, 0) = -kInfinity;
  at(z, 1) = kInfinity;
  for (int q = 1; q < n; ++q) {
    double s = intersection(q, at(v, k));
    while (s <= at(z, k)) {
      --k;
      s = intersection(q, at(v, k));
    }
    ++k;
    at(v, k) = q;
    at(z, k) = s;
    at(z, k + 1) = kInfinity;
  }
  k = 0;
  for (int q = 0; q < n; ++q) {
    while (at(z, k + 1) < q) ++k;
    const int p = at(v, k);
    at(d, q) = double(q - p) * (q - p) + at(f, p);
    at(arg, q) = p;
  }
  for (int q = 0; q < n; ++q) at(f, q) = at(d, q);
}

}  // namespace

Eigen::Vector2d Pose2::transform(const Eigen::Vector2d& p) const {
  const double c = std::cos(yaw_rad), s = std::sin(yaw_rad);
  return {x_m + c * p.x() - s * p.y(), y_m + s * p.x() + c * p.y()};
}

double wrapAngle(double rad) {
  rad = std::remainder(rad, 2.0 * std::numbers::pi);
  return rad <= -std::numbers::pi ? rad + 2.0 * std::numbers::pi : rad;
}

// ---------------------------------------------------------------------------
// OccupancyGrid2

OccupancyGrid2::OccupancyGrid2(GridConfig config) : config_(config) {}

bool OccupancyGrid2::cellOf(const Eigen::Vector2d& p, int* cx, int* cy) const {
  if (width_ == 0) return false;
  const double u = std::floor((p.x() - origin_.x()) / config_.resolution_m);
  const double v = std::floor((p.y() - origin_.y()) / config_.resolution_m);
  if (!(u >= 0 && v >= 0 && u < width_ && v < height_)) return false;
  *cx = static_cast<int>(u);
  *cy = static_cast<int>(v);
  return true;
}

void OccupancyGrid2::ensure(Eigen::Vector2d lo, Eigen::Vector2d hi) {
  const double res = config_.resolution_m;
  const double margin = 2.0;  // grow in steps, not cell by cell
  if (width_ > 0) {
    const Eigen::Vector2d cur_lo = origin_;
    const Eigen::Vector2d cur_hi = origin_ + res * Eigen::Vector2d(width_, height_);
    if (lo.x() >= cur_lo.x() && lo.y() >= cur_lo.y() && hi.x() < cur_hi.x() && hi.y() < cur_hi.y())
      return;
    lo = lo.cwiseMin(cur_lo);
    hi = hi.cwiseMax(cur_hi);
  }
  lo -= Eigen::Vector2d::Constant(margin);
  hi += Eigen::Vector2d::Constant(margin);
  Eigen::Vector2d new_lo, new_hi;
  for (int a = 0; a < 2; ++a) {
    // Never more than max_extent_m on a side; the current grid stays inside.
    double l = lo[a], h = hi[a];
    if (h - l > config_.max_extent_m) {
      if (width_ > 0) {
        const double cur_l = origin_[a];
        const double cur_h = origin_[a] + res * (a == 0 ? width_ : height_);
        l = std::max(l, cur_h - config_.max_extent_m);
        l = std::min(l, cur_l);
        h = std::min(h, l + config_.max_extent_m);
        h = std::max(h, cur_h);
      } else {
        const double mid = 0.5 * (l + h);
        l = mid - 0.5 * config_.max_extent_m;
        h = mid + 0.5 * config_.max_extent_m;
      }
    }
    new_lo[a] = l;
    new_hi[a] = h;
  }
  // Keep the lattice: the new origin is the old one minus whole cells.
  Eigen::Vector2d origin;
  if (width_ > 0) {
    for (int a = 0; a < 2; ++a)
      origin[a] = origin_[a] - res * std::ceil((origin_[a] - new_lo[a]) / res - 1e-9);
  } else {
    origin = (new_lo / res).array().floor().matrix() * res;
  }
  const int w = static_cast<int>(std::ceil((new_hi.x() - origin.x()) / res - 1e-9));
  const int h = static_cast<int>(std::ceil((new_hi.y() - origin.y()) / res - 1e-9));
  if (w == width_ && h == height_ && origin == origin_) return;
  std::vector<Cell> cells(static_cast<size_t>(w) * static_cast<size_t>(h));
  const int dx = static_cast<int>(std::lround((origin_.x() - origin.x()) / res));
  const int dy = static_cast<int>(std::lround((origin_.y() - origin.y()) / res));
  for (int y = 0; y < height_; ++y) {
    for (int x = 0; x < width_; ++x) {
      cells[index(x + dx, y + dy, w)] = cells_[index(x, y, width_)];
    }
  }
  origin_ = origin;
  width_ = w;
  height_ = h;
  cells_ = std::move(cells);
}

void OccupancyGrid2::addLogOdds(int cx, int cy, double delta) {
  Cell& cell = cells_[index(cx, cy, width_)];
  if (cell.touched == insertion_) return;  // once per scan
  cell.touched = insertion_;
  const float before = cell.log_odds;
  const float after =
      static_cast<float>(std::clamp(before + delta, config_.min_log_odds, config_.max_log_odds));
  cell.log_odds = after;
  occupied_cells_ += (after > 0.0f) - (before > 0.0f);
}

void OccupancyGrid2::traceFree(int x0, int y0, int x1, int y1, bool include_end) {
  // Bresenham from the sensor's cell to the end cell.
  const int dx = std::abs(x1 - x0), sx = x0 < x1 ? 1 : -1;
  const int dy = -std::abs(y1 - y0), sy = y0 < y1 ? 1 : -1;
  int err = dx + dy;
  int x = x0, y = y0;
  while (true) {
    const bool end = x == x1 && y == y1;
    if (end && !include_end) break;
    addLogOdds(x, y, config_.miss_log_odds);
    if (end) break;
    const int e2 = 2 * err;
    if (e2 >= dy) {
      err += dy;
      x += sx;
    }
    if (e2 <= dx) {
      err += dx;
      y += sy;
    }
  }
}

void OccupancyGrid2::insert(const Eigen::Vector2d& origin, const std::vector<Eigen::Vector2d>& hits,
                            const std::vector<Eigen::Vector2d>& free_ends,
                            const std::vector<Eigen::Vector2d>& between) {
  Eigen::Vector2d lo = origin, hi = origin;
  for (const auto* points : {&hits, &free_ends, &between}) {
    for (const auto& p : *points) {
      lo = lo.cwiseMin(p);
      hi = hi.cwiseMax(p);
    }
  }
  ensure(lo, hi);
  ++insertion_;
  if (insertion_ == 0) {  // wrapped: forget the marks
    for (auto& cell : cells_) cell.touched = 0;
    insertion_ = 1;
  }
  int ox = 0, oy = 0;
  if (!cellOf(origin, &ox, &oy)) return;
  // Hits first: a ray grazing a wall must not clear the cell another ray hit.
  for (const auto* points : {&hits, &between}) {
    for (const auto& p : *points) {
      int cx = 0, cy = 0;
      if (!cellOf(p, &cx, &cy)) continue;
      const Eigen::Vector2d ray = (p - origin).normalized();
      addLogOdds(cx, cy, config_.hit_log_odds);
      // Where in the cell the surface is: the mean of its hits (the recent
      // ones weigh more once it has many), so that matching is not limited to
      // the cell's centre.
      Cell& cell = cells_[index(cx, cy, width_)];
      if (cell.hits < kMaxHitsAveraged) ++cell.hits;
      const float weight = 1.0f / static_cast<float>(cell.hits);
      cell.hit_x += weight * (static_cast<float>(p.x()) - cell.hit_x);
      cell.hit_y += weight * (static_cast<float>(p.y()) - cell.hit_y);
      if (ray.allFinite()) {
        cell.ray_x += weight * (static_cast<float>(ray.x()) - cell.ray_x);
        cell.ray_y += weight * (static_cast<float>(ray.y()) - cell.ray_y);
      }
    }
  }
  for (const auto& p : hits) {
    int cx = 0, cy = 0;
    if (cellOf(p, &cx, &cy)) traceFree(ox, oy, cx, cy, false);
  }
  for (const auto& p : free_ends) {
    int cx = 0, cy = 0;
    if (cellOf(p, &cx, &cy)) traceFree(ox, oy, cx, cy, true);
  }
  recomputeField();
}

void OccupancyGrid2::recomputeField() {
  const size_t n = cells_.size();
  const int longest = std::max(width_, height_);
  // Each occupied cell's surface: where its hits are, and, when the hits of
  // the occupied cells around it lie along a line (a wall), that line's
  // normal, so that a point is scored by its distance to the wall and not to
  // the nearest hit (a wall seen from afar has one hit every few cells).
  surfaces_.clear();
  std::vector<int32_t> surface_of(n, -1);
  // The window grows with the field's width: a band of noisy hits needs a
  // longer stretch of wall to show its direction.
  const int r = std::clamp(
      static_cast<int>(std::lround(2.0 * config_.likelihood_sigma_m / config_.resolution_m)),
      kSurfaceRadiusCells, kMaxSurfaceRadiusCells);
  for (int y = 0; y < height_; ++y) {
    for (int x = 0; x < width_; ++x) {
      const Cell& cell = cells_[index(x, y, width_)];
      if (cell.log_odds <= 0.0f) continue;
      Surface surface;
      surface.point = {cell.hit_x, cell.hit_y};
      // Seen from one side: the rays that hit it agree in direction.
      const Eigen::Vector2d mean_ray(cell.ray_x, cell.ray_y);
      if (mean_ray.norm() > kOneSidedRay) surface.facing = -mean_ray.normalized();
      Eigen::Vector2d sum = Eigen::Vector2d::Zero();
      Eigen::Matrix2d outer = Eigen::Matrix2d::Zero();
      double count = 0.0, weight = 0.0;
      for (int j = std::max(0, y - r); j <= std::min(height_ - 1, y + r); ++j) {
        for (int i = std::max(0, x - r); i <= std::min(width_ - 1, x + r); ++i) {
          const Cell& other = cells_[index(i, j, width_)];
          if (other.log_odds <= 0.0f) continue;
          const Eigen::Vector2d q(other.hit_x, other.hit_y);
          const double w = other.hits;
          sum += w * q;
          outer += w * q * q.transpose();
          weight += w;
          count += 1.0;
        }
      }
      // A hit with no occupied cell near it (a wall seen at a grazing angle
      // from afar: one hit every few decimetres) says where the wall is
      // across it but not along it; as a point it would pull the next scan
      // along the wall. It is left out of the field until more hits come.
      if (count < 3.0) continue;
      const Eigen::Vector2d mean = sum / weight;
      const Eigen::Matrix2d cov = outer / weight - mean * mean.transpose();
      const Eigen::SelfAdjointEigenSolver<Eigen::Matrix2d> eig(cov);
      // Eigenvalues ascending: a line has one much smaller than the other.
      // The line runs through the hits' mean: a wall seen by a noisy lidar is
      // a band of occupied cells, and each of them then stands for the
      // band's middle.
      if (eig.eigenvalues()[0] < kLineRatio * eig.eigenvalues()[1]) {
        surface.normal = eig.eigenvectors().col(0);
        if (surface.normal.dot(surface.facing) < 0.0) surface.normal = -surface.normal;
        surface.point = mean;
        surface.linear = true;
      }
      surface_of[index(x, y, width_)] = static_cast<int32_t>(surfaces_.size());
      surfaces_.push_back(surface);
    }
  }
  std::vector<double> squared(n);
  for (size_t i = 0; i < n; ++i) squared[i] = surface_of[i] >= 0 ? 0.0 : kFar;
  std::vector<double> line(static_cast<size_t>(longest)), scratch(static_cast<size_t>(longest));
  std::vector<double> z(static_cast<size_t>(longest) + 1);
  std::vector<int> v(static_cast<size_t>(longest)), arg(static_cast<size_t>(longest));
  std::vector<int> nearest_row(n);
  for (int x = 0; x < width_; ++x) {  // columns: the nearest row with a surface
    for (int y = 0; y < height_; ++y) line[static_cast<size_t>(y)] = squared[index(x, y, width_)];
    distance1d(line, height_, v, z, scratch, arg);
    for (int y = 0; y < height_; ++y) {
      squared[index(x, y, width_)] = line[static_cast<size_t>(y)];
      nearest_row[index(x, y, width_)] = arg[static_cast<size_t>(y)];
    }
  }
  // Surfaces are looked up farther than the field reaches (3 sigma), so
  // that the scatter of a noisier lidar can be measured (surfaceDistance).
  const double reach_m = std::max(3.0 * config_.likelihood_sigma_m, kSurfaceReachM);
  const double cutoff_cells2 = reach_m * reach_m / (config_.resolution_m * config_.resolution_m);
  nearest_.assign(n, -1);
  for (int y = 0; y < height_; ++y) {  // rows: the nearest cell with a surface
    for (int x = 0; x < width_; ++x) line[static_cast<size_t>(x)] = squared[index(x, y, width_)];
    distance1d(line, width_, v, z, scratch, arg);
    for (int x = 0; x < width_; ++x) {
      if (line[static_cast<size_t>(x)] >= cutoff_cells2) continue;
      const int column = arg[static_cast<size_t>(x)];
      const int32_t surface =
          surface_of[index(column, nearest_row[index(column, y, width_)], width_)];
      nearest_[index(x, y, width_)] = surface;
    }
  }
  recomputeScores();
}

void OccupancyGrid2::recomputeScores() {
  score_.assign(cells_.size(), static_cast<float>(kLogFloor));
  facing_.assign(cells_.size(), Eigen::Vector2f::Zero());
  for (int y = 0; y < height_; ++y) {
    for (int x = 0; x < width_; ++x) {
      const size_t i = index(x, y, width_);
      if (nearest_[i] < 0) continue;
      facing_[i] = surfaces_[static_cast<size_t>(nearest_[i])].facing.cast<float>();
      const Eigen::Vector2d centre =
          origin_ + config_.resolution_m * Eigen::Vector2d(x + 0.5, y + 0.5);
      score_[i] = static_cast<float>(
          std::log(kFloor + (1.0 - kFloor) * likelihood(centre, nearest_[i], nullptr)));
    }
  }
}

void OccupancyGrid2::setSigma(double sigma_m) {
  config_.likelihood_sigma_m = sigma_m;
  if (!nearest_.empty()) recomputeScores();
}

std::optional<double> OccupancyGrid2::surfaceDistance(const Eigen::Vector2d& p,
                                                      bool lines_only) const {
  int cx = 0, cy = 0;
  if (!cellOf(p, &cx, &cy) || nearest_.empty()) return std::nullopt;
  const int32_t surface = nearest_[index(cx, cy, width_)];
  if (surface < 0) return std::nullopt;
  const Surface& s = surfaces_[static_cast<size_t>(surface)];
  const Eigen::Vector2d d = p - s.point;
  if (!s.linear && lines_only) return std::nullopt;
  return s.linear ? std::abs(s.normal.dot(d)) : d.norm();
}

double OccupancyGrid2::likelihood(const Eigen::Vector2d& p, int surface,
                                  Eigen::Vector2d* gradient) const {
  const Surface& s = surfaces_[static_cast<size_t>(surface)];
  Eigen::Vector2d d = p - s.point;
  if (s.linear) d = s.normal * s.normal.dot(d);  // to the line through the hits
  const double inv = 1.0 / (config_.likelihood_sigma_m * config_.likelihood_sigma_m);
  const double m = std::exp(-0.5 * d.squaredNorm() * inv);
  if (gradient) *gradient = -m * inv * d;
  return m;
}

double OccupancyGrid2::logOdds(const Eigen::Vector2d& p) const {
  int cx = 0, cy = 0;
  if (!cellOf(p, &cx, &cy)) return 0.0;
  return cells_[index(cx, cy, width_)].log_odds;
}

double OccupancyGrid2::searchScore(const Eigen::Vector2d& p) const {
  const Eigen::Vector2i c = cellCoordinates(p);
  return searchScoreAtCell(c.x(), c.y());
}

Eigen::Vector2i OccupancyGrid2::cellCoordinates(const Eigen::Vector2d& p) const {
  return {static_cast<int>(std::floor((p.x() - origin_.x()) / config_.resolution_m)),
          static_cast<int>(std::floor((p.y() - origin_.y()) / config_.resolution_m))};
}

double OccupancyGrid2::searchScoreAtCell(int cx, int cy) const {
  if (cx < 0 || cy < 0 || cx >= width_ || cy >= height_ || score_.empty()) return kLogFloor;
  return score_[index(cx, cy, width_)];
}

double OccupancyGrid2::searchScoreAtCell(int cx, int cy, const Eigen::Vector2d& ray) const {
  if (cx < 0 || cy < 0 || cx >= width_ || cy >= height_ || score_.empty()) return kLogFloor;
  // The nearest surface's facing, copied beside the score: one array read
  // more per point and candidate, not two indirections.
  const size_t i = index(cx, cy, width_);
  const Eigen::Vector2f& facing = facing_[i];
  if (ray.x() * facing.x() + ray.y() * facing.y() > kBackside) return kLogFloor;
  return score_[i];
}

double OccupancyGrid2::field(const Eigen::Vector2d& p, Eigen::Vector2d* gradient,
                             const Eigen::Vector2d* ray) const {
  if (gradient) gradient->setZero();
  int cx = 0, cy = 0;
  if (!cellOf(p, &cx, &cy) || nearest_.empty()) return 0.0;
  const int nearest = nearest_[index(cx, cy, width_)];
  if (nearest < 0) return 0.0;
  // A ray that would hit the surface from behind saw another surface.
  if (ray && ray->dot(surfaces_[static_cast<size_t>(nearest)].facing) > kBackside) return 0.0;
  return likelihood(p, nearest, gradient);
}

std::vector<Eigen::Vector2d> OccupancyGrid2::occupiedCentres() const {
  std::vector<Eigen::Vector2d> out;
  for (int y = 0; y < height_; ++y) {
    for (int x = 0; x < width_; ++x) {
      if (cells_[index(x, y, width_)].log_odds > 0.0f)
        out.push_back(origin_ + config_.resolution_m * Eigen::Vector2d(x + 0.5, y + 0.5));
    }
  }
  return out;
}

// ---------------------------------------------------------------------------
// Scans

double yawOf(const Eigen::Quaterniond& q) {
  const Eigen::Vector3d forward = q * Eigen::Vector3d::UnitX();
  return std::atan2(forward.y(), forward.x());
}

Eigen::Quaterniond tiltOf(const Eigen::Quaterniond& q) {
  const Eigen::Quaterniond heading(Eigen::AngleAxisd(yawOf(q), Eigen::Vector3d::UnitZ()));
  return (heading.conjugate() * q).normalized();
}

LevelScan levelScan(const PlanarScan& scan, const Eigen::Quaterniond& tilt,
                    const Eigen::Vector3d& mount_m, double body_z_m, const ScanConfig& config) {
  LevelScan out;
  const Eigen::Matrix3d r = tilt.toRotationMatrix();
  const Eigen::Vector3d sensor = r * mount_m;
  out.sensor = sensor.head<2>();
  out.hits.reserve(scan.ranges_m.size());
  bool have_last = false;
  Eigen::Vector2d last = Eigen::Vector2d::Zero();
  const double spacing2 = config.min_point_spacing_m * config.min_point_spacing_m;
  for (size_t i = 0; i < scan.ranges_m.size(); ++i) {
    const double range = scan.ranges_m[i];
    if (std::isnan(range) || range < 0 || range < scan.range_min_m) continue;
    const double angle = scan.angle_min_rad + static_cast<double>(i) * scan.angle_increment_rad;
    const Eigen::Vector3d direction = r * Eigen::Vector3d(std::cos(angle), std::sin(angle), 0.0);
    if (std::isinf(range) || range > scan.range_max_m || range > config.max_free_range_m) {
      const Eigen::Vector3d end = sensor + config.max_free_range_m * direction;
      out.free_ends.push_back(end.head<2>());
      continue;
    }
    const Eigen::Vector3d hit = sensor + range * direction;
    if (config.ground.mayBeGround(body_z_m + hit.z(), direction.z(), range)) continue;
    const Eigen::Vector2d p = hit.head<2>();
    if (have_last && (p - last).squaredNorm() < spacing2) continue;
    out.hits.push_back(p);
    out.hit_beams.push_back(static_cast<int>(i));
    last = p;
    have_last = true;
  }
  return out;
}

// ---------------------------------------------------------------------------
// Matching

MatchResult match(const OccupancyGrid2& grid, const std::vector<Eigen::Vector2d>& points,
                  const Pose2& predicted, const MatchConfig& config) {
  MatchResult result;
  result.pose = predicted;
  result.points = static_cast<int>(points.size());
  if (grid.empty() || result.points < config.min_points) {
    result.degenerate = true;
    return result;
  }
  const int nx = static_cast<int>(std::floor(config.window_m / config.step_m + 1e-9));
  const int nyaw = static_cast<int>(std::floor(config.window_rad / config.step_rad + 1e-9));
  const double n = static_cast<double>(points.size());
  // Score of every candidate: the log-likelihood of the points.
  struct Candidate {
    double dx, dy, dyaw, score;
  };
  std::vector<Candidate> candidates;
  candidates.reserve(static_cast<size_t>((2 * nx + 1) * (2 * nx + 1) * (2 * nyaw + 1)));
  double best = -std::numeric_limits<double>::infinity();
  size_t best_index = 0;
  // Positions step by whole cells: each point's cell is found once per
  // heading, and a candidate's score is a sum of table lookups.
  const int step_cells =
      std::max(1, static_cast<int>(std::lround(config.step_m / grid.resolution())));
  const double step_m = step_cells * grid.resolution();
  std::vector<Eigen::Vector2i> cells(points.size());
  std::vector<Eigen::Vector2d> rays(points.size());
  for (int k = -nyaw; k <= nyaw; ++k) {
    const double yaw = predicted.yaw_rad + k * config.step_rad;
    const double c = std::cos(yaw), s = std::sin(yaw);
    for (size_t i = 0; i < points.size(); ++i) {
      const Eigen::Vector2d along(c * points[i].x() - s * points[i].y(),
                                  s * points[i].x() + c * points[i].y());
      cells[i] = grid.cellCoordinates({predicted.x_m + along.x(), predicted.y_m + along.y()});
      rays[i] = along.normalized();
    }
    for (int ix = -nx; ix <= nx; ++ix) {
      for (int iy = -nx; iy <= nx; ++iy) {
        double score = 0.0;
        for (size_t i = 0; i < cells.size(); ++i) {
          score += grid.searchScoreAtCell(cells[i].x() + ix * step_cells,
                                          cells[i].y() + iy * step_cells, rays[i]);
        }
        candidates.push_back({ix * step_m, iy * step_m, k * config.step_rad, score});
        if (score > best) {
          best = score;
          best_index = candidates.size() - 1;
        }
      }
    }
  }
  // Covariance of the candidates weighted by their likelihood. The points'
  // errors are not independent (one wall, one noise draw per ray), so the
  // log-likelihood is tempered by the number of points: a mean change of
  // 0.05 nats per point is one nat.
  const double temperature = std::max(1.0, kTemperaturePerPoint * n);
  double total = 0.0;
  Eigen::Vector3d mean = Eigen::Vector3d::Zero();
  for (const auto& c : candidates) {
    const double w = std::exp((c.score - best) / temperature);
    total += w;
    mean += w * Eigen::Vector3d(c.dx, c.dy, c.dyaw);
  }
  mean /= total;
  Eigen::Matrix3d cov = Eigen::Matrix3d::Zero();
  for (const auto& c : candidates) {
    const double w = std::exp((c.score - best) / temperature);
    const Eigen::Vector3d d = Eigen::Vector3d(c.dx, c.dy, c.dyaw) - mean;
    cov += w * d * d.transpose();
  }
  cov /= total;
  cov += Eigen::Vector3d(step_m * step_m / 12.0, step_m * step_m / 12.0,
                         config.step_rad * config.step_rad / 12.0)
             .asDiagonal();
  result.covariance = cov;
  const Eigen::SelfAdjointEigenSolver<Eigen::Matrix2d> xy(cov.topLeftCorner<2, 2>());
  result.degenerate =
      xy.eigenvalues().maxCoeff() > config.degenerate_stddev_m * config.degenerate_stddev_m ||
      cov(2, 2) > config.degenerate_stddev_rad * config.degenerate_stddev_rad;

  // Gauss-Newton on the interpolated field from the best candidate,
  // minimising sum (1 - M(T p))^2, kept within one search step of it.
  const Candidate& start = candidates[best_index];
  Eigen::Vector3d xi(predicted.x_m + start.dx, predicted.y_m + start.dy,
                     predicted.yaw_rad + start.dyaw);
  const Eigen::Vector3d anchor = xi;
  const auto cost = [&](const Eigen::Vector3d& pose, Eigen::Matrix3d* h, Eigen::Vector3d* g) {
    const double c = std::cos(pose.z()), s = std::sin(pose.z());
    double sum = 0.0;
    if (h) h->setZero();
    if (g) g->setZero();
    for (const auto& p : points) {
      const Eigen::Vector2d q(pose.x() + c * p.x() - s * p.y(), pose.y() + s * p.x() + c * p.y());
      const Eigen::Vector2d ray = (q - pose.head<2>()).normalized();
      Eigen::Vector2d grad;
      const double m = grid.field(q, h ? &grad : nullptr, &ray);
      const double r = 1.0 - m;
      sum += r * r;
      if (h) {
        // dr/dxi = -grad . dq/dxi
        Eigen::Vector3d j(
            -grad.x(), -grad.y(),
            -(grad.x() * (-s * p.x() - c * p.y()) + grad.y() * (c * p.x() - s * p.y())));
        *h += j * j.transpose();
        *g += j * r;
      }
    }
    return sum;
  };
  double current = cost(xi, nullptr, nullptr);
  double lambda = 1e-3;
  for (int it = 0; it < config.iterations; ++it) {
    Eigen::Matrix3d h;
    Eigen::Vector3d g;
    cost(xi, &h, &g);
    Eigen::Matrix3d damped = h;
    damped.diagonal() *= (1.0 + lambda);
    damped.diagonal() += Eigen::Vector3d::Constant(1e-9);
    const Eigen::Vector3d delta = -damped.ldlt().solve(g);
    if (!delta.allFinite()) break;
    Eigen::Vector3d next = xi + delta;
    next.x() = std::clamp(next.x(), anchor.x() - step_m, anchor.x() + step_m);
    next.y() = std::clamp(next.y(), anchor.y() - step_m, anchor.y() + step_m);
    next.z() = std::clamp(next.z(), anchor.z() - config.step_rad, anchor.z() + config.step_rad);
    const double next_cost = cost(next, nullptr, nullptr);
    if (next_cost < current) {
      const bool small = (next - xi).head<2>().norm() < 1e-4 && std::abs(next.z() - xi.z()) < 1e-5;
      xi = next;
      current = next_cost;
      lambda = std::max(1e-6, lambda * 0.3);
      if (small) break;
    } else {
      lambda *= 10.0;
      if (lambda > 1e4) break;
    }
  }
  result.pose = {xi.x(), xi.y(), wrapAngle(xi.z())};
  result.score = 1.0 - std::sqrt(current / n);
  // Points on the map's surfaces: the rest may see space the map has not
  // (a room entered through its door) and neither help nor hurt.
  const double c = std::cos(xi.z()), s = std::sin(xi.z());
  for (const auto& p : points) {
    const Eigen::Vector2d q(xi.x() + c * p.x() - s * p.y(), xi.y() + s * p.x() + c * p.y());
    const Eigen::Vector2d ray = (q - xi.head<2>()).normalized();
    result.inliers += grid.field(q, nullptr, &ray) > 0.5;
  }
  result.matched =
      result.inliers >= std::max<double>(config.min_points, config.min_inlier_fraction * n);
  return result;
}

// ---------------------------------------------------------------------------
// LidarSlam

LidarSlam::LidarSlam(LidarSlamConfig config) : config_(config), grid_(config.grid) {}

void LidarSlam::start(const Pose2& pose) {
  grid_ = OccupancyGrid2(config_.grid);
  sigma_estimate_ = 0.0;
  start_ = pose;
  started_ = true;
  have_inserted_ = false;
  inserted_ = 0;
}

void LidarSlam::insert(const LevelScan& scan, const Pose2& pose, double stamp_s) {
  std::vector<Eigen::Vector2d> hits, ends;
  hits.reserve(scan.hits.size());
  ends.reserve(scan.free_ends.size());
  for (const auto& p : scan.hits) hits.push_back(pose.transform(p));
  for (const auto& p : scan.free_ends) ends.push_back(pose.transform(p));
  // The surface between adjacent hits, every half cell.
  std::vector<Eigen::Vector2d> between;
  const double step = 0.5 * config_.grid.resolution_m;
  for (size_t i = 1; i < scan.hits.size() && i < scan.hit_beams.size(); ++i) {
    const int beams = scan.hit_beams[i] - scan.hit_beams[i - 1];
    if (beams <= 0 || beams > config_.join_beams) continue;
    const double range =
        std::min((scan.hits[i] - scan.sensor).norm(), (scan.hits[i - 1] - scan.sensor).norm());
    const double gap = (hits[i] - hits[i - 1]).norm();
    const double limit =
        std::min(config_.join_max_m, config_.join_ratio * range * beam_spacing_rad_ * beams);
    if (gap > limit) continue;
    const int pieces = static_cast<int>(gap / step);
    for (int k = 1; k < pieces; ++k) {
      const double f = static_cast<double>(k) / pieces;
      between.push_back(hits[i - 1] + f * (hits[i] - hits[i - 1]));
    }
  }
  grid_.insert(pose.transform(scan.sensor), hits, ends, between);
  have_inserted_ = true;
  last_inserted_ = pose;
  last_inserted_s_ = stamp_s;
  ++inserted_;
}

bool LidarSlam::adaptSigma(const std::vector<Eigen::Vector2d>& points, const Pose2& pose) {
  std::vector<double> distances;
  distances.reserve(points.size());
  for (const auto& p : points) {
    // Lines only: a point's distance to the nearest hit of a band of noisy
    // hits says little of the noise.
    if (auto d = grid_.surfaceDistance(pose.transform(p), true)) distances.push_back(*d);
  }
  if (static_cast<int>(distances.size()) < config_.match.min_points) return false;
  const auto middle = distances.begin() + static_cast<std::ptrdiff_t>(distances.size() / 2);
  std::nth_element(distances.begin(), middle, distances.end());
  const double spread = 1.4826 * *middle;  // the median of |d|: 0.6745 sigma
  const double target =
      std::clamp(1.5 * spread, config_.grid.likelihood_sigma_m, config_.max_sigma_m);
  sigma_estimate_ = sigma_estimate_ <= 0.0 ? target : 0.7 * sigma_estimate_ + 0.3 * target;
  const double current = grid_.sigma();
  // A quick widening (the matches fail meanwhile), a slow narrowing.
  const double wanted = target > current ? std::max(sigma_estimate_, target) : sigma_estimate_;
  if (std::abs(wanted - current) <= 0.2 * current) return false;
  grid_.setSigma(wanted);
  return true;
}

ScanUpdate LidarSlam::addScan(const LevelScan& scan, const Pose2& predicted, double stamp_s,
                              double beam_spacing_rad) {
  beam_spacing_rad_ = beam_spacing_rad;
  ScanUpdate update;
  update.points = static_cast<int>(scan.hits.size());
  update.pose = predicted;
  if (!started_) start(predicted);
  if (!have_inserted_) {
    // The first scan makes the map, at the start pose.
    update.pose = start_;
    update.matched = true;
    update.covariance = Eigen::Vector3d(config_.min_stddev_m * config_.min_stddev_m,
                                        config_.min_stddev_m * config_.min_stddev_m,
                                        config_.min_stddev_rad * config_.min_stddev_rad)
                            .asDiagonal();
    insert(scan, start_, stamp_s);
    update.inserted = true;
    return update;
  }
  MatchResult m = match(grid_, scan.hits, predicted, config_.match);
  // A field too narrow for the scatter of the points (a noisier lidar than
  // the last scans had) scores a good match poorly: widen it and try again.
  if (adaptSigma(scan.hits, m.matched ? m.pose : predicted) && !m.matched)
    m = match(grid_, scan.hits, predicted, config_.match);
  update.matched = m.matched;
  update.degenerate = m.degenerate;
  update.score = m.score;
  update.inliers = m.inliers;
  if (!m.matched) return update;

  // Keep the prediction along what the scan cannot see.
  Eigen::Matrix3d cov = m.covariance;
  const double big = 100.0;  // m^2 and rad^2: no information
  const Eigen::SelfAdjointEigenSolver<Eigen::Matrix2d> xy(cov.topLeftCorner<2, 2>());
  const Eigen::Vector2d delta = m.pose.position() - predicted.position();
  Eigen::Vector2d kept = Eigen::Vector2d::Zero();
  Eigen::Matrix2d cov_xy = Eigen::Matrix2d::Zero();
  const double limit2 = config_.match.degenerate_stddev_m * config_.match.degenerate_stddev_m;
  const double min2 = config_.min_stddev_m * config_.min_stddev_m;
  for (int k = 0; k < 2; ++k) {
    const Eigen::Vector2d e = xy.eigenvectors().col(k);
    const double variance = xy.eigenvalues()[k];
    if (variance <= limit2) {
      kept += e * e.dot(delta);
      cov_xy += std::max(variance, min2) * e * e.transpose();
    } else {
      cov_xy += big * e * e.transpose();
    }
  }
  double yaw = predicted.yaw_rad, var_yaw = big;
  const double yaw_limit2 =
      config_.match.degenerate_stddev_rad * config_.match.degenerate_stddev_rad;
  if (cov(2, 2) <= yaw_limit2) {
    yaw = m.pose.yaw_rad;
    var_yaw = std::max(cov(2, 2), config_.min_stddev_rad * config_.min_stddev_rad);
  }
  update.pose = {predicted.x_m + kept.x(), predicted.y_m + kept.y(), wrapAngle(yaw)};
  update.covariance.setZero();
  update.covariance.topLeftCorner<2, 2>() = cov_xy;
  update.covariance(2, 2) = var_yaw;

  const double moved = (update.pose.position() - last_inserted_.position()).norm();
  const double turned = std::abs(wrapAngle(update.pose.yaw_rad - last_inserted_.yaw_rad));
  if (moved >= config_.insert_distance_m || turned >= config_.insert_angle_rad ||
      stamp_s - last_inserted_s_ >= config_.insert_interval_s) {
    insert(scan, update.pose, stamp_s);
    update.inserted = true;
  }
  return update;
}

}  // namespace behaviorlib::nav
