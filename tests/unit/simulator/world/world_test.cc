#include "formats/world/world.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <unistd.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <limits>
#include <numbers>
#include <string>

namespace behaviorlib::sim {
namespace {

using ::testing::HasSubstr;

constexpr double kInf = std::numeric_limits<double>::infinity();

std::string worldPath(const std::string& file) {
  return std::string(BEHAVIORLIB_WORLDS_DIR) + "/" + file;
}

/// Writes `text` to a fresh file in the test temp directory.
std::string writeTemp(const std::string& name, const std::string& text) {
  const std::string path =
      ::testing::TempDir() + "world_test_" + std::to_string(::getpid()) + "_" + name + ".yaml";
  std::ofstream(path) << text;
  return path;
}

/// Loads `text` from a temp file and expects an error at `line` containing `problem`.
void expectError(const std::string& name, const std::string& text, int line,
                 const std::string& problem) {
  const std::string path = writeTemp(name, text);
  const absl::StatusOr<world::World> world = world::loadWorld(path);
  ASSERT_FALSE(world.ok()) << name;
  EXPECT_EQ(world.status().code(), absl::StatusCode::kInvalidArgument) << world.status();
  const std::string message(world.status().message());
  EXPECT_THAT(message, HasSubstr(path + ":" + std::to_string(line) + ": ")) << name;
  EXPECT_THAT(message, HasSubstr(problem)) << name;
  std::filesystem::remove(path);
}

// ---------------------------------------------------------------- shipped worlds

TEST(ShippedWorlds, EveryWorldFileLoads) {
  int count = 0;
  for (const auto& entry : std::filesystem::directory_iterator(BEHAVIORLIB_WORLDS_DIR)) {
    if (entry.path().extension() != ".yaml") continue;
    const absl::StatusOr<world::World> world = world::loadWorld(entry.path().string());
    ASSERT_TRUE(world.ok()) << world.status();
    EXPECT_EQ(world->name(), entry.path().stem().string());
    EXPECT_FALSE(world->startPoses().empty()) << entry.path();
    for (const world::StartPose& pose : world->startPoses()) {
      EXPECT_FALSE(world->collides(pose.position_m, 0.0)) << pose.robot_id;
    }
    ++count;
  }
  EXPECT_GE(count, 3);
}

TEST(ShippedWorlds, EmptyFieldHasOnlyTheGround) {
  const absl::StatusOr<world::World> world = world::loadWorld(worldPath("empty_field.yaml"));
  ASSERT_TRUE(world.ok()) << world.status();
  EXPECT_TRUE(world->boxes().empty());
  ASSERT_NE(world->findStartPose("drone1"), nullptr);
  EXPECT_EQ(world->castRay({0, 0, 1}, {1, 0, 0}, 1000.0), kInf);
  EXPECT_DOUBLE_EQ(world->castRay({0, 0, 1}, {0, 0, -1}, 1000.0), 1.0);
}

TEST(ShippedWorlds, RoomsHasThreeOrMoreRoomsJoinedByDoors) {
  const absl::StatusOr<world::World> world = world::loadWorld(worldPath("rooms.yaml"));
  ASSERT_TRUE(world.ok()) << world.status();
  // 3 inner doors (A-B, B-C, C-D) plus the entrance.
  EXPECT_GE(world->doors().size(), 4u);
  const world::StartPose* start = world->findStartPose("drone1");
  ASSERT_NE(start, nullptr);
  // Inside: walls in all four directions at flight height.
  const Eigen::Vector3d eye = start->position_m + Eigen::Vector3d(0, 0, 1.0);
  for (double yaw : {0.0, 0.5 * std::numbers::pi, std::numbers::pi, 1.5 * std::numbers::pi}) {
    EXPECT_LT(world->castRay(eye, {std::cos(yaw), std::sin(yaw), 0}, 50.0), 20.0) << yaw;
  }
  // Through each door the ray passes, below the lintel it does not.
  for (const world::Door& door : world->doors()) {
    const Eigen::Vector3d across(-std::sin(door.yaw_rad), std::cos(door.yaw_rad), 0.0);
    const Eigen::Vector3d before = door.center_m + Eigen::Vector3d(0, 0, 1.0) - across * 0.5;
    EXPECT_GT(world->castRay(before, across, 1.0), 1.0) << door.wall;
    EXPECT_FALSE(world->collides(door.center_m + Eigen::Vector3d(0, 0, 1.0), 0.3)) << door.wall;
    const Eigen::Vector3d high = before + Eigen::Vector3d(0, 0, door.height_m + 0.2 - 1.0);
    EXPECT_LT(world->castRay(high, across, 1.0), 1.0) << door.wall;
  }
}

TEST(ShippedWorlds, AircraftHasMarkersOnItsSurfaces) {
  const absl::StatusOr<world::World> world = world::loadWorld(worldPath("aircraft.yaml"));
  ASSERT_TRUE(world.ok()) << world.status();
  ASSERT_GE(world->markers().size(), 3u);
  for (const world::Marker& marker : world->markers()) {
    EXPECT_FALSE(marker.attached_to.empty()) << marker.name;
    EXPECT_NE(world->findBox(marker.attached_to), nullptr) << marker.name;
    // The surface is right behind the marker and nothing is in front of it.
    EXPECT_NEAR(world->castRay(marker.center_m + marker.normal * 0.5, -marker.normal, 2.0), 0.5,
                1e-9)
        << marker.name;
  }
  for (const char* part : {"fuselage", "wings", "stabilizer", "fin"}) {
    EXPECT_NE(world->findBox(part), nullptr) << part;
  }
  ASSERT_NE(world->findStartPose("drone1"), nullptr);
}

TEST(ShippedWorlds, ReadmeExampleLoads) {
  std::ifstream in(worldPath("README.md"));
  ASSERT_TRUE(in) << "README.md";
  const std::string readme((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  const std::size_t begin = readme.find("```yaml\n");
  ASSERT_NE(begin, std::string::npos);
  const std::size_t end = readme.find("```", begin + 8);
  ASSERT_NE(end, std::string::npos);
  const absl::StatusOr<world::World> world =
      world::parseWorld(readme.substr(begin + 8, end - begin - 8), "README.md example");
  ASSERT_TRUE(world.ok()) << world.status();
  EXPECT_EQ(world->doors().size(), 1u);
  EXPECT_EQ(world->markers().size(), 1u);
}

// ---------------------------------------------------------------- malformed files

TEST(WorldFile, MissingFileNamesTheFile) {
  const absl::StatusOr<world::World> world = world::loadWorld("/nonexistent/dir/nowhere.yaml");
  ASSERT_FALSE(world.ok());
  EXPECT_EQ(world.status().code(), absl::StatusCode::kNotFound);
  EXPECT_THAT(world.status().message(), HasSubstr("/nonexistent/dir/nowhere.yaml"));
}

TEST(WorldFile, BadType) {
  expectError("bad_type",
              "name: t\n"
              "boxes:\n"
              "  - name: door\n"
              "    center_m: [1, 2, 3]\n"
              "    size_m: [1, 1, 1]\n"
              "    yaw_rad: sideways\n",
              6, "box 'door': yaw_rad must be a number");
  expectError("bad_vector",
              "name: t\n"
              "boxes:\n"
              "  - name: door\n"
              "    center_m: [1, 2]\n"
              "    size_m: [1, 1, 1]\n",
              4, "box 'door': center_m must be a list of 3 numbers");
  expectError("bad_color",
              "name: t\n"
              "boxes:\n"
              "  - name: door\n"
              "    center_m: [1, 2, 3]\n"
              "    size_m: [1, 1, 1]\n"
              "    color: [300, 0, 0]\n",
              6, "color must be a list of 3 integers 0..255");
  expectError("boxes_not_a_list", "name: t\nboxes: 3\n", 2, "world: boxes must be a list");
}

TEST(WorldFile, MissingKey) {
  expectError("missing_key",
              "name: t\n"
              "boxes:\n"
              "  - name: ok\n"
              "    center_m: [0, 5, 1]\n"
              "    size_m: [1, 1, 1]\n"
              "  - name: door\n"
              "    center_m: [1, 2, 3]\n",
              6, "box 'door': missing required key 'size_m'");
  expectError("missing_name", "description: no name\n", 1, "missing required key 'name'");
}

TEST(WorldFile, UnknownKey) {
  expectError("unknown_key",
              "name: t\n"
              "boxes:\n"
              "  - name: door\n"
              "    center_m: [1, 2, 3]\n"
              "    size_m: [1, 1, 1]\n"
              "    colour: [1, 2, 3]\n",
              6, "box 'door': unknown key 'colour'");
  expectError("unknown_top_key", "name: t\nobstacles: []\n", 2, "world: unknown key 'obstacles'");
}

TEST(WorldFile, NegativeSize) {
  expectError("negative_size",
              "name: t\n"
              "boxes:\n"
              "  - name: door\n"
              "    center_m: [1, 2, 3]\n"
              "    size_m: [1, -1, 1]\n",
              5, "box 'door': size_m must be a list of 3 positive numbers");
}

TEST(WorldFile, OtherProblems) {
  expectError("syntax", "name: t\nboxes: [\n  - name: a\n", 3, "not valid YAML");
  expectError("empty", "", 1, "the world file is empty");
  expectError("duplicate_key", "name: t\nname: u\n", 2, "duplicate key 'name'");
  expectError("duplicate_box",
              "name: t\n"
              "boxes:\n"
              "  - {name: a, center_m: [0, 5, 1], size_m: [1, 1, 1]}\n"
              "  - {name: a, center_m: [0, 9, 1], size_m: [1, 1, 1]}\n",
              4, "box 'a': another box or wall has this name");
  expectError("door_outside_wall",
              "name: t\n"
              "walls:\n"
              "  - name: w\n"
              "    from_m: [0, 0]\n"
              "    to_m: [4, 0]\n"
              "    height_m: 3\n"
              "    doors:\n"
              "      - {offset_m: 3.8, width_m: 1.0}\n",
              8, "does not fit in the wall");
  expectError("marker_off_its_box",
              "name: t\n"
              "boxes:\n"
              "  - {name: b, center_m: [5, 0, 1], size_m: [1, 1, 2]}\n"
              "markers:\n"
              "  - name: m\n"
              "    text: hello\n"
              "    center_m: [4.0, 0, 1]\n"
              "    normal: [-1, 0, 0]\n"
              "    size_m: 0.5\n"
              "    attached_to: b\n",
              7, "marker 'm': center_m is 0.5 m from the -x face of box 'b'");
  expectError("marker_too_big",
              "name: t\n"
              "boxes:\n"
              "  - {name: b, center_m: [5, 0, 1], size_m: [1, 1, 2]}\n"
              "markers:\n"
              "  - name: m\n"
              "    text: hello\n"
              "    center_m: [4.5, 0, 1]\n"
              "    normal: [-1, 0, 0]\n"
              "    size_m: 1.5\n"
              "    attached_to: b\n",
              9, "the marker does not fit on the -x face of box 'b'");
  expectError("start_inside_box",
              "name: t\n"
              "boxes:\n"
              "  - {name: b, center_m: [5, 0, 1], size_m: [1, 1, 2]}\n"
              "start_poses:\n"
              "  - robot_id: d1\n"
              "    position_m: [5, 0, 0.5]\n",
              6, "start pose 'd1': position_m is inside 'b'");
}

TEST(WorldFile, WallsBecomeBoxesWithGapsForDoors) {
  const absl::StatusOr<world::World> world = world::parseWorld(
      "name: t\n"
      "walls:\n"
      "  - name: w\n"
      "    from_m: [0, 0]\n"
      "    to_m: [0, 10]\n"
      "    height_m: 3\n"
      "    thickness_m: 0.2\n"
      "    doors:\n"
      "      - {offset_m: 5, width_m: 1, height_m: 2}\n",
      "inline");
  ASSERT_TRUE(world.ok()) << world.status();
  // Two segments and the lintel.
  ASSERT_EQ(world->boxes().size(), 3u);
  ASSERT_EQ(world->doors().size(), 1u);
  EXPECT_NEAR(world->doors()[0].center_m.y(), 5.0, 1e-12);
  // Ray along +x at y = 2 hits the wall face at x = -0.1 ... from x = -5.
  EXPECT_NEAR(world->castRay({-5, 2, 1}, {1, 0, 0}, 20.0), 4.9, 1e-9);
  EXPECT_EQ(world->castRay({-5, 5, 1}, {1, 0, 0}, 20.0), kInf);           // through the door
  EXPECT_NEAR(world->castRay({-5, 5, 2.5}, {1, 0, 0}, 20.0), 4.9, 1e-9);  // the lintel
  // The wall extends by half its thickness past its ends.
  EXPECT_NEAR(world->castRay({0, -5, 1}, {0, 1, 0}, 20.0), 4.9, 1e-9);
}

// ---------------------------------------------------------------- ray casting

world::World wallWorld() {
  world::World world("wall");
  // A wall whose near face is the plane x = 5.
  world.addBox(
      world::Box{"wall", {5.1, 0.0, 1.5}, {0.2, 10.0, 3.0}, 0.0, {}, world::Box::Kind::kWall});
  return world;
}

TEST(CastRay, KnownWallExactDistance) {
  const world::World world = wallWorld();
  EXPECT_DOUBLE_EQ(world.castRay({0, 0, 1}, {1, 0, 0}, 30.0), 5.0);
  EXPECT_DOUBLE_EQ(world.castRay({1, 2, 1}, {1, 0, 0}, 30.0), 4.0);
  // Oblique: 5 / cos(30 degrees).
  const double a = std::numbers::pi / 6;
  EXPECT_NEAR(world.castRay({0, 0, 1}, {std::cos(a), std::sin(a), 0}, 30.0), 5.0 / std::cos(a),
              1e-12);
  // Beyond the maximum range, away from it, past its end.
  EXPECT_EQ(world.castRay({0, 0, 1}, {1, 0, 0}, 4.99), kInf);
  EXPECT_EQ(world.castRay({0, 0, 1}, {-1, 0, 0}, 30.0), kInf);
  EXPECT_EQ(world.castRay({0, 6, 1}, {1, 0, 0}, 30.0), kInf);
  // Inside the wall.
  EXPECT_EQ(world.castRay({5.1, 0, 1}, {1, 0, 0}, 30.0), 0.0);
}

TEST(CastRay, Ground) {
  const world::World world("empty");
  EXPECT_DOUBLE_EQ(world.castRay({3, 4, 2}, {0, 0, -1}, 30.0), 2.0);
  const Eigen::Vector3d down45 = Eigen::Vector3d(1, 0, -1).normalized();
  EXPECT_NEAR(world.castRay({0, 0, 1}, down45, 30.0), std::sqrt(2.0), 1e-12);
  EXPECT_EQ(world.castRay({0, 0, 1}, {0, 0, 1}, 30.0), kInf);
  EXPECT_EQ(world.castRay({0, 0, -1}, {0, 0, 1}, 30.0), 0.0);  // below the ground
  // The wall is farther than the ground along this ray.
  EXPECT_NEAR(wallWorld().castRay({0, 0, 1}, down45, 30.0), std::sqrt(2.0), 1e-12);
}

TEST(CastRay, YawedBoxAndPlane) {
  world::World world("yaw");
  // A 2 m cube turned 45 degrees: its nearest edge is at x = 5 - sqrt(2).
  world.addBox(
      world::Box{"cube", {5, 0, 1}, {2, 2, 2}, std::numbers::pi / 4, {}, world::Box::Kind::kBox});
  EXPECT_NEAR(world.castRay({0, 0, 1}, {1, 0, 0}, 30.0), 5.0 - std::sqrt(2.0), 1e-12);
  EXPECT_EQ(world.castRay({0, 1.5, 1}, {1, 0, 0}, 30.0), kInf);
  // A plane x = 10 facing -x (solid beyond).
  world.addPlane(world::Plane{"cliff", {10, 0, 0}, {-2, 0, 0}, {}});
  EXPECT_NEAR(world.castRay({0, 3, 1}, {1, 0, 0}, 30.0), 10.0, 1e-12);
  EXPECT_EQ(world.castRay({11, 3, 1}, {1, 0, 0}, 30.0), 0.0);
}

TEST(Collides, SphereAgainstBoxesAndGround) {
  const world::World world = wallWorld();
  const world::CollisionWorld& collision = world;
  EXPECT_TRUE(collision.collides({4.8, 0, 1}, 0.3));
  EXPECT_FALSE(collision.collides({4.8, 0, 1}, 0.1));
  EXPECT_TRUE(collision.collides({5.1, 0, 1}, 0.0));  // inside
  // Near a corner: the wall's top edge at (5, z = 3).
  EXPECT_FALSE(collision.collides({4.8, 0, 3.2}, 0.28));  // 0.283 m from the edge
  EXPECT_TRUE(collision.collides({4.8, 0, 3.2}, 0.29));
  // Resting on the ground is not a collision; being below it is.
  EXPECT_FALSE(collision.collides({0, 0, 0}, 0.3));
  EXPECT_FALSE(collision.collides({0, 0, 0.1}, 0.3));
  EXPECT_TRUE(collision.collides({0, 0, -0.01}, 0.3));
  EXPECT_EQ(world.collidingSurface({4.8, 0, 1}, 0.3), "wall");
  EXPECT_EQ(world.collidingSurface({0, 0, -1}, 0.3), "ground");

  world::World yawed("yaw");
  yawed.addBox(
      world::Box{"cube", {5, 0, 1}, {2, 2, 2}, std::numbers::pi / 4, {}, world::Box::Kind::kBox});
  const double edge_x = 5.0 - std::sqrt(2.0);
  EXPECT_FALSE(yawed.collides({edge_x - 0.25, 0, 1}, 0.2));
  EXPECT_TRUE(yawed.collides({edge_x - 0.15, 0, 1}, 0.2));
}

}  // namespace
}  // namespace behaviorlib::sim
