#include "behaviorlib/navigation/wall_columns.h"

#include <gtest/gtest.h>

#include "behaviorlib/navigation/occupancy_map.h"

namespace behaviorlib::nav {
namespace {

// A plane lidar at 1.25 m looks along +x at a wall at x 3.05; a wrong hit at
// x 1.95 (a scan placed with a poor pose, noise on a jamb) lies in between.
class WallColumnsTest : public ::testing::Test {
 protected:
  const Eigen::Vector3d origin_{0.05, 0.05, 1.25};
  const Eigen::Vector3d wall_{3.05, 0.05, 1.25};
  const Eigen::Vector3d wrong_{1.95, 0.05, 1.25};
  OccupancyMap map_{MapOptions{.resolution_m = 0.1}};
  WallColumns columns_{WallColumnSettings{}};

  void scan(const Eigen::Vector3d& hit) {
    map_.insertScan(origin_, {hit});
    columns_.afterScan(map_, {hit});
  }
  bool occupiedAt(const Eigen::Vector3d& p, double z) const {
    return map_.occupied({p.x(), p.y(), z});
  }
};

TEST_F(WallColumnsTest, AHitRaisesItsColumnAtEveryHeight) {
  scan(wall_);
  EXPECT_EQ(columns_.standing(), 1u);
  for (double z : {0.05, 0.55, 1.25, 1.75, 2.95}) EXPECT_TRUE(occupiedAt(wall_, z)) << z;
  EXPECT_FALSE(occupiedAt(wall_, 3.05)) << "above max_z_m";
}

TEST_F(WallColumnsTest, AColumnIsRaisedOnce) {
  scan(wall_);
  scan(wall_);
  EXPECT_EQ(columns_.standing(), 1u);
  // Rays through the column's lower voxels would have cleared them: none
  // was cast (one zero-length ray per voxel, once).
  EXPECT_TRUE(occupiedAt(wall_, 0.55));
}

TEST_F(WallColumnsTest, AColumnFallsOnceRaysHaveCrossedItsVoxelManyTimes) {
  scan(wrong_);
  ASSERT_TRUE(occupiedAt(wrong_, 0.55));
  // Rays through the wrong voxel to the wall: the voxel turns free after a
  // few, the column still stands (a wall's face voxel grazed by a few rays
  // must not fall) ...
  int scans = 0;
  while (map_.occupied(wrong_)) {
    scan(wall_);
    ASSERT_LT(++scans, 10);
  }
  EXPECT_TRUE(occupiedAt(wrong_, 0.55)) << "fell as soon as its voxel was not occupied";
  // ... until the voxel is certainly free.
  while (!map_.certainlyFree(wrong_)) {
    scan(wall_);
    ASSERT_LT(++scans, 30);
  }
  scan(wall_);
  for (double z : {0.05, 0.55, 1.75, 2.95}) {
    EXPECT_FALSE(occupiedAt(wrong_, z)) << "the column still stands at " << z;
  }
  EXPECT_EQ(columns_.standing(), 1u) << "only the wall's";
  EXPECT_TRUE(occupiedAt(wall_, 0.55));
  // Hit again, it rises again.
  scan(wrong_);
  EXPECT_TRUE(occupiedAt(wrong_, 0.55));
  EXPECT_EQ(columns_.standing(), 2u);
}

TEST_F(WallColumnsTest, AHitAboveThePlanningHeightsStaysAVoxel) {
  const Eigen::Vector3d lintel{2.05, 0.05, 2.25};
  map_.insertScan(origin_, {lintel});
  columns_.afterScan(map_, {lintel});
  EXPECT_TRUE(map_.occupied(lintel));
  EXPECT_FALSE(occupiedAt(lintel, 1.25)) << "the door below the lintel stays open";
  EXPECT_EQ(columns_.standing(), 0u);
}

}  // namespace
}  // namespace behaviorlib::nav
