// LidarSlam (services/algorithms/navigation/.../lidar_slam.h) on scans the
// simulator's own lidar model casts in the shipped building, along a flight
// through its four rooms with noisy odometry and a drifting gyro.

#include "behaviorlib/navigation/lidar_slam.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <numbers>
#include <random>
#include <vector>

#include "formats/world/world.h"
#include "simulator/world/lidar.h"

namespace behaviorlib::nav {
namespace {

constexpr double kHeight = 1.2;

world::World loadWorld(const std::string& name) {
  auto world = world::loadWorld(std::string(BEHAVIORLIB_WORLDS_DIR) + "/" + name + ".yaml");
  EXPECT_TRUE(world.ok()) << world.status();
  return std::move(*world);
}

sim::LidarConfig planarLidar() {
  sim::LidarConfig c;  // the simulator's default 2-D lidar
  c.beams = 360;
  c.range_max_m = 30.0;
  c.noise_stddev_m = 0.01;
  c.mount_position_m = {0.0, 0.0, 0.1};
  c.seed = 11;
  return c;
}

struct TruePose {
  Eigen::Vector3d position;
  double yaw = 0.0;
  double roll = 0.0, pitch = 0.0;

  Eigen::Quaterniond attitude() const {
    return Eigen::Quaterniond(Eigen::AngleAxisd(yaw, Eigen::Vector3d::UnitZ()) *
                              Eigen::AngleAxisd(pitch, Eigen::Vector3d::UnitY()) *
                              Eigen::AngleAxisd(roll, Eigen::Vector3d::UnitX()));
  }
};

LevelScan scanAt(sim::Lidar& lidar, const TruePose& pose, const ScanConfig& config,
                 Eigen::Quaterniond tilt_measured) {
  const sim::LidarScan raw = lidar.scan(pose.position, pose.attitude());
  PlanarScan planar;
  planar.angle_min_rad = lidar.azimuthRad(0);
  planar.angle_increment_rad = lidar.azimuthRad(1) - lidar.azimuthRad(0);
  planar.range_min_m = lidar.config().range_min_m;
  planar.range_max_m = lidar.config().range_max_m;
  planar.ranges_m = raw.ranges_m;
  return levelScan(planar, tilt_measured, lidar.config().mount_position_m, pose.position.z(),
                   config);
}

// A flight through rooms A, B, C and D (simulator/worlds/rooms.yaml) at
// 0.6 m/s, 10 poses a second, heading along the way (turning at most
// 0.8 rad/s), rolling and pitching a few degrees.
std::vector<TruePose> flightThroughTheBuilding() {
  const std::vector<Eigen::Vector2d> waypoints = {
      {2.0, 2.0},  {3.0, 4.0},  {5.0, 5.0},  {7.0, 5.0},  {9.0, 3.5},  {11.0, 2.5},
      {13.0, 2.5}, {14.5, 3.0}, {15.0, 4.2}, {15.0, 5.8}, {14.0, 8.5}, {16.5, 8.8}};
  std::vector<TruePose> poses;
  const double dt = 0.1, speed = 0.6, max_turn = 0.8 * dt;
  TruePose pose;
  pose.position = {waypoints[0].x(), waypoints[0].y(), kHeight};
  pose.yaw = 0.0;
  double t = 0.0;
  for (size_t i = 1; i < waypoints.size(); ++i) {
    while (true) {
      const Eigen::Vector2d to = waypoints[i] - pose.position.head<2>();
      const double want = std::atan2(to.y(), to.x());
      pose.yaw = wrapAngle(pose.yaw + std::clamp(wrapAngle(want - pose.yaw), -max_turn, max_turn));
      pose.roll = 0.04 * std::sin(1.3 * t);
      pose.pitch = 0.05 * std::sin(0.9 * t + 1.0);
      poses.push_back(pose);
      t += dt;
      if (to.norm() <= speed * dt) break;
      pose.position.head<2>() += to.normalized() * speed * dt;
    }
  }
  return poses;
}

// A Kalman update of (x, y, yaw) with a measurement of the whole pose.
void fuse(const Pose2& measured, const Eigen::Matrix3d& r, Pose2* estimate, Eigen::Matrix3d* p) {
  const Eigen::Matrix3d k = *p * (*p + r).inverse();
  const Eigen::Vector3d innovation(measured.x_m - estimate->x_m, measured.y_m - estimate->y_m,
                                   wrapAngle(measured.yaw_rad - estimate->yaw_rad));
  const Eigen::Vector3d correction = k * innovation;
  *estimate = {estimate->x_m + correction.x(), estimate->y_m + correction.y(),
               wrapAngle(estimate->yaw_rad + correction.z())};
  *p = (Eigen::Matrix3d::Identity() - k) * *p;
}

// The range noise's standard deviation: the simulator's default, and 3, 6
// and 11 times it (its lidar NOISY fault at intensity 0.1, 0.25 and 0.5).
class LidarSlamFlight : public ::testing::TestWithParam<double> {};

TEST_P(LidarSlamFlight, LocalizesAndMapsThroughTheBuilding) {
  const double noise_m = GetParam();
  const world::World world = loadWorld("rooms");
  sim::LidarConfig lidar_config = planarLidar();
  lidar_config.noise_stddev_m = noise_m;
  auto lidar = sim::Lidar::create(world, lidar_config);
  ASSERT_TRUE(lidar.ok()) << lidar.status();
  const std::vector<TruePose> truth = flightThroughTheBuilding();
  ASSERT_GT(truth.size(), 350u);  // about 40 s

  LidarSlamConfig config;
  LidarSlam slam(config);
  std::mt19937_64 rng(5);
  std::normal_distribution<double> step_noise(0.0, 0.004), yaw_noise(0.0, 0.001),
      tilt_noise(0.0, 0.002);
  const double gyro_bias_rad_s = 0.004;  // 0.23 degree/s: 13 degrees a minute

  std::normal_distribution<double> imu_yaw_noise(0.0, 0.002);
  const Eigen::Matrix3d odometry_noise =
      Eigen::Vector3d(0.004 * 0.004, 0.004 * 0.004, 0.0015 * 0.0015).asDiagonal();
  Eigen::Matrix3d covariance = Eigen::Matrix3d::Identity() * 1e-6;
  Pose2 estimate{truth[0].position.x(), truth[0].position.y(), truth[0].yaw};
  Pose2 dead_reckoning = estimate;
  slam.start(estimate);
  double sum2 = 0.0, sum2_dr = 0.0, yaw2 = 0.0, worst = 0.0;
  int degenerate = 0, unmatched = 0;
  for (size_t k = 0; k < truth.size(); ++k) {
    if (k > 0) {
      // Odometry: the body-frame displacement (optical flow) and the turn
      // (gyro), with noise and the gyro's bias.
      const Eigen::Vector2d world_step = (truth[k].position - truth[k - 1].position).head<2>();
      const double c = std::cos(truth[k - 1].yaw), s = std::sin(truth[k - 1].yaw);
      const Eigen::Vector2d body(c * world_step.x() + s * world_step.y() + step_noise(rng),
                                 -s * world_step.x() + c * world_step.y() + step_noise(rng));
      const double turn =
          wrapAngle(truth[k].yaw - truth[k - 1].yaw) + gyro_bias_rad_s * 0.1 + yaw_noise(rng);
      for (Pose2* p : {&estimate, &dead_reckoning}) {
        const Eigen::Vector2d moved = Pose2{0, 0, p->yaw_rad}.transform(body);
        *p = {p->x_m + moved.x(), p->y_m + moved.y(), wrapAngle(p->yaw_rad + turn)};
      }
      covariance += odometry_noise;
    }
    const Eigen::Quaterniond tilt =
        tiltOf(truth[k].attitude()) *
        Eigen::Quaterniond(Eigen::AngleAxisd(tilt_noise(rng), Eigen::Vector3d::UnitX()));
    const LevelScan scan = scanAt(*lidar, truth[k], config.scan, tilt);
    const ScanUpdate u = slam.addScan(scan, estimate, 0.1 * static_cast<double>(k));
    degenerate += u.degenerate;
    unmatched += !u.matched;
    // What the behavior's filter does: the match and the IMU's heading
    // (an attitude reference, 0.002 rad of noise) weighed by their covariances.
    if (u.matched) fuse(u.pose, u.covariance, &estimate, &covariance);
    {
      Eigen::Matrix3d r = Eigen::Matrix3d::Identity() * 1e6;
      r(2, 2) = 0.002 * 0.002;
      fuse({estimate.x_m, estimate.y_m, truth[k].yaw + imu_yaw_noise(rng)}, r, &estimate,
           &covariance);
    }
    const double e = (estimate.position() - truth[k].position.head<2>()).norm();
    sum2 += e * e;
    worst = std::max(worst, e);
    yaw2 += std::pow(wrapAngle(estimate.yaw_rad - truth[k].yaw), 2);
    sum2_dr += (dead_reckoning.position() - truth[k].position.head<2>()).squaredNorm();
  }
  const double n = static_cast<double>(truth.size());
  const double rmse = std::sqrt(sum2 / n), rmse_dr = std::sqrt(sum2_dr / n);
  const double yaw_rmse_deg = std::sqrt(yaw2 / n) * 180.0 / std::numbers::pi;
  std::printf(
      "range noise %.2f m, %zu scans: rmse %.3f m (dead reckoning %.3f m), max %.3f m, yaw rmse "
      "%.2f deg, %d degenerate, %d unmatched, %llu inserted, %d occupied cells, sigma %.3f m\n",
      noise_m, truth.size(), rmse, rmse_dr, worst, yaw_rmse_deg, degenerate, unmatched,
      static_cast<unsigned long long>(slam.scansInserted()), slam.grid().occupiedCells(),
      slam.sigma());
  // Without the lidar the same odometry drifts far more: the test can fail.
  EXPECT_GT(rmse_dr, 3 * rmse);
  EXPECT_LT(yaw_rmse_deg, 1.0);
  // Six and eleven times the default noise (NOISY at 0.25 and 0.5): walls
  // are bands 0.2-0.4 m wide, as thick as the building's walls.
  const bool heavy = noise_m > 0.05;
  EXPECT_LT(rmse, heavy ? 0.10 : 0.05);
  EXPECT_LT(worst, heavy ? 0.25 : 0.15);
  EXPECT_EQ(unmatched, 0);
  // The field is as wide as the configured one with the simulator's noise,
  // and wider with three times it.
  if (noise_m > 0.02) {
    EXPECT_GT(slam.sigma(), 1.1 * config.grid.likelihood_sigma_m);
    return;  // the walls below are as wide as the noise
  }
  EXPECT_LT(slam.sigma(), 1.1 * config.grid.likelihood_sigma_m);

  // The map's walls are where the world's are: the distance from each
  // occupied cell's centre to the nearest surface at flight height.
  const auto occupied = slam.grid().occupiedCentres();
  ASSERT_GT(occupied.size(), 500u);
  int near = 0;
  double sum = 0.0;
  for (const auto& c : occupied) {
    const Eigen::Vector3d p(c.x(), c.y(), kHeight + 0.1);
    double lo = 0.0, hi = 0.5;
    if (world.collides(p, 1e-3)) {
      hi = 0.0;  // inside a wall: a hit placed at or behind the surface
    } else {
      for (int i = 0; i < 20; ++i) {
        const double mid = 0.5 * (lo + hi);
        (world.collides(p, mid) ? hi : lo) = mid;
      }
    }
    sum += hi;
    near += hi <= 0.1;
  }
  const double mean = sum / static_cast<double>(occupied.size());
  const double near_fraction = near / static_cast<double>(occupied.size());
  std::printf(
      "%zu occupied cells: %.3f m from the world's surfaces on average, %.1f %% within 0.1 m\n",
      occupied.size(), mean, 100.0 * near_fraction);
  EXPECT_LT(mean, 0.05);
  EXPECT_GT(near_fraction, 0.95);
}

INSTANTIATE_TEST_SUITE_P(RangeNoise, LidarSlamFlight, ::testing::Values(0.01, 0.03, 0.06, 0.11));

// A map of room A, scanned from (2, 2); the scans of the tests below are
// matched against it.
OccupancyGrid2 roomA(sim::Lidar& lidar) {
  LidarSlam slam;
  TruePose at{{2.0, 2.0, kHeight}, 0.0};
  slam.start({2.0, 2.0, 0.0});
  slam.addScan(scanAt(lidar, at, {}, Eigen::Quaterniond::Identity()), {2.0, 2.0, 0.0}, 0.0);
  return slam.grid();
}

TEST(Match, RecoversAnOffsetWithinItsWindow) {
  const world::World world = loadWorld("rooms");
  auto lidar = sim::Lidar::create(world, planarLidar());
  ASSERT_TRUE(lidar.ok());
  const OccupancyGrid2 grid = roomA(*lidar);
  const TruePose truth{{2.6, 2.4, kHeight}, 0.3};
  const LevelScan scan = scanAt(*lidar, truth, {}, Eigen::Quaterniond::Identity());
  const Pose2 predicted{2.6 + 0.17, 2.4 - 0.12, 0.3 + 0.07};
  const MatchResult m = match(grid, scan.hits, predicted, {});
  ASSERT_TRUE(m.matched) << m.score;
  EXPECT_FALSE(m.degenerate);
  EXPECT_NEAR(m.pose.x_m, 2.6, 0.02);
  EXPECT_NEAR(m.pose.y_m, 2.4, 0.02);
  EXPECT_NEAR(m.pose.yaw_rad, 0.3, 0.01);
  EXPECT_LT(std::sqrt(m.covariance(0, 0)), 0.05);
}

TEST(Match, ACorridorIsDegenerateAlongItsAxis) {
  // Two parallel walls 2 m apart and 60 m long: from the middle, a lidar of
  // 12 m range sees no end.
  OccupancyGrid2 grid;
  std::vector<Eigen::Vector2d> hits, points;
  for (double x = -30.0; x <= 30.0; x += 0.02) {
    hits.push_back({x, 1.01});  // inside cells, not on their boundary
    hits.push_back({x, -1.01});
  }
  for (int i = 0; i < 3; ++i) grid.insert({0.0, 0.0}, hits, {});
  for (double a = -std::numbers::pi; a < std::numbers::pi; a += 2 * std::numbers::pi / 360) {
    const double s = std::sin(a);
    if (std::abs(s) < 1e-3) continue;
    const double r = 1.01 / std::abs(s);
    if (r > 12.0) continue;
    points.push_back({r * std::cos(a), r * std::sin(a)});
  }
  const MatchResult m = match(grid, points, {0.1, 0.05, 0.0}, {});
  ASSERT_TRUE(m.matched);
  EXPECT_TRUE(m.degenerate);
  // Along the walls (x) the search cannot tell positions apart; across
  // them (y) it can.
  EXPECT_GT(std::sqrt(m.covariance(0, 0)), 0.08);
  EXPECT_LT(std::sqrt(m.covariance(1, 1)), 0.04);
  EXPECT_NEAR(m.pose.y_m, 0.0, 0.02);

  // LidarSlam keeps the prediction along the corridor and corrects across.
  LidarSlam slam;
  slam.start({0.0, 0.0, 0.0});
  LevelScan level;
  level.hits = hits;  // the whole corridor makes the map
  slam.addScan(level, {0.0, 0.0, 0.0}, 0.0);
  level.hits = points;
  const ScanUpdate u = slam.addScan(level, {0.1, 0.05, 0.0}, 0.1);
  EXPECT_TRUE(u.degenerate);
  EXPECT_NEAR(u.pose.x_m, 0.1, 1e-9);
  EXPECT_NEAR(u.pose.y_m, 0.0, 0.02);
  EXPECT_GT(u.covariance(0, 0), 1.0);
}

TEST(Match, AnOpenFieldIsNotMatched) {
  const world::World world = loadWorld("empty_field");
  auto lidar = sim::Lidar::create(world, planarLidar());
  ASSERT_TRUE(lidar.ok());
  LidarSlam slam;
  slam.start({0.0, 0.0, 0.0});
  const TruePose at{{0.0, 0.0, kHeight}, 0.0};
  const LevelScan scan = scanAt(*lidar, at, {}, Eigen::Quaterniond::Identity());
  EXPECT_TRUE(scan.hits.empty());
  EXPECT_FALSE(scan.free_ends.empty());
  slam.addScan(scan, {0.0, 0.0, 0.0}, 0.0);
  const ScanUpdate u = slam.addScan(scan, {0.3, 0.0, 0.0}, 0.1);
  EXPECT_FALSE(u.matched);
  EXPECT_TRUE(u.degenerate);
  EXPECT_NEAR(u.pose.x_m, 0.3, 1e-12);  // the prediction stands
}

TEST(LevelScan, DropsTheGroundAndLevelsATiltedScan) {
  PlanarScan scan;
  scan.angle_min_rad = 0.0;
  scan.angle_increment_rad = std::numbers::pi / 2;
  scan.range_min_m = 0.1;
  scan.range_max_m = 30.0;
  // Ahead, left, behind, right; the vehicle pitched 0.2 rad nose down at
  // 0.5 m: the ray ahead meets the ground at 0.6 / sin(0.2) = 3.0 m.
  scan.ranges_m = {2.9f, 4.0f, std::numeric_limits<float>::infinity(),
                   std::numeric_limits<float>::quiet_NaN()};
  const Eigen::Quaterniond tilt(Eigen::AngleAxisd(0.2, Eigen::Vector3d::UnitY()));
  ScanConfig config;
  config.ground.max_z_m = 0.05;
  LevelScan level = levelScan(scan, tilt, {0.0, 0.0, 0.1}, 0.5, config);
  ASSERT_EQ(level.hits.size(), 1u);  // the ground hit ahead is dropped, NaN skipped
  EXPECT_NEAR(level.hits[0].x(), 0.1 * std::sin(0.2), 1e-9);
  EXPECT_NEAR(level.hits[0].y(), 4.0, 1e-9);
  ASSERT_EQ(level.free_ends.size(), 1u);
  EXPECT_NEAR(level.free_ends[0].x(),
              -config.max_free_range_m * std::cos(0.2) + 0.1 * std::sin(0.2), 1e-9);

  scan.ranges_m = {3.1f, 4.0f, 1.0f, 1.0f};  // above the ground: kept
  level = levelScan(scan, tilt, {0.0, 0.0, 0.1}, 5.0, config);
  EXPECT_EQ(level.hits.size(), 4u);
}

TEST(OccupancyGrid2, TheFieldFallsWithTheDistanceToTheNearestWall) {
  GridConfig config;
  OccupancyGrid2 grid(config);
  // A wall along y at x = 1.025, a hit every 2 cm.
  std::vector<Eigen::Vector2d> wall;
  for (double y = -0.5; y <= 0.5; y += 0.02) wall.push_back({1.025, y});
  grid.insert({0.0, 0.0}, wall, {});
  ASSERT_TRUE(grid.occupied({1.02, 0.01}));
  EXPECT_FALSE(grid.occupied({0.5, 0.01}));
  EXPECT_LT(grid.logOdds({0.5, 0.01}), 0.0);  // the rays cleared it
  EXPECT_EQ(grid.logOdds({-5.0, 7.0}), 0.0);  // never seen
  const double sigma = config.likelihood_sigma_m;
  for (double along : {0.0, 0.013, 0.031}) {  // on a hit, between hits: the wall is a line
    EXPECT_NEAR(grid.field({1.025, along}), 1.0, 1e-5) << along;
    for (double d : {0.02, 0.04, 0.08}) {
      const double expected = std::exp(-d * d / (2 * sigma * sigma));
      EXPECT_NEAR(grid.field({1.025 + d, along}), expected, 1e-3) << d << " " << along;
      EXPECT_NEAR(grid.field({1.025 - d, along}), expected, 1e-3) << d << " " << along;
    }
  }
  EXPECT_LT(grid.field({1.025 + 4 * sigma, 0.0}), 1e-3);
  EXPECT_EQ(grid.field({1.025 + 0.5, 0.0}), 0.0);  // beyond the surfaces' reach
  EXPECT_NEAR(*grid.surfaceDistance({1.025 + 0.2, 0.013}), 0.2, 1e-3);
  EXPECT_FALSE(grid.surfaceDistance({1.025 + 0.5, 0.0}).has_value());
  Eigen::Vector2d gradient;
  grid.field({1.05, 0.0}, &gradient);
  EXPECT_LT(gradient.x(), 0.0);  // falls away from the wall
  EXPECT_NEAR(gradient.y(), 0.0, 1e-3);

  // A lone hit is not a surface yet: it says nothing about where along it
  // the wall runs.
  grid.insert({0.0, 0.0}, {{-3.0, 2.0}}, {});
  EXPECT_TRUE(grid.occupied({-3.0, 2.0}));
  EXPECT_EQ(grid.field({-3.0, 2.0}), 0.0);

  // Growing the grid keeps what it holds.
  const int before = grid.occupiedCells();
  grid.insert({0.0, 0.0}, {{-20.0, 15.0}}, {});
  EXPECT_TRUE(grid.occupied({1.02, 0.01}));
  EXPECT_NEAR(grid.field({1.045, 0.0}), std::exp(-0.02 * 0.02 / (2 * sigma * sigma)), 1e-3);
  EXPECT_TRUE(grid.occupied({-19.99, 15.01}));
  EXPECT_EQ(grid.occupiedCells(), before + 1);
}

TEST(OccupancyGrid2, AWallFaceSeenFromOneSideDoesNotDrawHitsFromTheOther) {
  GridConfig config;
  OccupancyGrid2 grid(config);
  // The west face of a 0.2 m thick wall, at x = 1.025, seen from the origin.
  std::vector<Eigen::Vector2d> wall;
  for (double y = -0.5; y <= 0.5; y += 0.02) wall.push_back({1.025, y});
  grid.insert({0.0, 0.0}, wall, {});
  const Eigen::Vector2d east(1.0, 0.0), west(-1.0, 0.0), north(0.0, 1.0);
  const double d = 0.04;  // a point one sigma east of the face
  const double expected = std::exp(-0.5);
  EXPECT_NEAR(grid.field({1.025 + d, 0.0}, nullptr, &east), expected, 1e-3)
      << "seen from the face's side";
  EXPECT_NEAR(grid.field({1.025 + d, 0.0}, nullptr, &north), expected, 1e-3) << "grazing";
  // A ray going west hit the wall's east face, not mapped yet: the west
  // face behind it does not draw it (with a field as wide as the wall, it
  // pulled every scan through a door by a wall's thickness).
  EXPECT_EQ(grid.field({1.025 + d, 0.0}, nullptr, &west), 0.0);
  const Eigen::Vector2i cell = grid.cellCoordinates({1.025 + d, 0.0});
  EXPECT_NEAR(grid.searchScoreAtCell(cell.x(), cell.y(), west), std::log(0.05), 1e-9)
      << "the search's floor";
  EXPECT_GT(grid.searchScoreAtCell(cell.x(), cell.y(), east), std::log(0.05));
  // Seen from both sides (a post), a surface draws hits from everywhere.
  std::vector<Eigen::Vector2d> post;
  for (double y = 2.0; y <= 2.2; y += 0.02) post.push_back({1.025, y});
  grid.insert({0.0, 2.1}, post, {});
  grid.insert({2.0, 2.1}, post, {});
  EXPECT_GT(grid.field({1.025 + 0.02, 2.1}, nullptr, &west), 0.5);
  EXPECT_GT(grid.field({1.025 - 0.02, 2.1}, nullptr, &east), 0.5);
}

TEST(OccupancyGrid2, StaysWithinItsMaximumExtent) {
  GridConfig config;
  config.max_extent_m = 20.0;
  OccupancyGrid2 grid(config);
  grid.insert({0.0, 0.0}, {{1.0, 0.0}}, {});
  grid.insert({0.0, 0.0}, {{500.0, 0.0}, {-500.0, 3.0}}, {});
  EXPECT_LE(grid.width() * grid.resolution(), 20.0 + 1e-9);
  EXPECT_LE(grid.height() * grid.resolution(), 20.0 + 1e-9);
  EXPECT_TRUE(grid.occupied({1.0, 0.0}));
  EXPECT_EQ(grid.occupiedCells(), 1);
}

}  // namespace
}  // namespace behaviorlib::nav
