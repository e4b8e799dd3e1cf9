// EXPLORE_WITH_FRONTIERS against real processes: the channel broker, the
// simulator in the deterministic mode (the rooms world), basic_quadrotor_
// behaviors (ground-truth localization, take-off), the PID motion system
// (its controller follows the references) and navigation_with_lidar. Given
// only the building's bounds, the vehicle explores from room A until no
// reachable frontier is left; the saved map is measured against the world
// (map_coverage) and the flown track must have entered every room. A
// time limit ends it TIME_OUT; bad bounds are refused. A requested coverage
// ends it GOAL_ACHIEVED, and with the lidar switched off (the map stops
// growing) it ends WRONG_PROGRESS.

#include <octomap/OcTree.h>
#include <unistd.h>

#include <array>
#include <filesystem>
#include <string>

#include "formats/world/world.h"
#include "motion_test_support.h"
#include "sim_faults.h"
#include "simulator/tools/map_coverage.h"

namespace {

using namespace motion_test;

constexpr char kExplore[] = "EXPLORE_WITH_FRONTIERS";
constexpr double kAltitude = 1.2;
constexpr char kBuilding[] = R"("bounds_min_m": {"x": 0.1, "y": 0.1, "z": 0.0},
                                "bounds_max_m": {"x": 17.9, "y": 9.9, "z": 3.0})";

class ExploreWithFrontiersTest : public ::testing::Test {
 protected:
  void SetUp() override {
    char dir[] = "/tmp/explore_with_frontiers_XXXXXX";
    ASSERT_NE(mkdtemp(dir), nullptr);
    dir_ = dir;
    std::string error;
    ASSERT_TRUE(stack_.start(&error, {"--world", "rooms", "--enable-fault-injection"})) << error;
    pid_ = stack_.startSystem(BEHAVIORLIB_PID_SYSTEM_PATH, BEHAVIORLIB_PID_CONFIG_PATH, &error);
    ASSERT_TRUE(pid_) << error;
    nav_ = stack_.startSystem(BEHAVIORLIB_NAVIGATION_WITH_LIDAR_PATH,
                              BEHAVIORLIB_NAVIGATION_CONFIG_PATH, &error, {"--map-dir", dir_});
    ASSERT_TRUE(nav_) << error;
    pid_client_ = std::make_unique<SystemClient>(pid_->address());
    nav_client_ = std::make_unique<SystemClient>(nav_->address());
    ASSERT_NO_FATAL_FAILURE(stack_.localizeAndTakeOff(kAltitude));
    ASSERT_FALSE(pid_client_->start("QUADROTOR_PID_MOTION_CONTROL", "{}").empty());
    ASSERT_TRUE(FlightStack::waitFor([&] {
      return nav_client_->checkSituation(kExplore).feasible();
    })) << nav_client_->checkSituation(kExplore).ShortDebugString();
  }

  void TearDown() override {
    nav_client_.reset();
    pid_client_.reset();
    for (auto* p : {&nav_, &pid_}) {
      if (*p && (*p)->running()) (*p)->kill();
    }
    stack_.stop();
    std::filesystem::remove_all(dir_);
  }

  std::string dir_;
  FlightStack stack_;
  std::unique_ptr<support::ServerProcess> pid_, nav_;
  std::unique_ptr<SystemClient> pid_client_, nav_client_;
};

TEST_F(ExploreWithFrontiersTest, ExploresTheBuildingFromItsBoundsAlone) {
  const std::string id = nav_client_->start(kExplore, std::string("{") + kBuilding + "}");
  ASSERT_FALSE(id.empty());
  const auto finished = nav_client_->finished(id, seconds(240));
  ASSERT_TRUE(finished.has_value()) << "the exploration did not finish";
  std::printf("EXPLORE_WITH_FRONTIERS: %s (%.1f s simulated)\n",
              finished->finished().message().c_str(),
              static_cast<double>(finished->finished().active_duration().seconds()));
  ASSERT_EQ(finished->finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED)
      << finished->ShortDebugString();
  EXPECT_NE(finished->finished().message().find("frontier left"), std::string::npos)
      << finished->finished().message();
  EXPECT_NE(stack_.flightStatus().state(), v1::FLIGHT_STATE_CRASHED);

  // The flown track entered every room.
  std::array<bool, 4> rooms{};
  for (const auto& s : stack_.truth().between(0, 1e9)) {
    const Eigen::Vector3d& p = s.position_m;
    if (p.y() < 0 || p.y() > 10 || p.x() < 0 || p.x() > 18) continue;
    if (p.x() < 6)
      rooms[0] = true;
    else if (p.x() < 12)
      rooms[1] = true;
    else if (p.y() < 5)
      rooms[2] = true;
    else
      rooms[3] = true;
  }
  EXPECT_TRUE(rooms[0] && rooms[1] && rooms[2] && rooms[3])
      << "rooms entered (A B C D): " << rooms[0] << rooms[1] << rooms[2] << rooms[3];

  // The saved map knows the building.
  const std::string file = dir_ + "/explored.bt";
  const std::string save =
      nav_client_->start("SAVE_OCCUPANCY_GRID", "{\"file_path\": \"" + file + "\"}");
  ASSERT_FALSE(save.empty());
  const auto saved = nav_client_->finished(save, seconds(20));
  ASSERT_TRUE(saved.has_value());
  ASSERT_EQ(saved->finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED)
      << saved->ShortDebugString();
  auto world = behaviorlib::world::loadWorld(std::string(BEHAVIORLIB_WORLDS_DIR) + "/rooms.yaml");
  ASSERT_TRUE(world.ok()) << world.status();
  octomap::OcTree map(0.1);
  ASSERT_TRUE(map.readBinary(file));
  const auto coverage =
      behaviorlib::nav::measureCoverage(*world, map, {.height_m = kAltitude + 0.1});
  std::printf("mapped fraction of the building: %.3f\n", coverage.mappedFraction());
  EXPECT_GE(coverage.mappedFraction(), 0.95);
}

TEST_F(ExploreWithFrontiersTest, ATimeLimitEndsItTimeOutAndBadBoundsAreRefused) {
  v1::ActivateResponse response;
  const grpc::Status refused = nav_client_->activate(
      kExplore,
      R"({"bounds_min_m": {"x": 18, "y": 0, "z": 0}, "bounds_max_m": {"x": 0, "y": 10, "z": 3}})",
      &response);
  EXPECT_EQ(refused.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << refused.error_message();
  const grpc::Status too_high = nav_client_->activate(
      kExplore, std::string("{") + kBuilding + R"(, "altitude_m": 2.5})", &response);
  EXPECT_EQ(too_high.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << too_high.error_message();
  EXPECT_NE(too_high.error_message().find("out of bounds"), std::string::npos)
      << too_high.error_message();

  const std::string id =
      nav_client_->start(kExplore, std::string("{") + kBuilding + R"(, "time_limit_s": 3})");
  ASSERT_FALSE(id.empty());
  const auto finished = nav_client_->finished(id, seconds(60));
  ASSERT_TRUE(finished.has_value());
  EXPECT_EQ(finished->finished().cause(), v1::TERMINATION_CAUSE_TIME_OUT)
      << finished->ShortDebugString();
  EXPECT_NE(finished->finished().message().find("time_limit_s"), std::string::npos)
      << finished->finished().message();
}

TEST_F(ExploreWithFrontiersTest, ARequestedCoverageEndsItAndAMapThatStopsGrowingIsWrongProgress) {
  // Three fifths of the area known is enough.
  std::string id =
      nav_client_->start(kExplore, std::string("{") + kBuilding + R"(, "coverage": 0.6})");
  ASSERT_FALSE(id.empty());
  auto finished = nav_client_->finished(id, seconds(120));
  ASSERT_TRUE(finished.has_value());
  EXPECT_EQ(finished->finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED)
      << finished->ShortDebugString();
  EXPECT_NE(finished->finished().message().find("coverage 0.60 reached"), std::string::npos)
      << finished->finished().message();
  EXPECT_EQ(finished->finished().message().find("after 0 legs"), std::string::npos)
      << "the take-off point sees 39 % of the area: " << finished->finished().message();

  // Without the lidar nothing new is mapped, wherever the vehicle flies:
  // the known fraction stops growing.
  const grpc::Status off = sim_faults::inject(stack_.simulator().address(), "drone1",
                                              v1::FAILURE_COMPONENT_LIDAR, v1::FAILURE_TYPE_OFF);
  ASSERT_TRUE(off.ok()) << off.error_message();
  id = nav_client_->start(kExplore, std::string("{") + kBuilding + R"(, "stall_s": 5})");
  ASSERT_FALSE(id.empty());
  finished = nav_client_->finished(id, seconds(120));
  ASSERT_TRUE(finished.has_value());
  EXPECT_EQ(finished->finished().cause(), v1::TERMINATION_CAUSE_WRONG_PROGRESS)
      << finished->ShortDebugString();
  EXPECT_NE(finished->finished().message().find("has grown by less than 0.01"), std::string::npos)
      << finished->finished().message();
  EXPECT_NE(stack_.flightStatus().state(), v1::FLIGHT_STATE_CRASHED);
}

}  // namespace
