// SELF_LOCALIZE_AND_MAP_WITH_LIDAR against real processes: the channel
// broker, the simulator in the deterministic mode (decision 18) with its
// default sensors and noise, and navigation_with_lidar following its time
// grants. The test flies the vehicle through the FlightController itself
// (velocity setpoints steered by the ground truth, so that the flight does
// not depend on the estimate under test) from room A through the doors of
// rooms B and C into room D, and compares the estimate published on
// robots/{id}/self_localization/pose with the ground truth, stamp by stamp:
// horizontal position and heading. Then the same with the lidar's noise
// multiplied by the NOISY fault; a silent lidar (PROCESS_FAILURE), no lidar
// at all (refused), and the open field, where the scans see nothing to
// match (WRONG_PROGRESS).
//
// On the SLAM's poses, GENERATE_PATH_WITH_OCCUPANCY_GRID is asked at
// take-off for a goal in room D, not yet seen: it waits for the map and
// plans once the flight has shown the way. From room D, a vehicle of
// radius 0.35 m then has a path out of the building through every door:
// on the map built with the SLAM's poses, and with the EKF's
// (SELF_LOCALIZE_WITH_EKF_SENSOR_FUSION of multi_sensor_fusion: GPS, IMU,
// barometer).

#include <google/protobuf/util/time_util.h>
#include <gtest/gtest.h>

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <functional>
#include <map>
#include <mutex>
#include <numbers>
#include <optional>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "behaviorlib/channel/channel_client.h"
#include "behaviorlib/v1/types.pb.h"
#include "motion_test_support.h"
#include "pose_tracks.h"
#include "sim_faults.h"

namespace {

using namespace motion_test;

constexpr char kBehavior[] = "SELF_LOCALIZE_AND_MAP_WITH_LIDAR";
constexpr double kAltitude = 1.2;
constexpr double kSpeed = 0.5;
constexpr char kPlanner[] = "GENERATE_PATH_WITH_OCCUPANCY_GRID";
constexpr char kEkf[] = "SELF_LOCALIZE_WITH_EKF_SENSOR_FUSION";
constexpr double kVehicleRadius = 0.35;

// The doors of simulator/worlds/rooms.yaml: the ends of each opening.
struct Door {
  const char* name;
  std::array<double, 2> a, b;
};
constexpr std::array<Door, 4> kDoors = {{{"entrance", {2.4, 0.0}, {3.6, 0.0}},
                                         {"A-B", {6.0, 4.4}, {6.0, 5.6}},
                                         {"B-C", {12.0, 1.9}, {12.0, 3.1}},
                                         {"C-D", {14.4, 5.0}, {15.6, 5.0}}}};

// Whether the segments p-q and a-b cross (2-D).
bool crosses(const std::array<double, 2>& p, const std::array<double, 2>& q,
             const std::array<double, 2>& a, const std::array<double, 2>& b) {
  const auto side = [](const std::array<double, 2>& o, const std::array<double, 2>& u,
                       const std::array<double, 2>& v) {
    return (u[0] - o[0]) * (v[1] - o[1]) - (u[1] - o[1]) * (v[0] - o[0]);
  };
  return side(p, q, a) * side(p, q, b) <= 0 && side(a, b, p) * side(a, b, q) <= 0;
}

using pose_tracks::Track;

struct Errors {
  int samples = 0;
  double horizontal_rmse_m = 0, horizontal_max_m = 0, yaw_rmse_deg = 0, z_rmse_m = 0;
};

// Each estimate against the ground truth at its stamp (interpolated between
// the neighbouring 100 Hz samples), from `from_ns` on.
Errors compare(const Track& truth, const Track& estimate, int64_t from_ns) {
  const auto t = truth.points();
  const auto e = estimate.points();
  Errors out;
  double h2 = 0, y2 = 0, z2 = 0;
  for (const auto& [stamp, p] : e) {
    if (stamp < from_ns) continue;
    auto hi = t.lower_bound(stamp);
    if (hi == t.end() || hi == t.begin()) continue;
    auto lo = std::prev(hi);
    if (hi->first - lo->first > 50'000'000) continue;
    const double w =
        static_cast<double>(stamp - lo->first) / static_cast<double>(hi->first - lo->first);
    std::array<double, 4> truth_at{};
    for (int i = 0; i < 3; ++i) truth_at[i] = (1 - w) * lo->second[i] + w * hi->second[i];
    truth_at[3] = lo->second[3] + w * wrap(hi->second[3] - lo->second[3]);
    const double h = std::hypot(p[0] - truth_at[0], p[1] - truth_at[1]);
    h2 += h * h;
    out.horizontal_max_m = std::max(out.horizontal_max_m, h);
    z2 += (p[2] - truth_at[2]) * (p[2] - truth_at[2]);
    const double dy = wrap(p[3] - truth_at[3]);
    y2 += dy * dy;
    ++out.samples;
  }
  if (out.samples == 0) return out;
  out.horizontal_rmse_m = std::sqrt(h2 / out.samples);
  out.z_rmse_m = std::sqrt(z2 / out.samples);
  out.yaw_rmse_deg = std::sqrt(y2 / out.samples) * 180.0 / std::numbers::pi;
  return out;
}

class LidarSlamSystemTest : public ::testing::Test {
 protected:
  // With `ekf`, multi_sensor_fusion too: its EKF localizes, not the SLAM.
  void startStack(const std::string& world, bool ekf = false) {
    ASSERT_TRUE(broker_.start()) << broker_.error();
    std::vector<std::string> args = {
        "--channel", broker_.address(),         "--world", world, "--seed",
        "7",         "--enable-fault-injection"};
    simulator_ = std::make_unique<support::ServerProcess>(
        BEHAVIORLIB_SIMULATOR_PATH, support::deterministicSimulatorArgs(args, ekf ? 2 : 1));
    ASSERT_TRUE(simulator_->start()) << simulator_->error();
    if (ekf) {
      fusion_ = std::make_unique<support::ServerProcess>(
          BEHAVIORLIB_MULTI_SENSOR_FUSION_PATH,
          support::followTimeArgs({"--robot-id", kRobot, "--channel", broker_.address(), "--clock",
                                   "sim", "--config", BEHAVIORLIB_FUSION_CONFIG_PATH},
                                  simulator_->address()));
      ASSERT_TRUE(fusion_->start()) << fusion_->error();
      fusion_client_ = std::make_unique<SystemClient>(fusion_->address());
    }
    system_ = std::make_unique<support::ServerProcess>(
        BEHAVIORLIB_NAVIGATION_WITH_LIDAR_PATH,
        support::followTimeArgs({"--robot-id", kRobot, "--channel", broker_.address(), "--clock",
                                 "sim", "--config", BEHAVIORLIB_NAVIGATION_CONFIG_PATH},
                                simulator_->address()));
    ASSERT_TRUE(system_->start()) << system_->error();
    system_client_ = std::make_unique<SystemClient>(system_->address());
    pilot_ = std::make_unique<Pilot>(simulator_->address());
    channel_ = std::make_unique<behaviorlib::channel::ChannelClient>(broker_.address());
  }

  void TearDown() override {
    tracks_.stop();
    system_client_.reset();
    fusion_client_.reset();
    if (system_ && system_->running()) system_->kill();
    if (fusion_ && fusion_->running()) fusion_->kill();
  }

  // Activates the behavior once its sensors are on the channel (simulated
  // time starts once the system joined); its activation id.
  std::string activate(const std::string& json) {
    EXPECT_TRUE(FlightStack::waitFor([&] { return checkSituation().feasible(); }, seconds(10)))
        << checkSituation().ShortDebugString();
    return system_client_->start(kBehavior, json);
  }

  v1::CheckSituationResponse checkSituation() { return system_client_->checkSituation(kBehavior); }

  // Flies through `waypoints` at kSpeed, steering on the newest ground
  // truth (every few milliseconds of wall time; simulated time runs as fast
  // as the stack keeps up). Returns the first stamp of the flight.
  int64_t fly(const std::vector<std::array<double, 2>>& waypoints, seconds wall_limit) {
    const auto wall_start = std::chrono::steady_clock::now();
    int64_t first = -1;
    size_t next = 0;
    while (next < waypoints.size()) {
      EXPECT_LT(std::chrono::steady_clock::now() - wall_start, wall_limit)
          << "reached " << next << " of " << waypoints.size() << " waypoints";
      if (std::chrono::steady_clock::now() - wall_start >= wall_limit) break;
      const auto now = tracks_.truth.newest();
      if (!now) {
        std::this_thread::sleep_for(milliseconds(5));
        continue;
      }
      if (first < 0) first = now->first;
      const auto& p = now->second;
      const double dx = waypoints[next][0] - p[0], dy = waypoints[next][1] - p[1];
      const double d = std::hypot(dx, dy);
      if (d < 0.15) {
        ++next;
        continue;
      }
      const double v = std::min(kSpeed, d);  // slow down into the last metre
      pilot_->setVelocity(v * dx / d, v * dy / d, 1.0 * (kAltitude - p[2]));
      std::this_thread::sleep_for(milliseconds(5));
    }
    pilot_->setVelocity(0, 0, 0);
    return first;
  }

  void flyWithANoisyLidar(double intensity);
  void injectLidar(v1::FailureType type, double intensity = 0.0) {
    auto simulator = v1::Simulator::NewStub(
        grpc::CreateChannel(simulator_->address(), grpc::InsecureChannelCredentials()));
    v1::InjectFailureRequest request;
    request.set_robot_id(kRobot);
    request.set_component(v1::FAILURE_COMPONENT_LIDAR);
    request.set_type(type);
    request.set_intensity(intensity);
    v1::InjectFailureResponse response;
    const grpc::Status status = simulator->InjectFailure(deadline().get(), request, &response);
    ASSERT_TRUE(status.ok()) << status.error_message();
  }

  // Room A to room D through the doors (simulator/worlds/rooms.yaml), at
  // least 0.5 m from every wall but in the doors themselves.
  static std::vector<std::array<double, 2>> throughTheBuilding() {
    return {{3.0, 4.0},  {5.0, 5.0},  {7.0, 5.0},  {9.0, 3.5},  {11.0, 2.5},
            {13.0, 2.5}, {14.5, 3.0}, {15.0, 4.2}, {15.0, 5.8}, {14.0, 8.5}};
  }

  // GENERATE_PATH_WITH_OCCUPANCY_GRID to `goal` at flight height, for a
  // vehicle of kVehicleRadius; its activation id.
  std::string planTo(double x, double y, double map_wait_s) {
    EXPECT_TRUE(FlightStack::waitFor([&] {
      return system_client_->checkSituation(kPlanner).feasible();
    })) << system_client_->checkSituation(kPlanner).ShortDebugString();
    std::ostringstream json;
    json << R"({"goal_m": {"x": )" << x << R"(, "y": )" << y << R"(, "z": )" << kAltitude
         << R"(}, "vehicle_radius_m": )" << kVehicleRadius << R"(, "map_wait_s": )" << map_wait_s
         << "}";
    return system_client_->start(kPlanner, json.str());
  }

  // Starts at the take-off point, flies through the building, compares.
  // `airborne` runs once the vehicle has taken off.
  Errors flyThroughTheBuilding(const std::function<void()>& airborne = {}) {
    SystemClient& localizer = fusion_client_ ? *fusion_client_ : *system_client_;
    std::string id;
    if (fusion_client_) {
      EXPECT_TRUE(FlightStack::waitFor([&] { return localizer.checkSituation(kEkf).feasible(); },
                                       seconds(10)))
          << localizer.checkSituation(kEkf).ShortDebugString();
      id = localizer.start(kEkf, "{}");
    } else {
      id = activate(R"({"initial_position_m": {"x": 2.0, "y": 2.0, "z": 0.0},
                        "initial_yaw_rad": 0.0})");
    }
    EXPECT_FALSE(id.empty());
    EXPECT_NO_FATAL_FAILURE(tracks_.record(*channel_, kRobot));
    pilot_->takeOff(kAltitude);
    if (airborne) airborne();
    const int64_t first = fly(throughTheBuilding(), seconds(150));
    tracks_.stop();
    const auto ended = localizer.finished(id, milliseconds(0));
    EXPECT_FALSE(ended.has_value()) << "the behavior ended during the flight: "
                                    << ended.value_or(v1::BehaviorEvent()).ShortDebugString();
    return compare(tracks_.truth, tracks_.estimate, first);
  }

  // From where the vehicle is (room D), a path out of the building's
  // entrance for a vehicle of kVehicleRadius, through every door.
  void expectAPathOutThroughEveryDoor(double map_wait_s) {
    std::mutex mutex;
    std::optional<v1::Path> path;
    auto sub = channel_->subscribeTyped<v1::Path>(
        std::string("robots/") + kRobot + "/navigation/path", {}, [&](const v1::Path& p) {
          std::lock_guard lock(mutex);
          path = p;
        });
    ASSERT_TRUE(sub->waitConnected(seconds(5)));
    const std::string out = planTo(3.0, -1.5, map_wait_s);
    ASSERT_FALSE(out.empty());
    const auto planned = system_client_->finished(out, seconds(30));
    ASSERT_TRUE(planned.has_value());
    ASSERT_EQ(planned->finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED)
        << planned->ShortDebugString();
    std::printf("out of the building: %s\n", planned->finished().message().c_str());
    EXPECT_NE(planned->finished().message().find("for the pose estimate's uncertainty"),
              std::string::npos)
        << "the estimator reports its uncertainty: " << planned->finished().message();
    ASSERT_TRUE(FlightStack::waitFor([&] {
      std::lock_guard lock(mutex);
      return path.has_value();
    }));
    std::lock_guard lock(mutex);
    for (const Door& door : kDoors) {
      bool through = false;
      for (int i = 1; i < path->poses_size(); ++i) {
        const auto& p = path->poses(i - 1).position_m();
        const auto& q = path->poses(i).position_m();
        through = through || crosses({p.x(), p.y()}, {q.x(), q.y()}, door.a, door.b);
      }
      EXPECT_TRUE(through) << "the path out does not pass the door " << door.name << ": "
                           << path->ShortDebugString();
    }
  }

  support::ServerProcess broker_{BEHAVIORLIB_CHANNEL_BROKER_PATH, {}};
  std::unique_ptr<support::ServerProcess> simulator_, system_, fusion_;
  std::unique_ptr<SystemClient> system_client_, fusion_client_;
  std::unique_ptr<Pilot> pilot_;
  std::unique_ptr<behaviorlib::channel::ChannelClient> channel_;
  pose_tracks::PoseTracks tracks_;
};

TEST_F(LidarSlamSystemTest, LocalizesThroughTheBuildingWithinTenCentimetresAndTwoDegrees) {
  ASSERT_NO_FATAL_FAILURE(startStack("rooms"));
  // Room D, beyond the map at take-off (the lidar sees room B through its
  // door, no further east than the wall at x = 12): the planner waits.
  std::string to_room_d;
  const Errors e = flyThroughTheBuilding([&] { to_room_d = planTo(14.0, 8.5, 200.0); });
  std::printf(
      "lidar SLAM over %d estimates: horizontal RMSE %.3f m (max %.3f m), yaw RMSE %.2f "
      "deg, z RMSE %.3f m\n",
      e.samples, e.horizontal_rmse_m, e.horizontal_max_m, e.yaw_rmse_deg, e.z_rmse_m);
  EXPECT_GT(e.samples, 2000) << "the estimate is published at 100 Hz of simulated time";
  EXPECT_LE(e.horizontal_rmse_m, 0.10);
  EXPECT_LE(e.yaw_rmse_deg, 2.0);

  ASSERT_FALSE(to_room_d.empty());
  const auto planned_d = system_client_->finished(to_room_d, seconds(10));
  ASSERT_TRUE(planned_d.has_value());
  EXPECT_EQ(planned_d->finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED)
      << planned_d->ShortDebugString();
  EXPECT_NE(planned_d->finished().message().find("after waiting"), std::string::npos)
      << planned_d->finished().message();
  std::printf("to room D: %s\n", planned_d->finished().message().c_str());
  expectAPathOutThroughEveryDoor(0.0);
}

TEST_F(LidarSlamSystemTest, EveryDoorStaysPassableOnTheEkfsPoses) {
  ASSERT_NO_FATAL_FAILURE(startStack("rooms", /*ekf=*/true));
  const Errors e = flyThroughTheBuilding();
  std::printf(
      "EKF (GPS, IMU, barometer) over %d estimates: horizontal RMSE %.3f m (max %.3f m), yaw "
      "RMSE %.2f deg\n",
      e.samples, e.horizontal_rmse_m, e.horizontal_max_m, e.yaw_rmse_deg);
  // The map smeared by GPS-grade poses: a few seconds of the hovering
  // vehicle's scans may be needed to clear a door.
  expectAPathOutThroughEveryDoor(10.0);
}

// The lidar's NOISY fault multiplies its range noise's standard deviation
// (1 cm configured) by 1 + 20 intensity.
void LidarSlamSystemTest::flyWithANoisyLidar(double intensity) {
  ASSERT_NO_FATAL_FAILURE(startStack("rooms"));
  ASSERT_NO_FATAL_FAILURE(injectLidar(v1::FAILURE_TYPE_NOISY, intensity));
  const Errors e = flyThroughTheBuilding();
  std::printf(
      "lidar SLAM, lidar NOISY at %.2f (x%.0f), over %d estimates: horizontal RMSE %.3f m (max "
      "%.3f m), yaw RMSE %.2f deg, z RMSE %.3f m\n",
      intensity, 1 + 20 * intensity, e.samples, e.horizontal_rmse_m, e.horizontal_max_m,
      e.yaw_rmse_deg, e.z_rmse_m);
  EXPECT_GT(e.samples, 2000);
  EXPECT_LE(e.horizontal_rmse_m, 0.10);
  EXPECT_LE(e.yaw_rmse_deg, 2.0);
}

TEST_F(LidarSlamSystemTest, LocalizesWithTheLidarsNoiseMultiplied) { flyWithANoisyLidar(0.1); }

// Six times the noise: a wall is a band as thick as the building's walls.
// (At 0.5, eleven times, matching becomes degenerate within the flight and
// the behavior ends WRONG_PROGRESS, as its monitoring should.)
TEST_F(LidarSlamSystemTest, LocalizesWithTheLidarsNoiseMultipliedSixTimes) {
  flyWithANoisyLidar(0.25);
}

TEST_F(LidarSlamSystemTest, NoLidarIsRefusedAndASilentLidarIsAProcessFailure) {
  ASSERT_NO_FATAL_FAILURE(startStack("rooms"));
  const std::string id = activate("{}");
  ASSERT_FALSE(id.empty());
  std::this_thread::sleep_for(milliseconds(500));
  ASSERT_NO_FATAL_FAILURE(injectLidar(v1::FAILURE_TYPE_OFF));
  auto finished = system_client_->finished(id, seconds(20));
  ASSERT_TRUE(finished.has_value());
  EXPECT_EQ(finished->finished().cause(), v1::TERMINATION_CAUSE_PROCESS_FAILURE)
      << finished->ShortDebugString();
  EXPECT_NE(finished->finished().message().find("lidar"), std::string::npos)
      << finished->finished().message();
  EXPECT_NE(finished->finished().message().find("silent"), std::string::npos)
      << finished->finished().message();
  // With the lidar still off, the behavior refuses to start once its last
  // scan is stale (simulated time runs on while nothing is active).
  v1::CheckSituationResponse situation;
  const auto until = std::chrono::steady_clock::now() + seconds(20);
  do {
    situation = checkSituation();
    if (!situation.feasible()) break;
    std::this_thread::sleep_for(milliseconds(50));
  } while (std::chrono::steady_clock::now() < until);
  EXPECT_FALSE(situation.feasible());
  ASSERT_GT(situation.reasons_size(), 0);
  EXPECT_NE(situation.reasons(0).find("no lidar"), std::string::npos) << situation.reasons(0);
  v1::ActivateResponse response;
  const grpc::Status refused = system_client_->activate(kBehavior, "{}", &response);
  EXPECT_EQ(refused.error_code(), grpc::StatusCode::FAILED_PRECONDITION) << refused.error_message();
  EXPECT_NE(refused.error_message().find("no lidar"), std::string::npos) << refused.error_message();
}

TEST_F(LidarSlamSystemTest, TheOpenFieldIsWrongProgress) {
  // Nothing within the lidar's range: no scan has a point to match.
  ASSERT_NO_FATAL_FAILURE(startStack("empty_field"));
  const std::string id = activate("{}");
  ASSERT_FALSE(id.empty());
  ASSERT_NO_FATAL_FAILURE(pilot_->takeOff(kAltitude));
  auto finished = system_client_->finished(id, seconds(40));
  ASSERT_TRUE(finished.has_value());
  EXPECT_EQ(finished->finished().cause(), v1::TERMINATION_CAUSE_WRONG_PROGRESS)
      << finished->ShortDebugString();
  EXPECT_NE(finished->finished().message().find("degenerate"), std::string::npos)
      << finished->finished().message();
}

}  // namespace
