#include "behaviorlib/navigation/ground_rejection.h"

#include <gtest/gtest.h>

#include <cmath>
#include <string>

#include "behaviorlib/navigation/occupancy_map.h"
#include "behaviorlib/navigation/wall_columns.h"
#include "formats/world/world.h"
#include "simulator/world/lidar.h"

namespace behaviorlib::nav {
namespace {

constexpr double kDeg = M_PI / 180.0;

TEST(GroundRejectionTest, LowHitsOfDescendingRaysAreTheGroundWithinTheEstimatesErrors) {
  const GroundRejection ground;  // 0.05 m, 0.2 m, 0.035 rad
  EXPECT_TRUE(ground.mayBeGround(0.05, 0.0, 3.0)) << "at max_z_m: the ground, level or not";
  EXPECT_FALSE(ground.mayBeGround(0.3, 0.0, 7.0)) << "a level ray cannot reach the floor";
  EXPECT_FALSE(ground.mayBeGround(0.3, 0.01, 7.0)) << "nor a rising one";
  // Within the attitude error of level: on the ground (the lidar 0.1 m up),
  // every hit is near the floor; only those at or below max_z_m go.
  EXPECT_FALSE(ground.mayBeGround(0.08, -0.02, 5.0));
  EXPECT_TRUE(ground.mayBeGround(0.08, -0.05, 5.0)) << "surely descending";
  // Descending, 7 m away: 0.05 + 0.2 + 7 x 0.035 = 0.495 m.
  EXPECT_TRUE(ground.mayBeGround(0.45, -0.19, 7.0));
  EXPECT_FALSE(ground.mayBeGround(0.55, -0.19, 7.0));
  // Nearer, the attitude error moves a hit less.
  EXPECT_FALSE(ground.mayBeGround(0.3, -0.19, 1.0));
}

// A plane lidar 1.3 m up in room B of the shipped building, on a vehicle that
// pitches 11 degrees nose down as it speeds up southwards. Its
// pose estimate has the altitude 0.15 m high and the pitch 1.5 degrees short
// (what the lidar SLAM's estimate was off by in flight). The floor, some
// 7 m ahead, then computes to about 0.3 m up.
class TiltedScanTest : public ::testing::Test {
 protected:
  void SetUp() override {
    auto world = world::loadWorld(std::string(BEHAVIORLIB_WORLDS_DIR) + "/rooms.yaml");
    ASSERT_TRUE(world.ok()) << world.status();
    world_ = std::move(*world);
    sim::LidarConfig config;
    config.beams = 360;
    config.channels = 1;
    config.elevation_min_rad = 0.0;
    config.elevation_max_rad = 0.0;
    config.range_max_m = 30.0;
    config.noise_stddev_m = 0.01;
    auto lidar = sim::Lidar::create(world_, config);
    ASSERT_TRUE(lidar.ok()) << lidar.status();
    lidar_.emplace(std::move(*lidar));
  }

  // Maps one scan as navigation_with_lidar's LidarMapper does, placed with
  // the estimate, rejecting the ground by `ground`; the number of wall
  // columns raised inside room B, away from its walls and its shelf.
  int columnsInsideRoomB(const GroundRejection& ground) {
    const Eigen::Vector3d body(9.0, 8.0, 1.2);
    const double yaw = -M_PI / 2;  // south
    auto attitude = [&](double pitch_rad) {
      return Eigen::Quaterniond(Eigen::AngleAxisd(yaw, Eigen::Vector3d::UnitZ()) *
                                Eigen::AngleAxisd(pitch_rad, Eigen::Vector3d::UnitY()));
    };
    const Eigen::Vector3d mount(0.0, 0.0, 0.1);
    const sim::LidarScan scan = lidar_->scan(body, attitude(11.0 * kDeg));
    const Eigen::Quaterniond estimate = attitude(9.5 * kDeg);
    const Eigen::Vector3d origin = body + Eigen::Vector3d(0, 0, 0.15) + estimate * mount;
    std::vector<Eigen::Vector3d> hits;
    for (int b = 0; b < scan.beams; ++b) {
      const double r = scan.at(0, b);
      if (!std::isfinite(r)) continue;
      const Eigen::Vector3d dir = estimate * lidar_->direction(0, b);
      const Eigen::Vector3d hit = origin + dir * (r + 0.03);
      if (!ground.mayBeGround(hit.z(), dir.z(), r)) hits.push_back(hit);
    }
    OccupancyMap map(MapOptions{.resolution_m = 0.1});
    WallColumns columns(WallColumnSettings{});
    map.insertScan(origin, hits, {});
    columns.afterScan(map, hits);
    int inside = 0;
    for (double x = 6.45; x < 11.6; x += 0.1) {
      for (double y = 0.45; y < 9.0; y += 0.1) {
        if (map.occupied({x, y, 0.55})) ++inside;
      }
    }
    walls_ = 0;
    for (double y = 7.55; y < 8.5; y += 0.1) walls_ += map.occupied({11.95, y, 0.55}) ? 1 : 0;
    return inside;
  }

  world::World world_;
  std::optional<sim::Lidar> lidar_;
  int walls_ = 0;  ///< columns of the B-C wall beside the vehicle
};

TEST_F(TiltedScanTest, TheFloorSeenTiltedRaisesNoColumnInTheRoom) {
  // Only "at or below 0.05 m" (the rule before): the floor hits are kept
  // and stand as a wall across the room.
  EXPECT_GT(columnsInsideRoomB(GroundRejection{
                .max_z_m = 0.05, .altitude_error_m = 0.0, .attitude_error_rad = 0.0}),
            10);
  EXPECT_EQ(columnsInsideRoomB(GroundRejection{}), 0);
  // The B-C wall beside the vehicle, seen by about level rays, is mapped.
  EXPECT_GE(walls_, 8);
}

}  // namespace
}  // namespace behaviorlib::nav
