// The mapped fraction the room exploration application reports: counted on
// the building's free cells at the lidar's height, growing as rooms are
// scanned, and blind to what is outside the building.

#include "simulator/tools/map_coverage.h"

#include <gtest/gtest.h>

#include "unit/navigation/mapping.h"

namespace behaviorlib::nav {
namespace {

class MapCoverageTest : public ::testing::Test {
 protected:
  void SetUp() override {
    auto world = world::loadWorld(std::string(BEHAVIORLIB_WORLDS_DIR) + "/rooms.yaml");
    ASSERT_TRUE(world.ok()) << world.status();
    world_ = std::make_unique<world::World>(std::move(*world));
    auto lidar = sim::Lidar::create(*world_, testing::mappingLidar());
    ASSERT_TRUE(lidar.ok());
    lidar_ = std::make_unique<sim::Lidar>(std::move(*lidar));
  }

  CoverageOptions options() const {
    CoverageOptions o;
    o.height_m = 1.5;
    return o;
  }

  std::unique_ptr<world::World> world_;
  std::unique_ptr<sim::Lidar> lidar_;
  OccupancyMap map_;
};

TEST_F(MapCoverageTest, TheBuildingIsTheBoxAroundItsWalls) {
  Eigen::Vector2d lo, hi;
  buildingExtent(*world_, &lo, &hi);
  // rooms.yaml: outer walls from (0, 0) to (18, 10), 0.2 m thick.
  EXPECT_NEAR(lo.x(), -0.1, 1e-9);
  EXPECT_NEAR(lo.y(), -0.1, 1e-9);
  EXPECT_NEAR(hi.x(), 18.1, 1e-9);
  EXPECT_NEAR(hi.y(), 10.1, 1e-9);

  world::World open_field("field");
  buildingExtent(open_field, &lo, &hi);
  EXPECT_EQ(lo, Eigen::Vector2d::Zero());
  EXPECT_EQ(hi, Eigen::Vector2d::Zero());
  EXPECT_EQ(measureCoverage(open_field, map_.tree()).free_cells, 0u);
}

TEST_F(MapCoverageTest, AnEmptyMapCoversNothingAndFreeSpaceExcludesWallsAndFurniture) {
  const MapCoverage c = measureCoverage(*world_, map_.tree(), options());
  EXPECT_EQ(c.known_free_cells, 0u);
  EXPECT_EQ(c.mappedFraction(), 0.0);
  // 18.2 x 10.2 m of cells less walls (about 0.2 m x 66 m) and the shelf
  // and pillar (the table and the crate are below 1.5 m).
  const double building = 18.2 * 10.2;
  EXPECT_LT(c.freeAreaM2(), building - 10.0);
  EXPECT_GT(c.freeAreaM2(), building - 20.0);
}

TEST_F(MapCoverageTest, TheFractionGrowsRoomByRoomAndAllRoomsCoverMostOfIt) {
  testing::scanInto(map_, *lidar_, {3, 3, 1.5});  // room A only
  const double one_room = measureCoverage(*world_, map_.tree(), options()).mappedFraction();
  // Room A is a third of the building; its doors let the lidar into B.
  EXPECT_GT(one_room, 0.25);
  EXPECT_LT(one_room, 0.6);

  for (const Eigen::Vector3d& p : {Eigen::Vector3d(9, 5, 1.5), Eigen::Vector3d(15, 3, 1.5),
                                   Eigen::Vector3d(15, 8.5, 1.5), Eigen::Vector3d(3, 7, 1.5)}) {
    testing::scanInto(map_, *lidar_, p);
  }
  const MapCoverage all = measureCoverage(*world_, map_.tree(), options());
  EXPECT_GT(all.mappedFraction(), 0.9);
  EXPECT_LE(all.mappedFraction(), 1.0);
  // The world's free cells are not where the map put walls.
  EXPECT_LT(all.occupied_cells, all.free_cells / 50);
}

TEST_F(MapCoverageTest, ScansOutsideTheBandDoNotCount) {
  testing::scanInto(map_, *lidar_, {3, 3, 1.5});
  CoverageOptions high = options();
  high.height_m = 2.8;  // the band 2.5..3.1 m: the 3-D lidar at 1.5 m reaches up to ~3 m near walls
  high.band_m = 0.05;
  EXPECT_LT(measureCoverage(*world_, map_.tree(), high).mappedFraction(),
            measureCoverage(*world_, map_.tree(), options()).mappedFraction());
}

TEST_F(MapCoverageTest, TheWallErrorIsSmallForScannedWallsAndGrowsWithAStrayVoxel) {
  EXPECT_EQ(measureCoverage(*world_, map_.tree(), options()).occupied_voxels, 0u);
  testing::scanInto(map_, *lidar_, {3, 3, 1.5});
  const MapCoverage scanned = measureCoverage(*world_, map_.tree(), options());
  ASSERT_GT(scanned.occupied_voxels, 100u);
  std::printf("wall error: %zu voxels, mean %.3f m, max %.3f m\n", scanned.occupied_voxels,
              scanned.wall_error_mean_m, scanned.wall_error_max_m);
  EXPECT_LT(scanned.wall_error_mean_m, 0.05);
  // A wall across room A where nothing is: the mean grows, and the maximum
  // is its farthest voxel's distance to any surface (around (3, 4, 1.5): the
  // table's top, 2.7 m away; the west wall's face, 2.9 m).
  std::vector<Eigen::Vector3d> stray;
  for (double y = 2.0; y <= 4.0; y += 0.1) stray.emplace_back(3.0, y, 1.5);
  map_.insertScan({1.0, 3.0, 1.5}, stray);
  const MapCoverage smeared = measureCoverage(*world_, map_.tree(), options());
  EXPECT_GT(smeared.wall_error_mean_m, scanned.wall_error_mean_m);
  EXPECT_GT(smeared.wall_error_max_m, 2.5);
  EXPECT_LT(smeared.wall_error_max_m, 3.0);
}

}  // namespace
}  // namespace behaviorlib::nav
