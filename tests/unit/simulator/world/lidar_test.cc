#include "simulator/world/lidar.h"

#include <gtest/gtest.h>

#include <chrono>
#include <cmath>
#include <cstdio>
#include <limits>
#include <numbers>

#include "formats/world/world.h"

namespace behaviorlib::sim {
namespace {

constexpr float kInf = std::numeric_limits<float>::infinity();

/// A wall whose near face is the plane x = 5, 20 m wide, 3 m high.
world::World wallAt5m() {
  world::World world("wall");
  world.addBox(
      world::Box{"wall", {5.1, 0.0, 1.5}, {0.2, 20.0, 3.0}, 0.0, {}, world::Box::Kind::kWall});
  return world;
}

Eigen::Quaterniond yaw(double yaw_rad) {
  return Eigen::Quaterniond(Eigen::AngleAxisd(yaw_rad, Eigen::Vector3d::UnitZ()));
}

TEST(Lidar, ForwardBeamOnAWallWithinThreeSigma) {
  const world::World world = wallAt5m();
  LidarConfig config;
  config.noise_stddev_m = 0.02;
  config.seed = 42;
  absl::StatusOr<Lidar> lidar = Lidar::create(world, config);
  ASSERT_TRUE(lidar.ok()) << lidar.status();
  const int forward = lidar->beamNearestAzimuth(0.0);
  EXPECT_NEAR(lidar->azimuthRad(forward), 0.0, 1e-12);
  const int left = lidar->beamNearestAzimuth(std::numbers::pi / 2);
  const int back = lidar->beamNearestAzimuth(std::numbers::pi);
  for (int i = 0; i < 20; ++i) {
    const LidarScan scan = lidar->scan({0, 0, 1}, Eigen::Quaterniond::Identity());
    ASSERT_EQ(scan.ranges_m.size(), 360u);
    EXPECT_NEAR(scan.at(0, forward), 5.0, 3 * config.noise_stddev_m);
    EXPECT_EQ(scan.at(0, left), kInf);  // open to the left (+y) ...
    EXPECT_EQ(scan.at(0, back), kInf);  // ... and behind
  }
}

TEST(Lidar, BeamsAreInTheBodyFrameCounterClockwise) {
  const world::World world = wallAt5m();
  LidarConfig config;
  config.noise_stddev_m = 0.0;
  absl::StatusOr<Lidar> lidar = Lidar::create(world, config);
  ASSERT_TRUE(lidar.ok());
  // Turned left by 90 degrees the wall (east) is on the right: azimuth -90.
  const LidarScan scan = lidar->scan({0, 0, 1}, yaw(std::numbers::pi / 2));
  EXPECT_NEAR(scan.at(0, lidar->beamNearestAzimuth(-std::numbers::pi / 2)), 5.0, 1e-5);
  EXPECT_EQ(scan.at(0, lidar->beamNearestAzimuth(0.0)), kInf);
  // 30 degrees to the right of the wall normal: 5 / cos(30).
  const float oblique = scan.at(0, lidar->beamNearestAzimuth(-std::numbers::pi / 2 + 0.5236));
  EXPECT_NEAR(
      oblique,
      5.0 / std::cos(lidar->azimuthRad(lidar->beamNearestAzimuth(-std::numbers::pi / 2 + 0.5236)) +
                     std::numbers::pi / 2),
      1e-4);
}

TEST(Lidar, SameSeedSameScanOtherSeedOtherScan) {
  const world::World world = wallAt5m();
  LidarConfig config;
  config.noise_stddev_m = 0.05;
  config.seed = 7;
  absl::StatusOr<Lidar> a = Lidar::create(world, config);
  absl::StatusOr<Lidar> b = Lidar::create(world, config);
  config.seed = 8;
  absl::StatusOr<Lidar> c = Lidar::create(world, config);
  ASSERT_TRUE(a.ok() && b.ok() && c.ok());
  const Eigen::Vector3d position(0, 0, 1);
  const LidarScan first = a->scan(position, Eigen::Quaterniond::Identity());
  EXPECT_EQ(first.ranges_m, b->scan(position, Eigen::Quaterniond::Identity()).ranges_m);
  EXPECT_NE(first.ranges_m, c->scan(position, Eigen::Quaterniond::Identity()).ranges_m);
  // Successive scans differ; reseeding repeats them; an external generator too.
  EXPECT_NE(first.ranges_m, a->scan(position, Eigen::Quaterniond::Identity()).ranges_m);
  a->reseed(7);
  EXPECT_EQ(first.ranges_m, a->scan(position, Eigen::Quaterniond::Identity()).ranges_m);
  std::mt19937_64 rng(7);
  EXPECT_EQ(first.ranges_m, a->scan(position, Eigen::Quaterniond::Identity(), rng).ranges_m);
}

TEST(Lidar, NoiseHasTheConfiguredSpread) {
  const world::World world = wallAt5m();
  LidarConfig config;
  config.beams = 1;
  config.angle_min_rad = config.angle_max_rad = 0.0;
  config.noise_stddev_m = 0.03;
  absl::StatusOr<Lidar> lidar = Lidar::create(world, config);
  ASSERT_TRUE(lidar.ok());
  double sum = 0.0, sum2 = 0.0;
  constexpr int kScans = 4000;
  for (int i = 0; i < kScans; ++i) {
    const double r = lidar->scan({0, 0, 1}, Eigen::Quaterniond::Identity()).at(0, 0);
    sum += r;
    sum2 += r * r;
  }
  const double mean = sum / kScans;
  const double stddev = std::sqrt(sum2 / kScans - mean * mean);
  EXPECT_NEAR(mean, 5.0, 0.003);
  EXPECT_NEAR(stddev, 0.03, 0.003);
}

TEST(Lidar, RangeLimitsFollowRep117) {
  const world::World world = wallAt5m();
  LidarConfig config;
  config.beams = 1;
  config.angle_min_rad = config.angle_max_rad = 0.0;
  config.noise_stddev_m = 0.0;
  config.range_min_m = 0.5;
  config.range_max_m = 4.0;
  absl::StatusOr<Lidar> lidar = Lidar::create(world, config);
  ASSERT_TRUE(lidar.ok());
  EXPECT_EQ(lidar->scan({0, 0, 1}, Eigen::Quaterniond::Identity()).at(0, 0), kInf);  // too far
  EXPECT_FLOAT_EQ(lidar->scan({1.5, 0, 1}, Eigen::Quaterniond::Identity()).at(0, 0), 3.5f);
  EXPECT_EQ(lidar->scan({4.8, 0, 1}, Eigen::Quaterniond::Identity()).at(0, 0), -kInf);  // too close
}

TEST(Lidar, ThreeDimensionalSeesTheGroundAndTheWall) {
  const world::World world = wallAt5m();
  LidarConfig config;
  config.beams = 180;
  config.channels = 16;
  config.elevation_min_rad = -15.0 * std::numbers::pi / 180.0;
  config.elevation_max_rad = 15.0 * std::numbers::pi / 180.0;
  config.noise_stddev_m = 0.0;
  config.mount_position_m = {0.1, 0.0, 0.05};
  absl::StatusOr<Lidar> lidar = Lidar::create(world, config);
  ASSERT_TRUE(lidar.ok());
  EXPECT_NEAR(lidar->elevationRad(0), config.elevation_min_rad, 1e-12);
  EXPECT_NEAR(lidar->elevationRad(15), config.elevation_max_rad, 1e-12);
  const Eigen::Vector3d body(0, 0, 0.95);  // the lidar itself at (0.1, 0, 1.0)
  const LidarScan scan = lidar->scan(body, Eigen::Quaterniond::Identity());
  ASSERT_EQ(scan.ranges_m.size(), 180u * 16u);
  const int forward = lidar->beamNearestAzimuth(0.0);
  // Lowest channel, forward: the ground 1 m below, at 1 / sin(15 degrees).
  EXPECT_NEAR(scan.at(0, forward), 1.0 / std::sin(15.0 * std::numbers::pi / 180.0), 1e-4);
  // Highest channel, forward: the wall 4.9 m ahead, at 4.9 / cos(15 degrees)
  // (it reaches z = 2.31 < 3).
  EXPECT_NEAR(scan.at(15, forward), 4.9 / std::cos(15.0 * std::numbers::pi / 180.0), 1e-4);
  // Backwards, upwards: nothing.
  EXPECT_EQ(scan.at(15, lidar->beamNearestAzimuth(std::numbers::pi)), kInf);
}

TEST(Lidar, InvalidConfigIsRejected) {
  const world::World world = wallAt5m();
  LidarConfig config;
  config.beams = 0;
  EXPECT_FALSE(Lidar::create(world, config).ok());
  config = LidarConfig();
  config.range_max_m = config.range_min_m;
  EXPECT_FALSE(Lidar::create(world, config).ok());
}

TEST(Lidar, TimePerScan) {
  absl::StatusOr<world::World> world =
      world::loadWorld(std::string(BEHAVIORLIB_WORLDS_DIR) + "/rooms.yaml");
  ASSERT_TRUE(world.ok()) << world.status();
  const Eigen::Vector3d position =
      world->findStartPose("drone1")->position_m + Eigen::Vector3d(0, 0, 1);
  for (int channels : {1, 16}) {
    LidarConfig config;
    config.channels = channels;
    config.elevation_min_rad = channels == 1 ? 0.0 : -0.26;
    config.elevation_max_rad = channels == 1 ? 0.0 : 0.26;
    absl::StatusOr<Lidar> lidar = Lidar::create(*world, config);
    ASSERT_TRUE(lidar.ok());
    constexpr int kScans = 50;
    const auto start = std::chrono::steady_clock::now();
    for (int i = 0; i < kScans; ++i) lidar->scan(position, yaw(0.01 * i));
    const double ms =
        std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start)
            .count() /
        kScans;
    std::printf("[ timing ] lidar %d x %d beams in rooms.yaml (%zu boxes): %.3f ms per scan\n",
                config.beams, channels, world->boxes().size(), ms);
  }
}

}  // namespace
}  // namespace behaviorlib::sim
