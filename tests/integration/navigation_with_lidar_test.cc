// navigation_with_lidar against real processes: the channel broker, the
// simulator (the four-room building, its 2-D lidar, 4x), the coordinator
// (belief memory), basic_quadrotor_behaviors (SELF_LOCALIZE_WITH_GROUND_TRUTH,
// TAKE_OFF) and the system under test. The vehicle takes off in room A, the
// map builds from its scans; paths to room B avoid the building's real walls
// and reach belief memory and the channel; goals out of bounds are refused,
// goals not yet seen, in a wall or beyond doors too narrow wait for the map,
// then end naming why, and a bad save path is reported; planning time-outs
// re-plan up to max_replans, then end TIME_OUT; the saved map is read back
// with OctoMap; CLEAR empties it (the lidar stopped by fault injection).

#include <octomap/OcTree.h>
#include <unistd.h>

#include <atomic>
#include <filesystem>
#include <fstream>

#include "behaviorlib/channel/channel_client.h"
#include "behaviorlib/v1/coordinator.grpc.pb.h"
#include "behaviorlib/v1/types.pb.h"
#include "formats/world/world.h"
#include "motion_test_support.h"
#include "sim_faults.h"
#include "support/deterministic.h"

namespace {

using namespace motion_test;

constexpr double kRadius = 0.3;
const Eigen::Vector3d kGoalInRoomB(9.0, 7.0, 1.0);

class NavigationWithLidarTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    char dir[] = "/tmp/navigation_with_lidar_XXXXXX";
    ASSERT_NE(mkdtemp(dir), nullptr);
    dir_ = new std::string(dir);
    auto world = behaviorlib::world::loadWorld(std::string(BEHAVIORLIB_WORLDS_DIR) + "/rooms.yaml");
    ASSERT_TRUE(world.ok()) << world.status();
    world_ = new behaviorlib::world::World(std::move(*world));

    broker_ = new support::ServerProcess(BEHAVIORLIB_CHANNEL_BROKER_PATH, {});
    ASSERT_TRUE(broker_->start()) << broker_->error();
    simulator_ = new support::ServerProcess(
        BEHAVIORLIB_SIMULATOR_PATH,
        support::deterministicSimulatorArgs({"--channel", broker_->address(), "--world", "rooms",
                                             "--seed", kSeed, "--enable-fault-injection"},
                                            1));
    ASSERT_TRUE(simulator_->start()) << simulator_->error();
    coordinator_ = new support::ServerProcess(BEHAVIORLIB_COORDINATOR_PATH,
                                              {"--state-dir", *dir_ + "/coordinator"});
    ASSERT_TRUE(coordinator_->start()) << coordinator_->error();
    const std::vector<std::string> common =
        support::followTimeArgs({"--robot-id", kRobot, "--channel", broker_->address(), "--clock",
                                 "sim", "--flight-controller", simulator_->address()},
                                simulator_->address());
    auto args = common;
    args.insert(args.end(), {"--config", BEHAVIORLIB_BASIC_CONFIG_PATH});
    basic_ = new support::ServerProcess(BEHAVIORLIB_BASIC_QUADROTOR_BEHAVIORS_PATH, args);
    ASSERT_TRUE(basic_->start()) << basic_->error();
    args = common;
    args.insert(args.end(), {"--config", BEHAVIORLIB_NAVIGATION_CONFIG_PATH, "--coordinator",
                             coordinator_->address(), "--map-dir", *dir_});
    navigation_ = new support::ServerProcess(BEHAVIORLIB_NAVIGATION_WITH_LIDAR_PATH, args);
    ASSERT_TRUE(navigation_->start()) << navigation_->error();
    basic_client_ = new SystemClient(basic_->address());
    nav_client_ = new SystemClient(navigation_->address());
    channel_ = new behaviorlib::channel::ChannelClient(broker_->address());
    beliefs_ = v1::Coordinator::NewStub(
                   grpc::CreateChannel(coordinator_->address(), grpc::InsecureChannelCredentials()))
                   .release();

    // Take off in room A, then let the map build from 20 more scans (2 s of
    // simulated time at the lidar's 10 Hz).
    ASSERT_FALSE(basic_client_->start("SELF_LOCALIZE_WITH_GROUND_TRUTH", "{}").empty());
    ASSERT_TRUE(
        FlightStack::waitFor([] { return basic_client_->checkSituation("TAKE_OFF").feasible(); }));
    const std::string take_off = basic_client_->start("TAKE_OFF", "{\"altitude_m\": 1.0}");
    ASSERT_FALSE(take_off.empty());
    const auto finished = basic_client_->finished(take_off);
    ASSERT_TRUE(finished) << "TAKE_OFF did not finish";
    ASSERT_EQ(finished->finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED)
        << finished->ShortDebugString();
    std::atomic<int> scans{0};
    {
      auto sub = channel_->subscribeTyped<v1::LaserScan>(
          std::string("robots/") + kRobot + "/lidar/scan",
          {.mode = v1::DELIVERY_MODE_QUEUE, .queue_size = 100},
          [&](const v1::LaserScan&) { ++scans; });
      ASSERT_TRUE(FlightStack::waitFor([&] { return scans >= 20; }, seconds(15)));
    }
    ASSERT_TRUE(FlightStack::waitFor([] {
      return nav_client_->checkSituation("GENERATE_PATH_WITH_OCCUPANCY_GRID").feasible();
    })) << nav_client_->checkSituation("GENERATE_PATH_WITH_OCCUPANCY_GRID").ShortDebugString();
  }

  static void TearDownTestSuite() {
    delete beliefs_;
    delete channel_;
    delete nav_client_;
    delete basic_client_;
    for (support::ServerProcess* p : {navigation_, basic_, coordinator_, simulator_, broker_}) {
      if (p && p->running()) p->kill();
      delete p;
    }
    delete world_;
    std::filesystem::remove_all(*dir_);
    delete dir_;
  }

  static std::string goalJson(const Eigen::Vector3d& goal, double radius,
                              const std::string& extra = "") {
    std::ostringstream out;
    out << "{\"goal_m\": {\"x\": " << goal.x() << ", \"y\": " << goal.y() << ", \"z\": " << goal.z()
        << "}, \"vehicle_radius_m\": " << radius << extra << "}";
    return out.str();
  }

  /// The finished event of one activation (expected to be accepted).
  static v1::BehaviorEvent run(const std::string& behavior, const std::string& json) {
    const std::string id = nav_client_->start(behavior, json);
    EXPECT_FALSE(id.empty());
    auto finished = nav_client_->finished(id, seconds(20));
    EXPECT_TRUE(finished) << behavior << " did not finish";
    return finished.value_or(v1::BehaviorEvent());
  }

  static void injectLidar(v1::FailureType type) {
    const grpc::Status status =
        sim_faults::inject(simulator_->address(), kRobot, v1::FAILURE_COMPONENT_LIDAR, type);
    ASSERT_TRUE(status.ok()) << status.error_message();
  }

  static size_t occupiedIn(const std::string& file) {
    octomap::OcTree tree(0.1);
    EXPECT_TRUE(tree.readBinary(file)) << file;
    size_t occupied = 0;
    for (auto it = tree.begin_leafs(); it != tree.end_leafs(); ++it)
      occupied += tree.isNodeOccupied(*it);
    return occupied;
  }

  static grpc::Status readBelief(const std::string& key, v1::Belief* belief) {
    v1::ReadBeliefRequest request;
    request.set_key(key);
    v1::ReadBeliefResponse response;
    grpc::Status status = beliefs_->ReadBelief(deadline().get(), request, &response);
    *belief = response.belief();
    return status;
  }

  static std::string* dir_;
  static behaviorlib::world::World* world_;
  static support::ServerProcess *broker_, *simulator_, *coordinator_, *basic_, *navigation_;
  static SystemClient *basic_client_, *nav_client_;
  static behaviorlib::channel::ChannelClient* channel_;
  static v1::Coordinator::Stub* beliefs_;
};

std::string* NavigationWithLidarTest::dir_ = nullptr;
behaviorlib::world::World* NavigationWithLidarTest::world_ = nullptr;
support::ServerProcess* NavigationWithLidarTest::broker_ = nullptr;
support::ServerProcess* NavigationWithLidarTest::simulator_ = nullptr;
support::ServerProcess* NavigationWithLidarTest::coordinator_ = nullptr;
support::ServerProcess* NavigationWithLidarTest::basic_ = nullptr;
support::ServerProcess* NavigationWithLidarTest::navigation_ = nullptr;
SystemClient* NavigationWithLidarTest::basic_client_ = nullptr;
SystemClient* NavigationWithLidarTest::nav_client_ = nullptr;
behaviorlib::channel::ChannelClient* NavigationWithLidarTest::channel_ = nullptr;
v1::Coordinator::Stub* NavigationWithLidarTest::beliefs_ = nullptr;

TEST_F(NavigationWithLidarTest, PlansFromRoomAToRoomBAroundTheWallsIntoBeliefAndChannel) {
  std::mutex mutex;
  std::optional<v1::Path> published;
  auto sub = channel_->subscribeTyped<v1::Path>(
      std::string("robots/") + kRobot + "/navigation/path", {}, [&](const v1::Path& p) {
        std::lock_guard lock(mutex);
        published = p;
      });
  ASSERT_TRUE(sub->waitConnected(seconds(5)));
  const auto finished = run("GENERATE_PATH_WITH_OCCUPANCY_GRID", goalJson(kGoalInRoomB, kRadius));
  ASSERT_EQ(finished.finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED)
      << finished.ShortDebugString();

  // The belief: a list of {x, y, z}, FOLLOW_PATH's path_m.
  v1::Belief belief;
  ASSERT_TRUE(readBelief(std::string(kRobot) + "/path", &belief).ok());
  EXPECT_EQ(belief.writer(), std::string(kRobot) + "/GENERATE_PATH_WITH_OCCUPANCY_GRID");
  std::vector<Eigen::Vector3d> path;
  for (const auto& v : belief.value().list_value().values()) {
    const auto& f = v.struct_value().fields();
    path.emplace_back(f.at("x").number_value(), f.at("y").number_value(), f.at("z").number_value());
  }
  ASSERT_GE(path.size(), 2u);
  const auto truth_start = Eigen::Vector3d(2.0, 2.0, 1.0);
  EXPECT_LT((path.front() - truth_start).norm(), 0.5) << path.front().transpose();
  EXPECT_LT((path.back() - kGoalInRoomB).norm(), 1e-6) << path.back().transpose();
  // The map it was planned on (the vehicle hovers: it hardly changes).
  const std::string file = *dir_ + "/planned_on.bt";
  ASSERT_EQ(run("SAVE_OCCUPANCY_GRID", "{\"file_path\": \"" + file + "\"}").finished().cause(),
            v1::TERMINATION_CAUSE_GOAL_ACHIEVED);
  octomap::OcTree map(0.1);
  ASSERT_TRUE(map.readBinary(file));
  std::vector<Eigen::Vector3d> occupied;
  for (auto it = map.begin_leafs(); it != map.end_leafs(); ++it) {
    if (map.isNodeOccupied(*it)) occupied.emplace_back(it.getX(), it.getY(), it.getZ());
  }
  // Every point of every segment, every 5 cm, keeps the radius (less 10 %
  // for the voxels' discretization) from the map's occupied voxels, and,
  // where the map knows the space, from the world's real surfaces (unknown
  // space counts as free: a wall never seen is not avoided).
  size_t known = 0, points = 0;
  for (size_t i = 1; i < path.size(); ++i) {
    const Eigen::Vector3d a = path[i - 1], b = path[i];
    const int n = std::max(1, static_cast<int>((b - a).norm() / 0.05));
    for (int k = 0; k <= n; ++k) {
      const Eigen::Vector3d p = a + (b - a) * (static_cast<double>(k) / n);
      ++points;
      for (const Eigen::Vector3d& o : occupied) {
        ASSERT_GT((p - o).cwiseAbs().maxCoeff() - 0.05, -1e-9) << "voxel " << o.transpose();
        const Eigen::Vector3d d = ((p - o).cwiseAbs().array() - 0.05).max(0.0).matrix();
        ASSERT_GE(d.norm(), 0.9 * kRadius) << "at " << p.transpose() << ", voxel " << o.transpose();
      }
      // The 2-D lidar knows the plane it scans (1.1 m up, the vehicle at 1 m).
      if (map.search(p.x(), p.y(), 1.05) == nullptr && map.search(p.x(), p.y(), 1.15) == nullptr)
        continue;
      ++known;
      ASSERT_EQ(world_->collidingSurface(p, 0.9 * kRadius), "") << "at " << p.transpose();
    }
  }
  // Part of the path may run outside (through the entrance, in space never
  // seen); its start in room A is mapped.
  EXPECT_GT(known, 0u) << points << " points";
  // The same path on the channel.
  ASSERT_TRUE(FlightStack::waitFor([&] {
    std::lock_guard lock(mutex);
    return published.has_value();
  }));
  std::lock_guard lock(mutex);
  ASSERT_EQ(published->poses_size(), static_cast<int>(path.size()));
  EXPECT_EQ(published->header().frame_id(), "world");
  for (size_t i = 0; i < path.size(); ++i) {
    const auto& q = published->poses(static_cast<int>(i)).position_m();
    EXPECT_DOUBLE_EQ(q.x(), path[i].x());
    EXPECT_DOUBLE_EQ(q.y(), path[i].y());
  }
}

TEST_F(NavigationWithLidarTest, AGoalBeyondDoorsNarrowerThanTheVehicleIsBlocked) {
  // 0.7 m of radius: the 1.2 m doors are closed to it; room A is shut. The
  // hovering vehicle's new scans change the map; each change is tried again
  // until map_wait_s (simulated time) has passed.
  const auto finished = run(
      "GENERATE_PATH_WITH_OCCUPANCY_GRID",
      goalJson(kGoalInRoomB, 0.7, ", \"belief_key\": \"drone1/wide_path\", \"map_wait_s\": 2.5"));
  EXPECT_EQ(finished.finished().cause(), v1::TERMINATION_CAUSE_WRONG_PROGRESS)
      << finished.ShortDebugString();
  const std::string& message = finished.finished().message();
  EXPECT_NE(message.find("unreachable (blocked): no free passage"), std::string::npos) << message;
  EXPECT_NE(message.find("waited"), std::string::npos) << message;
  EXPECT_GE(finished.finished().active_duration().seconds(), 2) << message;
  // One scan a second is mapped while the vehicle hovers: tried again.
  EXPECT_EQ(message.find(" 0 new attempts"), std::string::npos) << message;
  v1::Belief belief;
  EXPECT_EQ(readBelief("drone1/wide_path", &belief).error_code(), grpc::StatusCode::NOT_FOUND);
}

TEST_F(NavigationWithLidarTest, PlanningTimeOutsRePlanUpToTheLimitThenEndTimeOut) {
  // A second navigation system on the same robot mapping at 5 cm: building
  // the inflated grid of the building alone takes far longer than the 10 ms
  // planning limit, and with no grace and 100 Hz monitoring every attempt
  // is seen running past it: re-planned max_replans times, then TIME_OUT.
  const std::string config = *dir_ + "/fine_map.yaml";
  {
    std::ofstream out(config);
    out << "mapping:\n  resolution_m: 0.05\n"
           "behaviors:\n  GENERATE_PATH_WITH_OCCUPANCY_GRID:\n"
           "    frequency_hz: 100\n    timeout_grace_s: 0\n";
  }
  support::ServerProcess fine(BEHAVIORLIB_NAVIGATION_WITH_LIDAR_PATH,
                              {"--robot-id", kRobot, "--channel", broker_->address(), "--clock",
                               "sim", "--config", config});
  ASSERT_TRUE(fine.start()) << fine.error();
  SystemClient client(fine.address());
  ASSERT_TRUE(FlightStack::waitFor([&] {
    return client.checkSituation("GENERATE_PATH_WITH_OCCUPANCY_GRID").feasible();
  })) << client.checkSituation("GENERATE_PATH_WITH_OCCUPANCY_GRID").ShortDebugString();
  const std::string id = client.start(
      "GENERATE_PATH_WITH_OCCUPANCY_GRID",
      goalJson(kGoalInRoomB, kRadius, ", \"planning_time_limit_s\": 0.01, \"max_replans\": 2"));
  ASSERT_FALSE(id.empty());
  const auto finished = client.finished(id, seconds(30));
  ASSERT_TRUE(finished.has_value());
  EXPECT_EQ(finished->finished().cause(), v1::TERMINATION_CAUSE_TIME_OUT)
      << finished->ShortDebugString();
  EXPECT_NE(finished->finished().message().find("each of 3 attempt(s) (max_replans 2)"),
            std::string::npos)
      << finished->finished().message();
  fine.terminate();
}

TEST_F(NavigationWithLidarTest, GoalsOutOfBoundsAreRefusedUnseenOrInAWallSaySo) {
  v1::ActivateResponse response;
  grpc::Status too_high = nav_client_->activate("GENERATE_PATH_WITH_OCCUPANCY_GRID",
                                                goalJson({3, 5, 2.5}, kRadius), &response);
  EXPECT_EQ(too_high.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << describe(too_high);
  EXPECT_NE(too_high.error_message().find("out of bounds"), std::string::npos)
      << too_high.error_message();
  // Far beyond anything the lidar has seen.
  auto outside = run("GENERATE_PATH_WITH_OCCUPANCY_GRID",
                     goalJson({60, 60, 1.0}, kRadius, ", \"map_wait_s\": 0"));
  EXPECT_EQ(outside.finished().cause(), v1::TERMINATION_CAUSE_WRONG_PROGRESS)
      << outside.ShortDebugString();
  EXPECT_NE(outside.finished().message().find("(unknown): it lies outside the space mapped"),
            std::string::npos)
      << outside.finished().message();
  // The wall between rooms A and B, seen by the lidar.
  auto in_wall = run("GENERATE_PATH_WITH_OCCUPANCY_GRID",
                     goalJson({6.0, 2.0, 1.0}, kRadius, ", \"map_wait_s\": 0"));
  EXPECT_EQ(in_wall.finished().cause(), v1::TERMINATION_CAUSE_WRONG_PROGRESS)
      << in_wall.ShortDebugString();
  EXPECT_NE(in_wall.finished().message().find("(blocked): an occupied voxel"), std::string::npos)
      << in_wall.finished().message();
}

TEST_F(NavigationWithLidarTest, BoundsClipThePlanningVolumeAndBadBoundsAreRefused) {
  const auto expect_refused = [](const std::string& json, const std::string& reason) {
    v1::ActivateResponse response;
    const grpc::Status status =
        nav_client_->activate("GENERATE_PATH_WITH_OCCUPANCY_GRID", json, &response);
    EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << describe(status);
    EXPECT_NE(status.error_message().find(reason), std::string::npos) << status.error_message();
  };
  // Room B's centre is in the map, but outside a box around room A only.
  expect_refused(R"({"goal_m": {"x": 9, "y": 5, "z": 1}, "bounds_min_m": {"x": 0, "y": 0, "z": 0},
                     "bounds_max_m": {"x": 6, "y": 10, "z": 3}})",
                 "out of bounds");
  expect_refused(
      R"({"goal_m": {"x": 3, "y": 5, "z": 1}, "bounds_min_m": {"x": 0, "y": 0, "z": 0}})",
      "go together");
  expect_refused(R"({"goal_m": {"x": 3, "y": 5, "z": 1}, "bounds_min_m": {"x": 18, "y": 0, "z": 0},
                     "bounds_max_m": {"x": 0, "y": 10, "z": 3}})",
                 "must be below bounds_max_m");
  // Inside the box around the building, the plan from room A to room B
  // stays in the box.
  const auto finished =
      run("GENERATE_PATH_WITH_OCCUPANCY_GRID",
          R"({"goal_m": {"x": 9, "y": 5, "z": 1}, "belief_key": "drone1/bounded_path",
              "bounds_min_m": {"x": 0, "y": 0, "z": 0}, "bounds_max_m": {"x": 18, "y": 10, "z": 3}})");
  ASSERT_EQ(finished.finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED)
      << finished.ShortDebugString();
  v1::Belief belief;
  ASSERT_TRUE(readBelief("drone1/bounded_path", &belief).ok());
  ASSERT_GT(belief.value().list_value().values_size(), 1);
  for (const auto& point : belief.value().list_value().values()) {
    const auto& f = point.struct_value().fields();
    for (const char* axis : {"x", "y"}) {
      const double v = f.contains(axis) ? f.at(axis).number_value() : 0.0;
      EXPECT_GE(v, 0.0) << axis;
      EXPECT_LE(v, std::string(axis) == "x" ? 18.0 : 10.0) << axis;
    }
  }
}

TEST_F(NavigationWithLidarTest, SavesAMapOctoMapReadsBackAndNamesItInBeliefMemory) {
  const std::string file = *dir_ + "/building.bt";
  const auto finished = run("SAVE_OCCUPANCY_GRID", "{\"file_path\": \"" + file + "\"}");
  ASSERT_EQ(finished.finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED)
      << finished.ShortDebugString();
  octomap::OcTree tree(0.1);
  ASSERT_TRUE(tree.readBinary(file));
  EXPECT_DOUBLE_EQ(tree.getResolution(), 0.1);
  size_t occupied = 0;
  for (auto it = tree.begin_leafs(); it != tree.end_leafs(); ++it)
    occupied += tree.isNodeOccupied(*it);
  EXPECT_GT(occupied, 500u);
  // Room A's walls at flight height are occupied (their faces: x = 5.9 for
  // the wall to room B, x = 0.1 for the west wall); its middle is free.
  auto occupiedAcross = [&](double x, double y) {
    for (double dx = -0.1; dx <= 0.1001; dx += 0.05) {
      const octomap::OcTreeNode* node = tree.search(x + dx, y, 1.1);
      if (node != nullptr && tree.isNodeOccupied(node)) return true;
    }
    return false;
  };
  EXPECT_TRUE(occupiedAcross(5.9, 2.0));
  EXPECT_TRUE(occupiedAcross(0.1, 5.0));
  bool seen_free = false;
  for (double z : {1.05, 1.15}) {
    const octomap::OcTreeNode* middle = tree.search(3.5, 4.0, z);
    if (middle == nullptr) continue;
    EXPECT_FALSE(tree.isNodeOccupied(middle)) << "z " << z;
    seen_free = true;
  }
  EXPECT_TRUE(seen_free);
  v1::Belief belief;
  ASSERT_TRUE(readBelief(std::string(kRobot) + "/map_file", &belief).ok());
  EXPECT_EQ(belief.value().string_value(), file);

  // The operators' view of the same map: its occupied voxels at the lidar's
  // height on the channel, room A's wall to room B among them.
  auto latest = channel_->getLatest(std::string("robots/") + kRobot + "/map/occupied");
  ASSERT_TRUE(latest.ok()) << latest.status();
  v1::PointCloud cloud;
  ASSERT_TRUE(latest->sample().UnpackTo(&cloud));
  EXPECT_EQ(cloud.header().frame_id(), "world");
  EXPECT_GT(cloud.points_m_size(), 50);
  bool wall = false;
  for (const auto& p : cloud.points_m()) {
    EXPECT_LT(std::abs(p.z() - 1.1), 0.6) << p.ShortDebugString();
    wall = wall || (std::abs(p.x() - 5.9) < 0.2 && p.y() > 0.5 && p.y() < 3.5);
  }
  EXPECT_TRUE(wall) << "no occupied voxel on room A's wall to room B";
}

TEST_F(NavigationWithLidarTest, ASavePathOutsideTheMapDirectoryIsRefusedNamingIt) {
  v1::ActivateResponse response;
  // Outside --map-dir: absolute, through "..", or through a link.
  std::filesystem::create_directory_symlink("/tmp", *dir_ + "/out");
  for (const std::string& path :
       {std::string("/tmp/map.bt"), std::string("../map.bt"), std::string("out/map.bt")}) {
    grpc::Status status = nav_client_->activate("SAVE_OCCUPANCY_GRID",
                                                "{\"file_path\": \"" + path + "\"}", &response);
    EXPECT_EQ(status.error_code(), grpc::StatusCode::PERMISSION_DENIED) << describe(status);
    EXPECT_NE(status.error_message().find("maps must be inside " + *dir_), std::string::npos)
        << status.error_message();
  }
  // Inside, in a directory that does not exist.
  grpc::Status status = nav_client_->activate(
      "SAVE_OCCUPANCY_GRID", "{\"file_path\": \"nonexistent-dir/map.bt\"}", &response);
  EXPECT_EQ(status.error_code(), grpc::StatusCode::NOT_FOUND) << describe(status);
  EXPECT_NE(status.error_message().find("nonexistent-dir/map.bt"), std::string::npos)
      << status.error_message();
  // The system keeps working.
  EXPECT_TRUE(nav_client_->checkSituation("GENERATE_PATH_WITH_OCCUPANCY_GRID").feasible());
}

// Last: it stops the lidar for a while (and waits until the map is back).
TEST_F(NavigationWithLidarTest, ClearEmptiesTheMapAndMappingStartsAgainFromTheNextScan) {
  // With the lidar stopped, the cleared map stays empty.
  ASSERT_NO_FATAL_FAILURE(injectLidar(v1::FAILURE_TYPE_OFF));
  std::this_thread::sleep_for(milliseconds(300));  // scans in flight are mapped first
  const auto cleared = run("CLEAR_OCCUPANCY_GRID", "{}");
  ASSERT_EQ(cleared.finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED)
      << cleared.ShortDebugString();
  const auto situation = nav_client_->checkSituation("GENERATE_PATH_WITH_OCCUPANCY_GRID");
  EXPECT_FALSE(situation.feasible());
  ASSERT_GT(situation.reasons_size(), 0);
  EXPECT_NE(situation.reasons(0).find("the map is empty"), std::string::npos)
      << situation.ShortDebugString();
  const std::string empty_file = *dir_ + "/cleared.bt";
  ASSERT_EQ(
      run("SAVE_OCCUPANCY_GRID", "{\"file_path\": \"" + empty_file + "\"}").finished().cause(),
      v1::TERMINATION_CAUSE_GOAL_ACHIEVED);
  EXPECT_EQ(occupiedIn(empty_file), 0u);

  // The lidar back: the map builds again.
  ASSERT_NO_FATAL_FAILURE(injectLidar(v1::FAILURE_TYPE_OK));
  ASSERT_TRUE(FlightStack::waitFor(
      [] { return nav_client_->checkSituation("GENERATE_PATH_WITH_OCCUPANCY_GRID").feasible(); }));
  std::this_thread::sleep_for(milliseconds(500));  // 2 s simulated: 20 scans
  const std::string rebuilt_file = *dir_ + "/rebuilt.bt";
  ASSERT_EQ(
      run("SAVE_OCCUPANCY_GRID", "{\"file_path\": \"" + rebuilt_file + "\"}").finished().cause(),
      v1::TERMINATION_CAUSE_GOAL_ACHIEVED);
  EXPECT_GT(occupiedIn(rebuilt_file), 100u);
}

}  // namespace
