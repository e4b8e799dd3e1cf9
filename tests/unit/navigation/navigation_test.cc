#include <gtest/gtest.h>
#include <unistd.h>

#include <cstdio>

#include "behaviorlib/navigation/occupancy_map.h"
#include "behaviorlib/navigation/path_planner.h"
#include "unit/navigation/mapping.h"

namespace behaviorlib::nav {
namespace {

class Building : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    seedPlanner(42);
    auto world = world::loadWorld(std::string(BEHAVIORLIB_WORLDS_DIR) + "/rooms.yaml");
    ASSERT_TRUE(world.ok()) << world.status();
    world_ = new world::World(std::move(*world));
    auto lidar = sim::Lidar::create(*world_, testing::mappingLidar());
    ASSERT_TRUE(lidar.ok());
    map_ = new OccupancyMap();
    // Scan from the middle of each room and each doorway, 1.5 m up.
    for (const Eigen::Vector3d& p :
         {Eigen::Vector3d(3, 3, 1.5), Eigen::Vector3d(3, 7, 1.5), Eigen::Vector3d(9, 5, 1.5),
          Eigen::Vector3d(15, 3, 1.5), Eigen::Vector3d(15, 8, 1.5), Eigen::Vector3d(6, 5, 1.5),
          Eigen::Vector3d(12, 3, 1.5), Eigen::Vector3d(15, 5.5, 1.5)}) {
      testing::scanInto(*map_, *lidar, p);
    }
  }
  static void TearDownTestSuite() {
    delete map_;
    delete world_;
  }

  static PlanOptions buildingVolume() {
    PlanOptions o;
    o.bounds_min_m = {0.2, 0.2, 0.8};
    o.bounds_max_m = {17.8, 9.8, 2.0};
    return o;
  }

  // The path's segments, sampled every 5 cm, keep the vehicle's radius from
  // the world's real surfaces.
  static void expectCollisionFree(const PlannedPath& path, double radius) {
    for (size_t i = 1; i < path.waypoints_m.size(); ++i) {
      const Eigen::Vector3d a = path.waypoints_m[i - 1], b = path.waypoints_m[i];
      const int n = std::max(1, static_cast<int>((b - a).norm() / 0.05));
      for (int k = 0; k <= n; ++k) {
        const Eigen::Vector3d p = a + (b - a) * (static_cast<double>(k) / n);
        ASSERT_EQ(world_->collidingSurface(p, radius * 0.9), "") << "at (" << p.transpose() << ")";
      }
    }
  }

  static world::World* world_;
  static OccupancyMap* map_;
};

world::World* Building::world_ = nullptr;
OccupancyMap* Building::map_ = nullptr;

TEST_F(Building, TheMapHasTheWallsAndTheRoomsFreeSpace) {
  EXPECT_TRUE(map_->occupied({6.0, 2.0, 1.5}));   // wall between A and B
  EXPECT_FALSE(map_->occupied({3.0, 3.0, 1.5}));  // room A
  EXPECT_TRUE(map_->known({3.0, 3.0, 1.5}));
  EXPECT_FALSE(map_->known({30.0, 30.0, 1.5}));
  EXPECT_TRUE(map_->collides({5.8, 2.0, 1.5}, 0.3));
  EXPECT_FALSE(map_->collides({3.0, 3.0, 1.5}, 0.3));
  // Most of the building's free volume between 0.8 and 2.0 m is mapped.
  const double mapped = map_->freeVolumeM3({0.1, 0.1, 0.8}, {17.9, 9.9, 2.0});
  EXPECT_GT(mapped, 0.7 * 17.8 * 9.8 * 1.2);
}

TEST_F(Building, PlansFromRoomToRoomThroughTheDoors) {
  const PlanOptions options = buildingVolume();
  for (const auto& [from, to] : std::vector<std::pair<Eigen::Vector3d, Eigen::Vector3d>>{
           {{2, 2, 1.5}, {16.5, 8.5, 1.5}},  // A -> D: through B and C
           {{9, 8, 1.5}, {3, 7, 1.5}},       // B -> A (above the table)
           {{15, 2, 1.5}, {9, 2, 1.5}}}) {
    auto path = planPath(*map_, from, to, options);
    ASSERT_TRUE(path.ok()) << path.status();
    EXPECT_EQ(path->waypoints_m.front(), from);
    EXPECT_LT((path->waypoints_m.back() - to).norm(), 1e-6);
    EXPECT_GT(path->length_m, (to - from).norm() - 1e-9);
    expectCollisionFree(*path, options.vehicle_radius_m);
  }
}

// Around the pillar in room D (the straight line goes through it): the
// shortened path keeps the preferred clearance beyond the radius from the
// real pillar; with none preferred it is pulled against the pillar's corner.
TEST_F(Building, TheShortenedPathKeepsThePreferredClearanceWhereThereIsRoom) {
  PlanOptions options = buildingVolume();
  const Eigen::Vector3d from(16.5, 6.0, 1.5), to(13.5, 9.0, 1.5);
  auto kept = planPath(*map_, from, to, options);
  ASSERT_TRUE(kept.ok()) << kept.status();
  EXPECT_GE(kept->min_clearance_m, options.preferred_clearance_m - 0.05);
  // 0.9 of it from the world's real surfaces (the voxels are 0.1 m).
  expectCollisionFree(*kept,
                      (options.vehicle_radius_m + 0.9 * options.preferred_clearance_m) / 0.9);

  options.preferred_clearance_m = 0.0;
  auto hugging = planPath(*map_, from, to, options);
  ASSERT_TRUE(hugging.ok()) << hugging.status();
  EXPECT_LT(hugging->min_clearance_m, 0.1);
  expectCollisionFree(*hugging, options.vehicle_radius_m);
}

// Through the doors (1.2 m) the preferred clearance cannot be kept: the
// path goes through their middle and still arrives.
TEST_F(Building, ADoorNarrowerThanThePreferredClearanceIsPassedInItsMiddle) {
  PlanOptions options = buildingVolume();
  options.vehicle_radius_m = 0.35;
  options.preferred_clearance_m = 0.5;
  auto path = planPath(*map_, {3, 3, 1.5}, {9, 5, 1.5}, options);  // A -> B, door at y 5
  ASSERT_TRUE(path.ok()) << path.status();
  EXPECT_LT(path->min_clearance_m, 0.5);
  expectCollisionFree(*path, options.vehicle_radius_m);
  // Where the path crosses the wall (x = 6) it is within 0.1 m of the door's middle.
  for (size_t i = 1; i < path->waypoints_m.size(); ++i) {
    const Eigen::Vector3d a = path->waypoints_m[i - 1], b = path->waypoints_m[i];
    if ((a.x() - 6.0) * (b.x() - 6.0) > 0) continue;
    const double y = a.y() + (b.y() - a.y()) * (6.0 - a.x()) / (b.x() - a.x());
    EXPECT_NEAR(y, 5.0, 0.1);
  }
}

// The localization's uncertainty widens the inflation where the space
// allows: within a room the margin is kept and the path keeps it from the
// walls; through a door too narrow for it, the plan keeps the bare radius
// (the vehicle fits) and says so.
TEST_F(Building, TheUncertaintyMarginIsKeptWhereTheSpaceAllowsAndDroppedInADoor) {
  PlanOptions options = buildingVolume();
  options.vehicle_radius_m = 0.35;
  options.preferred_clearance_m = 0.0;
  options.uncertainty_margin_m = 0.3;  // 0.35 + 0.09 + 0.3 > the door's half-width of 0.6 m
  auto within_a = planPath(*map_, {2, 2, 1.5}, {4, 8.5, 1.5}, options);
  ASSERT_TRUE(within_a.ok()) << within_a.status();
  EXPECT_TRUE(within_a->margin_kept);
  EXPECT_GT(within_a->inflation_radius_m, 0.7);
  EXPECT_GE(within_a->min_clearance_m, 0.3 - 0.1) << "the margin, less a cell";
  auto through_door = planPath(*map_, {3, 3, 1.5}, {9, 5, 1.5}, options);
  ASSERT_TRUE(through_door.ok()) << through_door.status();
  EXPECT_FALSE(through_door->margin_kept);
  EXPECT_LT(through_door->inflation_radius_m, 0.5);
  expectCollisionFree(*through_door, options.vehicle_radius_m);
  // Without a margin the door is passed as before.
  options.uncertainty_margin_m = 0.0;
  auto bare = planPath(*map_, {3, 3, 1.5}, {9, 5, 1.5}, options);
  ASSERT_TRUE(bare.ok()) << bare.status();
  EXPECT_TRUE(bare->margin_kept);
}

TEST_F(Building, TheInflatedGridJoinsRoomsThroughDoorsTheVehicleFits) {
  const PlanOptions o = buildingVolume();
  const double margin = cellMarginM(map_->resolutionM());
  const InflatedGrid grid(*map_, o.bounds_min_m, o.bounds_max_m, 0.8 + margin);
  const Eigen::Vector3d a(3, 3, 1.5), d(16.5, 8.5, 1.5);
  EXPECT_TRUE(grid.connected(a, d, 0.35 + margin));    // through three doors
  EXPECT_FALSE(grid.connected(a, d, 0.7 + margin));    // the doors are 1.2 m wide
  EXPECT_FALSE(grid.connected(a, {40, 2, 1.5}, 0.1));  // outside the grid
  // The radius given is used, not the grid's own.
  EXPECT_TRUE(grid.blocked(a, 5.0));
  EXPECT_FALSE(grid.blocked(a, 0.35 + margin));
}

TEST_F(Building, RefusesGoalsOutsideTheMapOrInsideObstacles) {
  const PlanOptions options = buildingVolume();
  auto outside = planPath(*map_, {2, 2, 1.5}, {40, 2, 1.5}, options);
  EXPECT_EQ(outside.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(std::string(outside.status().message()).find("outside the planning volume"),
            std::string::npos);
  auto in_wall = planPath(*map_, {2, 2, 1.5}, {6.0, 2.0, 1.5}, options);
  EXPECT_EQ(in_wall.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(std::string(in_wall.status().message()).find("inside an obstacle"), std::string::npos);
}

// A vehicle 0.2 m from the wall between A and B (x = 6), with a radius of
// 0.35 m: refused by default; with escape_m, the path first moves straight
// away from the wall to a point clear at the radius, then goes on.
TEST_F(Building, AStartNearAWallIsRefusedOrEscapedFromWhenAllowed) {
  PlanOptions options = buildingVolume();
  options.vehicle_radius_m = 0.35;
  const Eigen::Vector3d start(5.75, 2.0, 1.5);
  const Eigen::Vector3d goal(3.0, 3.0, 1.5);
  auto clear = planPath(*map_, {3.0, 2.0, 1.5}, goal, options);
  ASSERT_TRUE(clear.ok()) << clear.status();
  EXPECT_EQ(clear->escape_length_m, 0.0);
  auto refused = planPath(*map_, start, goal, options);
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_NE(std::string(refused.status().message()).find("move it away first"), std::string::npos);

  options.escape_m = 0.7;
  auto escaped = planPath(*map_, start, goal, options);
  ASSERT_TRUE(escaped.ok()) << escaped.status();
  ASSERT_GE(escaped->waypoints_m.size(), 3u);
  EXPECT_EQ(escaped->waypoints_m.front(), start);
  const Eigen::Vector3d away = escaped->waypoints_m[1];
  EXPECT_LT(away.x(), start.x()) << "away from the wall: " << away.transpose();
  EXPECT_LE((away - start).norm(), 0.7 + 1e-9);
  EXPECT_DOUBLE_EQ(escaped->escape_length_m, (away - start).norm());
  EXPECT_LT(escaped->min_clearance_m, 0.0) << "it began nearer the wall than its radius";
  EXPECT_FALSE(map_->collides(away, 0.35)) << away.transpose();
  EXPECT_EQ(escaped->waypoints_m.back(), goal);
  // From the point it moved to, the path keeps the radius from the walls.
  PlannedPath rest = *escaped;
  rest.waypoints_m.erase(rest.waypoints_m.begin());
  expectCollisionFree(rest, 0.35);

  // Inside the wall itself there is nothing to escape from.
  auto inside = planPath(*map_, {6.0, 2.0, 1.5}, goal, options);
  EXPECT_EQ(inside.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_NE(std::string(inside.status().message()).find("is clear of it"), std::string::npos);
}

TEST(OccupancyMapAlone, AnUnreachableGoalIsReportedAfterTheTimeout) {
  // A closed box around the goal.
  OccupancyMap map;
  std::vector<Eigen::Vector3d> shell;
  for (double a = -1.0; a <= 1.0001; a += 0.05) {
    for (double b = -1.0; b <= 1.0001; b += 0.05) {
      for (const Eigen::Vector3d& p :
           {Eigen::Vector3d(-1, a, b), Eigen::Vector3d(1, a, b), Eigen::Vector3d(a, -1, b),
            Eigen::Vector3d(a, 1, b), Eigen::Vector3d(a, b, -1), Eigen::Vector3d(a, b, 1)}) {
        shell.push_back(p + Eigen::Vector3d(5, 5, 2));
      }
    }
  }
  for (int i = 0; i < 3; ++i) map.insertScan({5, 5, 2}, shell);
  PlanOptions options;
  options.bounds_min_m = {0, 0, 0.5};
  options.bounds_max_m = {10, 10, 4};
  options.timeout_s = 0.2;
  auto path = planPath(map, {1, 1, 2}, {5, 5, 2}, options);
  EXPECT_EQ(path.status().code(), absl::StatusCode::kNotFound);
  EXPECT_NE(std::string(path.status().message()).find("may be unreachable"), std::string::npos);
}

// OctoMap's own way of inserting a scan, as OccupancyMap did it before it
// batched the inner nodes: every leaf update walks back up its path.
void insertTheOctoMapWay(octomap::OcTree& tree, const Eigen::Vector3d& origin_m,
                         const std::vector<Eigen::Vector3d>& hits_m,
                         const std::vector<Eigen::Vector3d>& misses_m) {
  const auto octo = [](const Eigen::Vector3d& p) {
    return octomap::point3d(static_cast<float>(p.x()), static_cast<float>(p.y()),
                            static_cast<float>(p.z()));
  };
  const octomap::point3d origin = octo(origin_m);
  octomap::KeySet free_cells;
  octomap::KeyRay ray;
  for (const auto& p : misses_m) {
    if (tree.computeRayKeys(origin, octo(p), ray)) free_cells.insert(ray.begin(), ray.end());
  }
  for (const auto& key : free_cells) tree.updateNode(key, false, /*lazy_eval=*/false);
  octomap::Pointcloud cloud;
  for (const auto& p : hits_m) cloud.push_back(octo(p));
  tree.insertPointCloud(cloud, origin, -1.0, /*lazy_eval=*/false, /*discretize=*/true);
}

// Every node of both trees, inner ones included, in the same order with the
// same odds and the same children.
void expectSameTree(const octomap::OcTree& a, const octomap::OcTree& b) {
  ASSERT_EQ(a.size(), b.size());
  auto ia = a.begin_tree(), ib = b.begin_tree();
  size_t nodes = 0;
  for (; ia != a.end_tree() && ib != b.end_tree(); ++ia, ++ib, ++nodes) {
    ASSERT_EQ(ia.getKey(), ib.getKey()) << "node " << nodes;
    ASSERT_EQ(ia.getDepth(), ib.getDepth()) << "node " << nodes;
    ASSERT_EQ(ia.isLeaf(), ib.isLeaf()) << "node " << nodes;
    ASSERT_EQ(ia->getLogOdds(), ib->getLogOdds()) << "node " << nodes << " depth " << ia.getDepth();
  }
  EXPECT_TRUE(ia == a.end_tree() && ib == b.end_tree());
  EXPECT_EQ(nodes, a.size());
}

TEST(OccupancyMapAlone, ScansBuildTheSameTreeAsOctoMapsPerLeafUpdates) {
  auto world = world::loadWorld(std::string(BEHAVIORLIB_WORLDS_DIR) + "/rooms.yaml");
  ASSERT_TRUE(world.ok()) << world.status();
  sim::LidarConfig planar;  // the simulator's default: 2-D, 360 beams
  planar.range_max_m = 12.0;
  planar.noise_stddev_m = 0.05;
  auto lidar2d = sim::Lidar::create(*world, planar);
  auto lidar3d = sim::Lidar::create(*world, testing::mappingLidar());
  ASSERT_TRUE(lidar2d.ok() && lidar3d.ok());
  OccupancyMap map;
  octomap::OcTree reference(map.tree().getResolution());
  // A flight through three rooms and two doors, tilted now and then, scans
  // repeated where it hovers (voxels reach the clamping bounds and prune).
  for (int step = 0; step < 60; ++step) {
    const double t = step / 59.0;
    const Eigen::Vector3d position(2.0 + 13.0 * t, 3.0 + 2.5 * std::sin(6.0 * t), 1.2 + 0.3 * t);
    const Eigen::Quaterniond attitude(
        Eigen::AngleAxisd(0.1 * std::sin(step), Eigen::Vector3d::UnitX()));
    sim::Lidar& lidar = step % 3 == 0 ? *lidar3d : *lidar2d;
    std::vector<Eigen::Vector3d> hits, misses;
    testing::scanPoints(lidar, position, attitude, hits, misses);
    for (int repeat = 0; repeat < (step % 10 == 0 ? 6 : 1); ++repeat) {
      map.insertScan(position, hits, misses);
      insertTheOctoMapWay(reference, position, hits, misses);
    }
    ASSERT_NO_FATAL_FAILURE(expectSameTree(map.tree(), reference)) << "after scan " << step;
  }
  EXPECT_GT(map.occupiedLeafCount(), 1000u);
}

TEST(OccupancyMapAlone, SavesAFileOctoMapReadsBack) {
  OccupancyMap map;
  map.insertScan({0, 0, 1}, {{2, 0, 1}, {0, 2, 1}, {-2, 0, 1}});
  char name[] = "/tmp/map_XXXXXX";
  close(mkstemp(name));
  const std::string path = std::string(name) + ".bt";
  ASSERT_TRUE(map.save(path).ok());
  octomap::OcTree loaded(0.1);
  ASSERT_TRUE(loaded.readBinary(path));
  size_t occupied = 0;
  for (auto it = loaded.begin_leafs(); it != loaded.end_leafs(); ++it)
    occupied += loaded.isNodeOccupied(*it);
  EXPECT_EQ(occupied, map.occupiedLeafCount());
  EXPECT_EQ(map.save("/nonexistent-dir/map.bt").code(), absl::StatusCode::kInvalidArgument);
  std::remove(path.c_str());
  std::remove(name);
}

}  // namespace
}  // namespace behaviorlib::nav
