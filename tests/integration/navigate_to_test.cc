// NAVIGATE_TO against real processes: the channel broker, the simulator in
// the deterministic mode (the rooms world), basic_quadrotor_behaviors
// (ground-truth localization, take-off), the PID motion system (its
// controller follows the references) and navigation_with_lidar. From room
// A, the vehicle flies to a point in room D that the map has not seen, with
// no intermediate point; the flown track never comes nearer the world's
// true surfaces than the vehicle's body. With the C-D door walled up (a
// world variant), it ends WRONG_PROGRESS naming the cause, without touching
// anything; a partition the map has not seen is flown around after a new
// plan. A goal outside the bounds, or at an altitude the plans do not use, is
// refused at activation.

#include <unistd.h>

#include <filesystem>
#include <sstream>
#include <string>

#include "formats/world/world.h"
#include "motion_test_support.h"
#include "support/rooms_world.h"

namespace {

using namespace motion_test;

constexpr char kNavigate[] = "NAVIGATE_TO";
constexpr double kAltitude = 1.2;
constexpr double kRadius = 0.35;
// The vehicle's body: the quadrotor's arms reach 0.25 m from its centre.
constexpr double kBodyM = 0.25;
constexpr char kBuilding[] = R"("bounds_min_m": {"x": 0.1, "y": 0.1, "z": 0.0},
                                "bounds_max_m": {"x": 17.9, "y": 9.9, "z": 3.0})";

std::string goalJson(double x, double y, double z) {
  std::ostringstream out;
  out << R"({"goal_m": {"x": )" << x << R"(, "y": )" << y << R"(, "z": )" << z << "}, " << kBuilding
      << "}";
  return out.str();
}

// The least distance between the track and the world's surfaces (m, to 1 mm;
// 1 m at most).
double closestApproachM(const behaviorlib::world::World& world,
                        const std::vector<TruthSample>& track) {
  double closest = 1.0;
  for (const auto& s : track) {
    if (!world.collides(s.position_m, closest)) continue;
    double lo = 0.0, hi = closest;  // collides at hi, not at lo
    while (hi - lo > 1e-3) {
      const double mid = 0.5 * (lo + hi);
      (world.collides(s.position_m, mid) ? hi : lo) = mid;
    }
    closest = lo;
  }
  return closest;
}

class NavigateToTest : public ::testing::Test {
 protected:
  void TearDown() override {
    nav_client_.reset();
    pid_client_.reset();
    for (auto* p : {&nav_, &pid_}) {
      if (*p && (*p)->running()) (*p)->kill();
    }
    stack_.stop();
    if (!dir_.empty()) std::filesystem::remove_all(dir_);
  }

  // The stack in the world of `world_text`, the vehicle flying at kAltitude.
  void startIn(const std::string& world_text) {
    char dir[] = "/tmp/navigate_to_XXXXXX";
    ASSERT_NE(mkdtemp(dir), nullptr);
    dir_ = dir;
    const std::string world_file = dir_ + "/world.yaml";
    std::ofstream(world_file) << world_text;
    auto world = behaviorlib::world::parseWorld(world_text, world_file);
    ASSERT_TRUE(world.ok()) << world.status();
    world_ = std::make_unique<behaviorlib::world::World>(std::move(*world));
    std::string error;
    ASSERT_TRUE(stack_.start(&error, {"--world", world_file})) << error;
    pid_ = stack_.startSystem(BEHAVIORLIB_PID_SYSTEM_PATH, BEHAVIORLIB_PID_CONFIG_PATH, &error);
    ASSERT_TRUE(pid_) << error;
    nav_ = stack_.startSystem(BEHAVIORLIB_NAVIGATION_WITH_LIDAR_PATH,
                              BEHAVIORLIB_NAVIGATION_CONFIG_PATH, &error);
    ASSERT_TRUE(nav_) << error;
    pid_client_ = std::make_unique<SystemClient>(pid_->address());
    nav_client_ = std::make_unique<SystemClient>(nav_->address());
    ASSERT_NO_FATAL_FAILURE(stack_.localizeAndTakeOff(kAltitude));
    ASSERT_FALSE(pid_client_->start("QUADROTOR_PID_MOTION_CONTROL", "{}").empty());
    ASSERT_TRUE(FlightStack::waitFor([&] {
      return nav_client_->checkSituation(kNavigate).feasible();
    })) << nav_client_->checkSituation(kNavigate).ShortDebugString();
  }

  double closestApproach() { return closestApproachM(*world_, stack_.truth().between(0, 1e9)); }

  std::string dir_;
  std::unique_ptr<behaviorlib::world::World> world_;
  FlightStack stack_;
  std::unique_ptr<support::ServerProcess> pid_, nav_;
  std::unique_ptr<SystemClient> pid_client_, nav_client_;
};

TEST_F(NavigateToTest, FromRoomAToRoomDWithNoIntermediatePoint) {
  ASSERT_NO_FATAL_FAILURE(startIn(support::roomsWorldText()));
  const std::string id = nav_client_->start(kNavigate, goalJson(15.5, 8, kAltitude));
  ASSERT_FALSE(id.empty());
  const auto finished = nav_client_->finished(id, seconds(240));
  ASSERT_TRUE(finished.has_value()) << "the navigation did not finish";
  std::printf("NAVIGATE_TO: %s (%.1f s simulated)\n", finished->finished().message().c_str(),
              static_cast<double>(finished->finished().active_duration().seconds()));
  ASSERT_EQ(finished->finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED)
      << finished->ShortDebugString();
  const auto end = stack_.truth().latest();
  ASSERT_TRUE(end);
  EXPECT_LE((end->position_m - Eigen::Vector3d(15.5, 8, kAltitude)).norm(), 0.5);
  EXPECT_NE(stack_.flightStatus().state(), v1::FLIGHT_STATE_CRASHED);
  const double closest = closestApproach();
  std::printf("closest approach to a surface: %.3f m\n", closest);
  EXPECT_GE(closest, kBodyM) << "the vehicle touched a surface";
}

TEST_F(NavigateToTest, AGoalBehindAClosedDoorEndsWrongProgressWithoutTouchingAnything) {
  const auto text = support::roomsWithTheCdDoorWalledUp();
  ASSERT_TRUE(text) << "rooms.yaml declares the C-D door otherwise";
  ASSERT_NO_FATAL_FAILURE(startIn(*text));
  const std::string id = nav_client_->start(kNavigate, goalJson(15.5, 8, kAltitude));
  ASSERT_FALSE(id.empty());
  const auto finished = nav_client_->finished(id, seconds(240));
  ASSERT_TRUE(finished.has_value()) << "the navigation did not finish";
  std::printf("NAVIGATE_TO behind a closed door: %s\n", finished->finished().message().c_str());
  ASSERT_EQ(finished->finished().cause(), v1::TERMINATION_CAUSE_WRONG_PROGRESS)
      << finished->ShortDebugString();
  EXPECT_NE(finished->finished().message().find("unreachable"), std::string::npos)
      << finished->finished().message();
  EXPECT_NE(stack_.flightStatus().state(), v1::FLIGHT_STATE_CRASHED);
  const double closest = closestApproach();
  std::printf("closest approach to a surface: %.3f m\n", closest);
  EXPECT_GE(closest, kBodyM) << "the vehicle touched a surface";
}

// A partition across room B that the map has not seen when the first plan
// is made (from room A the lidar sees only its middle, through the door): the
// vehicle meets it on the way, holds, plans again around its south end (the
// only way past it) and reaches room D, touching nothing.
TEST_F(NavigateToTest, AWallTheMapHasNotSeenIsFlownAroundAfterANewPlan) {
  std::string text = support::roomsWorldText();
  const std::string marker = "\nboxes:";
  const size_t at = text.find(marker);
  ASSERT_NE(at, std::string::npos);
  text.insert(at, R"(
  - name: partition_b
    from_m: [9, 1.8]
    to_m: [9, 10]
    height_m: 3.0
)");
  ASSERT_NO_FATAL_FAILURE(startIn(text));
  const std::string id = nav_client_->start(kNavigate, goalJson(15.5, 8, kAltitude));
  ASSERT_FALSE(id.empty());
  const auto finished = nav_client_->finished(id, seconds(240));
  ASSERT_TRUE(finished.has_value()) << "the navigation did not finish";
  const std::string& message = finished->finished().message();
  std::printf("NAVIGATE_TO past a partition: %s\n", message.c_str());
  ASSERT_EQ(finished->finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED)
      << finished->ShortDebugString();
  // At least one new plan for a wall seen ahead, beyond the building's own
  // (the flight without the partition makes 3).
  const size_t counted = message.find(" after a wall seen ahead");
  ASSERT_NE(counted, std::string::npos) << message;
  const size_t number = message.rfind(", ", counted);
  ASSERT_NE(number, std::string::npos) << message;
  EXPECT_GE(std::stoi(message.substr(number + 2, counted - number - 2)), 4) << message;
  // It passed the partition's line south of its end.
  const auto track = stack_.truth().between(0, 1e9);
  for (size_t i = 1; i < track.size(); ++i) {
    const auto& a = track[i - 1].position_m;
    const auto& b = track[i].position_m;
    if ((a.x() < 9) != (b.x() < 9)) {
      EXPECT_LT(b.y(), 1.8) << "crossed x = 9 at y " << b.y();
    }
  }
  const double closest = closestApproach();
  std::printf("closest approach to a surface: %.3f m\n", closest);
  EXPECT_GE(closest, kBodyM) << "the vehicle touched a surface";
}

TEST_F(NavigateToTest, GoalsOutsideTheBoundsOrTheirAltitudesAreRefusedAtActivation) {
  ASSERT_NO_FATAL_FAILURE(startIn(support::roomsWorldText()));
  v1::ActivateResponse response;
  grpc::Status status = nav_client_->activate(kNavigate, goalJson(25, 8, kAltitude), &response);
  EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << describe(status);
  EXPECT_NE(status.error_message().find("outside the bounds"), std::string::npos)
      << status.error_message();
  status = nav_client_->activate(kNavigate, goalJson(15.5, 8, 2.8), &response);
  EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << describe(status);
  EXPECT_NE(status.error_message().find("altitude"), std::string::npos) << status.error_message();
  status = nav_client_->activate(
      kNavigate,
      R"({"goal_m": {"x": 3, "y": 3, "z": 1.2}, "bounds_min_m": {"x": 0, "y": 0, "z": 0},
          "bounds_max_m": {"x": 2000, "y": 2000, "z": 3}})",
      &response);
  EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << describe(status);
  EXPECT_NE(status.error_message().find("more than"), std::string::npos) << status.error_message();
}

}  // namespace
