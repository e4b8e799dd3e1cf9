#include "behaviorlib/navigation/frontiers.h"

#include <gtest/gtest.h>

#include <cmath>
#include <numbers>

#include "unit/navigation/mapping.h"

namespace behaviorlib::nav {
namespace {

// A disc of free space of `radius` around `origin` (a scan that hit
// nothing), in the plane z = origin.z().
OccupancyMap freeDisc(const Eigen::Vector3d& origin, double radius) {
  OccupancyMap map;
  std::vector<Eigen::Vector3d> misses;
  for (int i = 0; i < 720; ++i) {
    const double a = 2 * std::numbers::pi * i / 720;
    misses.push_back(origin + radius * Eigen::Vector3d(std::cos(a), std::sin(a), 0));
  }
  map.insertScan(origin, {}, misses);
  return map;
}

SliceOptions around(const Eigen::Vector3d& c, double half) {
  return {.min_m = c.head<2>() - Eigen::Vector2d::Constant(half),
          .max_m = c.head<2>() + Eigen::Vector2d::Constant(half),
          .z_min_m = c.z() - 0.1,
          .z_max_m = c.z() + 0.1};
}

TEST(MapSliceTest, AnEmptyMapIsUnknownWithoutFrontiers) {
  OccupancyMap map;
  const MapSlice slice(map, around({0, 0, 1.5}, 2.0));
  EXPECT_EQ(slice.width(), 40);
  EXPECT_EQ(slice.census().unknown, 1600u);
  EXPECT_EQ(slice.census().knownFraction(), 0.0);
  EXPECT_TRUE(slice.frontiers(1).empty());
}

TEST(MapSliceTest, TheFreeDiscsRimIsOneFrontierAndTheAreasEdgeIsNone) {
  const Eigen::Vector3d origin(1.0, -2.0, 1.5);
  const OccupancyMap map = freeDisc(origin, 4.0);
  // Inside the disc: all known, nothing to explore.
  const MapSlice inner(map, around(origin, 2.0));
  EXPECT_EQ(inner.census().knownFraction(), 1.0);
  EXPECT_TRUE(inner.frontiers(1).empty());
  // Around it: its rim, about 2 pi 4 m long, one cluster centred on the disc.
  const MapSlice outer(map, around(origin, 6.0));
  const auto frontiers = outer.frontiers(3);
  ASSERT_EQ(frontiers.size(), 1u);
  EXPECT_GT(frontiers[0].cells_m.size(), 150u);
  EXPECT_LT((frontiers[0].centroid_m - origin.head<2>()).norm(), 0.2);
  for (const Eigen::Vector2d& c : frontiers[0].cells_m) {
    EXPECT_NEAR((c - origin.head<2>()).norm(), 4.0, 0.3) << c.transpose();
  }
  const double disc = std::numbers::pi * 16.0 / 144.0;  // of the 12 m square
  EXPECT_NEAR(outer.census().knownFraction(), disc, 0.03);
  // Another slice height sees nothing of the disc.
  SliceOptions high = around(origin, 6.0);
  high.z_min_m = 2.0;
  high.z_max_m = 2.2;
  EXPECT_EQ(MapSlice(map, high).census().knownFraction(), 0.0);
}

TEST(MapSliceTest, AClusterSmallerThanTheMinimumIsNoise) {
  OccupancyMap map = freeDisc({0, 0, 1.5}, 0.25);  // a few cells
  const MapSlice slice(map, around({0, 0, 1.5}, 2.0));
  ASSERT_FALSE(slice.frontiers(1).empty());
  EXPECT_TRUE(slice.frontiers(1000).empty());
}

TEST(MapSliceTest, TheAreaIsClippedToTheCellBudget) {
  OccupancyMap map;
  const MapSlice slice(map, around({0, 0, 1.5}, 500.0), 10'000);
  EXPECT_LE(static_cast<size_t>(slice.width()) * slice.height(), 10'000u);
}

class BuildingSlices : public ::testing::Test {
 protected:
  void SetUp() override {
    auto world = world::loadWorld(std::string(BEHAVIORLIB_WORLDS_DIR) + "/rooms.yaml");
    ASSERT_TRUE(world.ok()) << world.status();
    world_ = std::make_unique<world::World>(std::move(*world));
    // A plane lidar, as on the vehicle: one level channel.
    sim::LidarConfig plane = testing::mappingLidar();
    plane.channels = 1;
    plane.elevation_min_rad = plane.elevation_max_rad = 0.0;
    auto lidar = sim::Lidar::create(*world_, plane);
    ASSERT_TRUE(lidar.ok());
    lidar_ = std::make_unique<sim::Lidar>(std::move(*lidar));
  }
  // The lidar's plane (scans at 1.5 m).
  static SliceOptions building() {
    return {.min_m = {0.1, 0.1}, .max_m = {17.9, 9.9}, .z_min_m = 1.4, .z_max_m = 1.6};
  }
  std::unique_ptr<world::World> world_;
  std::unique_ptr<sim::Lidar> lidar_;
};

TEST_F(BuildingSlices, FromRoomAAloneTheFrontiersLieBeyondItsDoors) {
  OccupancyMap map;
  testing::scanInto(map, *lidar_, {3, 3, 1.5});
  const MapSlice slice(map, building());
  const double known = slice.census().knownFraction();
  EXPECT_GT(known, 0.25);
  EXPECT_LT(known, 0.6);
  // Room A (x < 5.9) is known: no frontier in it (of 5 cells or more: a
  // corner pocket far from the sensor can stay unknown); room B, seen
  // through the door, has some.
  const auto frontiers = slice.frontiers(5);
  ASSERT_FALSE(frontiers.empty());
  bool in_b = false;
  for (const Frontier& f : frontiers) {
    for (const Eigen::Vector2d& c : f.cells_m) {
      EXPECT_GT(c.x(), 5.9) << "a frontier in room A at " << c.transpose();
      in_b = in_b || (c.x() > 6.1 && c.x() < 11.9);
    }
  }
  EXPECT_TRUE(in_b);
}

TEST_F(BuildingSlices, ScansInEveryRoomLeaveTheBuildingKnown) {
  OccupancyMap map;
  for (const Eigen::Vector3d& p :
       {Eigen::Vector3d(3, 3, 1.5), Eigen::Vector3d(3, 7, 1.5), Eigen::Vector3d(9, 5, 1.5),
        Eigen::Vector3d(15, 3, 1.5), Eigen::Vector3d(15, 8, 1.5), Eigen::Vector3d(6, 5, 1.5),
        Eigen::Vector3d(12, 3, 1.5), Eigen::Vector3d(15, 5.5, 1.5)}) {
    testing::scanInto(map, *lidar_, p);
  }
  const MapSlice slice(map, building());
  EXPECT_GT(slice.census().knownFraction(), 0.97);
  size_t cells = 0;
  for (const Frontier& f : slice.frontiers(5)) cells += f.cells_m.size();
  std::printf("known %.3f, %zu frontier cells in clusters of 5 or more\n",
              slice.census().knownFraction(), cells);
  EXPECT_EQ(cells, 0u);
}

}  // namespace
}  // namespace behaviorlib::nav
