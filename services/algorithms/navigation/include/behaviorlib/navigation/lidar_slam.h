#pragma once

// LidarSlam: localization and mapping in the plane of a 2-D lidar.
//
// The vehicle flies at a roughly constant height among vertical walls; its
// lidar sees one plane. Each scan is levelled with the attitude the IMU gives
// (roll and pitch removed, ground hits dropped: levelScan), matched against
// the map built so far from the pose predicted by odometry (match), and then
// inserted into that map at the corrected pose (OccupancyGrid2::insert).
//
//   LidarSlam slam(config);
//   slam.start(initial_pose);                      // the map's frame
//   ...
//   LevelScan scan = levelScan(planar, tilt, mount, body_z, config.scan);
//   ScanUpdate u = slam.addScan(scan, predicted_pose);
//   if (u.matched) fuse(u.pose, u.covariance);     // e.g. into an INS filter
//
// The map is a log-odds occupancy grid (OccupancyGrid2); scans are matched
// against its likelihood field, exp(-d^2 / 2 sigma^2) of the distance d to the
// nearest occupied cell, kept up to date after every insertion with an exact
// Euclidean distance transform (Felzenszwalb and Huttenlocher). Matching is a
// correlative search over a window around the prediction (every position
// step and heading step; the score is the scan's log-likelihood in the
// field), then Gauss-Newton on the bilinearly interpolated field from the
// best cell of the search. The search also gives the match's covariance
// (the candidates weighted by their likelihood, as in Olson's real-time
// correlative scan matching): a corridor or an open field, where the scan
// cannot tell positions apart, shows as a large variance along the
// direction it cannot see; such a match is `degenerate`, and addScan keeps
// the prediction along that direction.
//
// Units: metres and radians; frames: the map's (world ENU when started from a
// world pose) and the vehicle's level frame (x along the heading, z up).
// Deterministic; not thread-safe. Memory is bounded: the grid covers at most
// `max_extent_m` on a side; what falls outside is ignored.

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cstdint>
#include <optional>
#include <vector>

#include "behaviorlib/navigation/ground_rejection.h"

namespace behaviorlib::nav {

/// A pose in the plane.
struct Pose2 {
  double x_m = 0.0;
  double y_m = 0.0;
  double yaw_rad = 0.0;

  Eigen::Vector2d position() const { return {x_m, y_m}; }
  /// Map <- level frame.
  Eigen::Vector2d transform(const Eigen::Vector2d& p) const;
};

/// Angle wrapped to (-pi, pi].
double wrapAngle(double rad);

struct GridConfig {
  double resolution_m = 0.05;
  double hit_log_odds = 0.85;   ///< added to a cell a ray ends in (p 0.7)
  double miss_log_odds = -0.4;  ///< added to a cell a ray passes (p 0.4)
  double min_log_odds = -2.0;   ///< clamps: a cell can change its mind
  double max_log_odds = 3.5;
  double likelihood_sigma_m = 0.04;  ///< width of the matching field
  /// The grid's side at most: 100 m at 0.05 m is 4 million cells, about
  /// 100 MB with the matching field.
  double max_extent_m = 100.0;
};

/// The map: a log-odds occupancy grid that grows as scans reach new space.
class OccupancyGrid2 {
 public:
  explicit OccupancyGrid2(GridConfig config = {});

  /// Rays from `origin`: each hit's cell more occupied and the cells before
  /// it more free; each of `free_ends` (a ray that hit nothing within range)
  /// free up to and including its end. Then the likelihood field is
  /// recomputed. Map frame.
  /// `between`: points of the surfaces between adjacent hits (see
  /// LidarSlam), marked as hits but with no ray.
  void insert(const Eigen::Vector2d& origin, const std::vector<Eigen::Vector2d>& hits,
              const std::vector<Eigen::Vector2d>& free_ends,
              const std::vector<Eigen::Vector2d>& between = {});

  /// Log-odds of the cell holding `p` (0: unknown, also outside the grid).
  double logOdds(const Eigen::Vector2d& p) const;
  /// Whether the cell holding `p` is more likely occupied than not.
  bool occupied(const Eigen::Vector2d& p) const { return logOdds(p) > 0.0; }
  /// Likelihood field at `p`, 0..1: exp(-d^2 / 2 sigma^2), d the distance
  /// from `p` to the surface of the occupied cell nearest `p`'s cell (the
  /// mean of the hits that fell in it), 0 beyond 3 sigma; its gradient (per
  /// metre) when `gradient` is given. With `ray` (the unit direction the
  /// point was seen along), a surface seen only from its other side does not
  /// count (0): a thin wall's two faces are two surfaces, and a hit on the
  /// face not mapped yet must not be drawn to the one behind it.
  double field(const Eigen::Vector2d& p, Eigen::Vector2d* gradient = nullptr,
               const Eigen::Vector2d* ray = nullptr) const;
  /// The correlative search's score of a point in the cell holding `p`:
  /// log(floor + (1 - floor) field(cell centre)), precomputed.
  double searchScore(const Eigen::Vector2d& p) const;
  /// The cell holding `p` (which may be outside the grid), and the search's
  /// score of a cell (the floor's outside).
  Eigen::Vector2i cellCoordinates(const Eigen::Vector2d& p) const;
  double searchScoreAtCell(int cx, int cy) const;
  /// The same for a point seen along `ray`: the floor when the cell's
  /// surface was seen only from its other side (field()).
  double searchScoreAtCell(int cx, int cy, const Eigen::Vector2d& ray) const;

  /// Distance from `p` to the nearest surface (its line, or its point), if
  /// one is within kSurfaceReachM (or 3 sigma); with `lines_only`, only if
  /// that surface is a line.
  std::optional<double> surfaceDistance(const Eigen::Vector2d& p, bool lines_only = false) const;
  /// Changes the field's width (the search's scores are recomputed).
  void setSigma(double sigma_m);
  double sigma() const { return config_.likelihood_sigma_m; }

  bool empty() const { return width_ == 0; }
  int occupiedCells() const { return occupied_cells_; }
  double resolution() const { return config_.resolution_m; }
  /// Lowest corner of the grid and its size in cells.
  Eigen::Vector2d origin() const { return origin_; }
  int width() const { return width_; }
  int height() const { return height_; }
  /// Centres of the occupied cells (for drawing, for tests).
  std::vector<Eigen::Vector2d> occupiedCentres() const;

 private:
  bool cellOf(const Eigen::Vector2d& p, int* cx, int* cy) const;
  /// Grows the grid so that `lo`..`hi` are inside (within max_extent_m).
  void ensure(Eigen::Vector2d lo, Eigen::Vector2d hi);
  void addLogOdds(int cx, int cy, double delta);
  void traceFree(int x0, int y0, int x1, int y1, bool include_end);
  void recomputeField();
  void recomputeScores();
  double likelihood(const Eigen::Vector2d& p, int surface, Eigen::Vector2d* gradient) const;
  static size_t index(int x, int y, int width) {
    return static_cast<size_t>(y) * static_cast<size_t>(width) + static_cast<size_t>(x);
  }

  static constexpr uint16_t kMaxHitsAveraged = 20;
  static constexpr double kSurfaceReachM = 0.4;
  // A cell's surface is fitted to the hits of the occupied cells within this
  // many cells of it; it is a line when the smaller spread is below this
  // ratio of the larger.
  static constexpr int kSurfaceRadiusCells = 3;
  static constexpr int kMaxSurfaceRadiusCells = 10;
  static constexpr double kLineRatio = 0.3;
  struct Surface {
    Eigen::Vector2d point = Eigen::Vector2d::Zero();  // the mean of its hits
    Eigen::Vector2d normal = Eigen::Vector2d::UnitX();
    // Towards the side the surface was seen from (against the mean ray of
    // its hits); zero when seen from every side alike (a thin post).
    Eigen::Vector2d facing = Eigen::Vector2d::Zero();
    bool linear = false;
  };
  struct Cell {
    float log_odds = 0.0f;
    float hit_x = 0.0f, hit_y = 0.0f;  // mean of the hits in the cell (map frame)
    float ray_x = 0.0f, ray_y = 0.0f;  // mean unit direction of the rays that hit it
    uint16_t hits = 0;
    uint32_t touched = 0;  // the insertion that last changed it
  };

  GridConfig config_;
  Eigen::Vector2d origin_ = Eigen::Vector2d::Zero();
  int width_ = 0, height_ = 0;
  std::vector<Cell> cells_;
  std::vector<Surface> surfaces_;        // one per occupied cell
  std::vector<int32_t> nearest_;         // per cell: the surface of the occupied cell nearest it
                                         // within 3 sigma, or -1
  std::vector<float> score_;             // per cell: searchScore
  std::vector<Eigen::Vector2f> facing_;  // per cell: its nearest surface's facing (search)
  uint32_t insertion_ = 0;
  int occupied_cells_ = 0;
};

struct ScanConfig {
  GroundRejection ground;             ///< which hits may be the ground (dropped)
  double max_free_range_m = 12.0;     ///< rays longer than this clear space up to it only
  double min_point_spacing_m = 0.03;  ///< points closer than this to the last kept one merge
};

/// A scan in the vehicle's level frame.
struct LevelScan {
  Eigen::Vector2d sensor = Eigen::Vector2d::Zero();  ///< the lidar's position
  std::vector<Eigen::Vector2d> hits;                 ///< surfaces
  std::vector<int> hit_beams;                        ///< the beam of each hit
  std::vector<Eigen::Vector2d> free_ends;            ///< rays without a hit, cut
};

/// A planar scan as the lidar gives it: ranges from angle_min_rad, every
/// angle_increment_rad, counter-clockwise from the sensor's +x.
struct PlanarScan {
  double angle_min_rad = 0.0;
  double angle_increment_rad = 0.0;
  double range_min_m = 0.0;
  double range_max_m = 0.0;
  std::vector<float> ranges_m;
};

/// Levels a scan: `tilt` is the body's attitude without its heading (roll
/// and pitch), `mount_m` the lidar's position in the body, `body_z_m` the
/// body's height above the ground (to drop ground hits). NaN and -inf ranges
/// are skipped; +inf (nothing within range_max_m) clears space.
LevelScan levelScan(const PlanarScan& scan, const Eigen::Quaterniond& tilt,
                    const Eigen::Vector3d& mount_m, double body_z_m, const ScanConfig& config);

/// The attitude without its heading: q = Rz(yaw) * tilt.
Eigen::Quaterniond tiltOf(const Eigen::Quaterniond& q);
/// Heading of an attitude (the body's +x projected on the plane).
double yawOf(const Eigen::Quaterniond& q);

struct MatchConfig {
  double window_m = 0.25;  ///< search: +- this around the prediction
  double step_m = 0.05;
  double window_rad = 0.1;  ///< +- this around the predicted heading
  double step_rad = 0.01;
  int iterations = 10;  ///< Gauss-Newton
  int min_points = 30;  ///< fewer hits: no match (an open field)
  /// A match needs this many points on the map's surfaces (field > 0.5),
  /// and this fraction of the scan's.
  double min_inlier_fraction = 0.1;
  /// A direction whose standard deviation (from the search) exceeds this is
  /// one the scan cannot see: the match is degenerate.
  double degenerate_stddev_m = 0.08;
  double degenerate_stddev_rad = 0.04;
};

struct MatchResult {
  bool matched = false;     ///< enough points on the map's surfaces
  bool degenerate = false;  ///< a direction the scan cannot tell apart
  Pose2 pose;               ///< the match (the prediction if none)
  Eigen::Matrix3d covariance = Eigen::Matrix3d::Identity();  ///< x, y, yaw
  double score = 0.0;  ///< 1 - the RMS of (1 - field) over the points
  int points = 0;
  int inliers = 0;  ///< points on the map's surfaces (field > 0.5)
};

/// Matches `points` (level frame) against `grid` around `predicted`.
MatchResult match(const OccupancyGrid2& grid, const std::vector<Eigen::Vector2d>& points,
                  const Pose2& predicted, const MatchConfig& config);

struct LidarSlamConfig {
  GridConfig grid;
  ScanConfig scan;
  MatchConfig match;
  /// Insert a scan into the map when the vehicle moved this much or turned
  /// this much since the last one inserted, or after `insert_interval_s`.
  double insert_distance_m = 0.1;
  double insert_angle_rad = 0.05;
  double insert_interval_s = 1.0;
  /// Hits of beams at most `join_beams` apart are joined by a segment in the
  /// map when they are closer than `join_ratio` times the spacing of beams at
  /// their range (and than `join_max_m`): a wall seen from afar is then a
  /// line of cells, not a hit every few cells, and a point of the next scan
  /// is scored by its distance to that line. Beams striking a wall at a
  /// grazing angle, or an edge in front of a farther wall, are not joined.
  int join_beams = 4;
  double join_ratio = 3.0;
  double join_max_m = 0.5;
  /// Smallest standard deviations the match reports (the grid's resolution
  /// limits what the search can resolve).
  double min_stddev_m = 0.02;
  double min_stddev_rad = 0.005;
  /// The field widens with the scatter of the matched points about the
  /// map's surfaces (a noisier lidar, a rougher map): sigma follows 1.5
  /// times their robust standard deviation, between grid.likelihood_sigma_m
  /// and this.
  double max_sigma_m = 0.3;
};

struct ScanUpdate {
  bool matched = false;
  bool degenerate = false;
  bool inserted = false;
  /// The corrected pose: the match along the directions it constrains, the
  /// prediction along those it does not.
  Pose2 pose;
  Eigen::Matrix3d covariance = Eigen::Matrix3d::Identity();
  double score = 0.0;
  int points = 0;
  int inliers = 0;
};

class LidarSlam {
 public:
  explicit LidarSlam(LidarSlamConfig config = {});

  /// Forgets the map; the next scan starts it at `pose`.
  void start(const Pose2& pose);
  /// One scan, stamped `stamp_s`, with the pose predicted for that stamp;
  /// `beam_spacing_rad` is the angle between its beams.
  ScanUpdate addScan(const LevelScan& scan, const Pose2& predicted, double stamp_s,
                     double beam_spacing_rad = 2.0 * 3.141592653589793 / 360.0);

  const OccupancyGrid2& grid() const { return grid_; }
  const LidarSlamConfig& config() const { return config_; }
  uint64_t scansInserted() const { return inserted_; }
  /// The field's width now (see max_sigma_m).
  double sigma() const { return grid_.sigma(); }

 private:
  void insert(const LevelScan& scan, const Pose2& pose, double stamp_s);
  /// Adapts the field's width to the scatter of `points` at `pose`; true
  /// when it changed.
  bool adaptSigma(const std::vector<Eigen::Vector2d>& points, const Pose2& pose);

  LidarSlamConfig config_;
  double beam_spacing_rad_ = 0.0;  // of the scans, set by addScan
  OccupancyGrid2 grid_;
  Pose2 start_;
  bool started_ = false;
  bool have_inserted_ = false;
  Pose2 last_inserted_;
  double last_inserted_s_ = 0.0;
  uint64_t inserted_ = 0;
  double sigma_estimate_ = 0.0;
};

}  // namespace behaviorlib::nav
