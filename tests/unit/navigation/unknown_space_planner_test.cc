// planThroughUnknown (NAVIGATE_TO's planner) on maps made from simulated
// lidar scans of the shipped building: from room A alone it plans into room
// D through space the map has not seen; with the building known, its path
// goes through the doors, near the shortest, clear of the true walls; a
// closed door makes the goal unreachable; bad requests are refused.

#include "behaviorlib/navigation/unknown_space_planner.h"

#include <gtest/gtest.h>

#include <memory>
#include <sstream>
#include <string>

#include "support/rooms_world.h"
#include "unit/navigation/mapping.h"

namespace behaviorlib::nav {
namespace {

constexpr double kPlane = 1.5;     // the lidar's height
constexpr double kAltitude = 1.4;  // the path's
constexpr double kRadius = 0.35;

UnknownSpacePlanOptions building() {
  UnknownSpacePlanOptions o;
  o.vehicle_radius_m = kRadius;
  o.bounds_min_m = {0.1, 0.1, 0.5};
  o.bounds_max_m = {17.9, 9.9, 1.6};
  o.altitude_m = kAltitude;
  o.slice_z_min_m = kPlane - 0.15;
  o.slice_z_max_m = kPlane + 0.15;
  return o;
}

std::string pathText(const UnknownSpacePlan& plan) {
  std::ostringstream out;
  for (const auto& p : plan.waypoints_m) out << " (" << p.x() << ", " << p.y() << ")";
  return out.str();
}

class UnknownSpacePlannerTest : public ::testing::Test {
 protected:
  // The building of `yaml_text` (the shipped one by default), seen by a
  // plane lidar at kPlane.
  void load(const std::string& yaml_text = "") {
    const std::string text = yaml_text.empty() ? support::roomsWorldText() : yaml_text;
    auto world = world::parseWorld(text, "rooms");
    ASSERT_TRUE(world.ok()) << world.status();
    world_ = std::make_unique<world::World>(std::move(*world));
    sim::LidarConfig plane = testing::mappingLidar();
    plane.channels = 1;
    plane.elevation_min_rad = plane.elevation_max_rad = 0.0;
    auto lidar = sim::Lidar::create(*world_, plane);
    ASSERT_TRUE(lidar.ok());
    lidar_ = std::make_unique<sim::Lidar>(std::move(*lidar));
  }
  void scanEveryRoom(OccupancyMap& map) {
    for (const Eigen::Vector3d& p :
         {Eigen::Vector3d(3, 3, kPlane), Eigen::Vector3d(3, 7, kPlane),
          Eigen::Vector3d(9, 5, kPlane), Eigen::Vector3d(15, 3, kPlane),
          Eigen::Vector3d(15, 8, kPlane), Eigen::Vector3d(6, 5, kPlane),
          Eigen::Vector3d(12, 3, kPlane), Eigen::Vector3d(15, 5.5, kPlane)}) {
      testing::scanInto(map, *lidar_, p);
    }
  }
  // Every point of the path, every 5 cm, clear of the true surfaces by the
  // radius.
  void expectClearOfTheWorld(const UnknownSpacePlan& plan, double radius) {
    for (size_t i = 1; i < plan.waypoints_m.size(); ++i) {
      const Eigen::Vector3d a = plan.waypoints_m[i - 1], b = plan.waypoints_m[i];
      const double length = (b - a).norm();
      for (double s = 0; s <= length; s += 0.05) {
        const Eigen::Vector3d p = a + (b - a) * (s / length);
        ASSERT_EQ(world_->collidingSurface(p, radius), "")
            << "at (" << p.transpose() << "):" << pathText(plan);
      }
    }
  }
  std::unique_ptr<world::World> world_;
  std::unique_ptr<sim::Lidar> lidar_;
};

TEST_F(UnknownSpacePlannerTest, FromRoomAItPlansIntoRoomDThroughUnknownSpace) {
  ASSERT_NO_FATAL_FAILURE(load());
  OccupancyMap map;
  testing::scanInto(map, *lidar_, {2, 2, kPlane});
  testing::scanInto(map, *lidar_, {3, 6, kPlane});
  const Eigen::Vector3d start(2, 2, 1.2), goal(15.5, 8, kAltitude);
  auto plan = planThroughUnknown(map, start, goal, building());
  ASSERT_TRUE(plan.ok()) << plan.status();
  std::printf("from room A: %.1f m, %.1f m unknown, %zu cells expanded, %.1f ms:%s\n",
              plan->length_m, plan->unknown_m, plan->expanded_cells, plan->planning_time_s * 1e3,
              pathText(*plan).c_str());
  EXPECT_EQ(plan->waypoints_m.front().head<2>(), start.head<2>());
  EXPECT_EQ(plan->waypoints_m.back(), goal);
  for (const auto& p : plan->waypoints_m) EXPECT_DOUBLE_EQ(p.z(), kAltitude);
  // Room A is known: the path leaves it by the A-B door, the only opening
  // seen, clear of its walls; beyond, it crosses unknown space.
  bool through_door = false;
  for (size_t i = 1; i < plan->waypoints_m.size(); ++i) {
    const Eigen::Vector3d a = plan->waypoints_m[i - 1], b = plan->waypoints_m[i];
    if (a.x() < 6 && b.x() >= 6) {
      const double y = a.y() + (b.y() - a.y()) * (6 - a.x()) / (b.x() - a.x());
      through_door = y > 4.4 + kRadius - 0.1 && y < 5.6 - kRadius + 0.1;
    }
  }
  EXPECT_TRUE(through_door) << pathText(*plan);
  EXPECT_GT(plan->unknown_m, 3.0);
  EXPECT_GE(plan->min_clearance_m, 0.0) << "nearer a wall seen than the radius";
  for (const auto& p : plan->waypoints_m) {
    if (p.x() < 5.8) {
      EXPECT_EQ(world_->collidingSurface(p, kRadius), "") << p.transpose();
    }
  }
}

TEST_F(UnknownSpacePlannerTest, WithTheBuildingKnownItGoesThroughTheDoorsNearTheShortest) {
  ASSERT_NO_FATAL_FAILURE(load());
  OccupancyMap map;
  scanEveryRoom(map);
  const Eigen::Vector3d start(2, 2, 1.2), goal(15.5, 8, kAltitude);
  auto plan = planThroughUnknown(map, start, goal, building());
  ASSERT_TRUE(plan.ok()) << plan.status();
  std::printf("building known: %.2f m, %.2f m unknown, clearance %.2f m, %.1f ms:%s\n",
              plan->length_m, plan->unknown_m, plan->min_clearance_m, plan->planning_time_s * 1e3,
              pathText(*plan).c_str());
  EXPECT_LT(plan->unknown_m, 0.5);
  ASSERT_NO_FATAL_FAILURE(expectClearOfTheWorld(*plan, kRadius));
  // Through the doors' centres: 5.0 + 6.5 + 3.9 + 3.0 = 18.4 m; a path
  // that keeps its clearance is a little longer, and not much.
  const double through_centres = (Eigen::Vector2d(6, 5) - Eigen::Vector2d(2, 2)).norm() +
                                 (Eigen::Vector2d(12, 2.5) - Eigen::Vector2d(6, 5)).norm() +
                                 (Eigen::Vector2d(15, 5) - Eigen::Vector2d(12, 2.5)).norm() +
                                 (Eigen::Vector2d(15.5, 8) - Eigen::Vector2d(15, 5)).norm();
  EXPECT_GT(plan->length_m, through_centres - 1.0);
  EXPECT_LT(plan->length_m, 1.15 * through_centres);
  // The same map, the same path.
  auto again = planThroughUnknown(map, start, goal, building());
  ASSERT_TRUE(again.ok());
  EXPECT_EQ(again->waypoints_m, plan->waypoints_m);
}

TEST_F(UnknownSpacePlannerTest, AClosedDoorMakesTheGoalUnreachable) {
  const auto text = support::roomsWithTheCdDoorWalledUp();
  ASSERT_TRUE(text) << "rooms.yaml declares the C-D door otherwise";
  ASSERT_NO_FATAL_FAILURE(load(*text));
  OccupancyMap map;
  scanEveryRoom(map);
  // Room D seen from where its door was: its walls are known all round.
  testing::scanInto(map, *lidar_, {15, 8, kPlane});
  auto plan = planThroughUnknown(map, {2, 2, 1.2}, {15.5, 8, kAltitude}, building());
  ASSERT_FALSE(plan.ok()) << pathText(*plan);
  EXPECT_EQ(plan.status().code(), absl::StatusCode::kNotFound) << plan.status();
  EXPECT_NE(plan.status().message().find("unreachable"), std::string::npos) << plan.status();
  EXPECT_NE(plan.status().message().find("blocked on every side"), std::string::npos)
      << plan.status();
}

TEST_F(UnknownSpacePlannerTest, BadRequestsAreRefused) {
  ASSERT_NO_FATAL_FAILURE(load());
  OccupancyMap map;
  scanEveryRoom(map);
  auto plan = planThroughUnknown(map, {2, 2, 1.2}, {25, 8, kAltitude}, building());
  EXPECT_EQ(plan.status().code(), absl::StatusCode::kInvalidArgument) << plan.status();
  EXPECT_NE(plan.status().message().find("outside the area"), std::string::npos);

  UnknownSpacePlanOptions unordered = building();
  unordered.bounds_max_m.x() = 0;
  plan = planThroughUnknown(map, {2, 2, 1.2}, {15.5, 8, kAltitude}, unordered);
  EXPECT_EQ(plan.status().code(), absl::StatusCode::kInvalidArgument) << plan.status();

  UnknownSpacePlanOptions huge = building();
  huge.bounds_min_m = {-500, -500, 0.5};
  huge.bounds_max_m = {500, 500, 1.6};
  plan = planThroughUnknown(map, {2, 2, 1.2}, {15.5, 8, kAltitude}, huge);
  EXPECT_EQ(plan.status().code(), absl::StatusCode::kInvalidArgument) << plan.status();
  EXPECT_NE(plan.status().message().find("more than the"), std::string::npos) << plan.status();

  // A goal in the A-B wall, seen.
  plan = planThroughUnknown(map, {2, 2, 1.2}, {6.0, 2, kAltitude}, building());
  EXPECT_EQ(plan.status().code(), absl::StatusCode::kNotFound) << plan.status();
  EXPECT_NE(plan.status().message().find("within"), std::string::npos) << plan.status();

  // Too little unknown space allowed for a plan from room A alone.
  OccupancyMap room_a;
  testing::scanInto(room_a, *lidar_, {2, 2, kPlane});
  UnknownSpacePlanOptions cautious = building();
  cautious.max_unknown_m = 1.0;
  plan = planThroughUnknown(room_a, {2, 2, 1.2}, {15.5, 8, kAltitude}, cautious);
  EXPECT_EQ(plan.status().code(), absl::StatusCode::kNotFound) << plan.status();
  EXPECT_NE(plan.status().message().find("max_unknown_m"), std::string::npos) << plan.status();
}

}  // namespace
}  // namespace behaviorlib::nav
