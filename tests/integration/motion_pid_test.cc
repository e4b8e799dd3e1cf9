// quadrotor_motion_with_pid_control flown against the real simulator: the
// channel broker, the simulator at 5x (fixed seed), basic_quadrotor_behaviors
// (SELF_LOCALIZE_WITH_GROUND_TRUTH, TAKE_OFF, LAND) and the PID system, each a
// real process on free loopback ports, driven over gRPC. Tracking is measured
// on the simulator's ground truth (Simulator.WatchState); every time is
// simulated time.

#include "motion_test_support.h"

namespace motion_test {
namespace {

// Tolerances, set from the margins over repeated runs (docs/benchmarks.md):
// the issue's bound on the square's RMS cross-track error, the rotation's
// 2 degrees.
constexpr double kMaxRmsCrossTrackM = 0.15;
constexpr double kYawToleranceRad = 2.0 * M_PI / 180.0;
constexpr double kAltitude = 1.5;

class MotionPidTest : public ::testing::Test {
 protected:
  void SetUp() override { startWith(BEHAVIORLIB_PID_CONFIG_PATH); }

  void startWith(const std::string& config) {
    std::string error;
    ASSERT_TRUE(stack_.start(&error)) << error;
    pid_ = stack_.startSystem(BEHAVIORLIB_PID_SYSTEM_PATH, config, &error);
    ASSERT_TRUE(pid_) << error;
    client_ = std::make_unique<SystemClient>(pid_->address());
  }

  void TearDown() override {
    client_.reset();
    if (pid_ && pid_->running()) pid_->kill();
    stack_.stop();
  }

  // The finished event of `activation_id` (fails the test without one).
  v1::BehaviorEvent finished(const std::string& activation_id, milliseconds timeout = seconds(20)) {
    auto event = client_->finished(activation_id, timeout);
    EXPECT_TRUE(event) << activation_id << " did not finish";
    return event.value_or(v1::BehaviorEvent());
  }

  Eigen::Vector3d position() { return stack_.truth().latest().value().position_m; }

  FlightStack stack_;
  std::unique_ptr<support::ServerProcess> pid_;
  std::unique_ptr<SystemClient> client_;
};

TEST_F(MotionPidTest, FollowsA4mSquareWithinTheCrossTrackBoundRotates90DegreesAndLands) {
  ASSERT_NO_FATAL_FAILURE(stack_.localizeAndTakeOff(kAltitude));
  const std::string controller = client_->start("QUADROTOR_PID_MOTION_CONTROL", "{}");
  ASSERT_FALSE(controller.empty());
  EXPECT_EQ(stack_.flightStatus().lease_holder(), "drone1/QUADROTOR_PID_MOTION_CONTROL");

  const Eigen::Vector3d start = position();
  const double z = start.z();
  const std::vector<Eigen::Vector3d> square = {{start.x() + 4, start.y(), z},
                                               {start.x() + 4, start.y() + 4, z},
                                               {start.x(), start.y() + 4, z},
                                               {start.x(), start.y(), z}};
  const std::string path = client_->start("FOLLOW_PATH", pathJson(square));
  ASSERT_FALSE(path.empty());
  const auto done = finished(path, seconds(30));
  ASSERT_EQ(done.finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED)
      << done.ShortDebugString();
  std::vector<Eigen::Vector3d> polyline = {start};
  polyline.insert(polyline.end(), square.begin(), square.end());
  const Tracking t = tracking(stack_.truth(), client_->activated(path).value(), done, polyline);
  std::printf(
      "PID square 4 m at 1 m/s: RMS cross-track %.4f m, max %.4f m, %zu samples, %.1f s "
      "(%s)\n",
      t.rms_m, t.max_m, t.samples, t.duration_s, done.finished().message().c_str());
  EXPECT_GT(t.samples, 1000u) << "ground truth at 100 Hz over about 20 s";
  EXPECT_LE(t.rms_m, kMaxRmsCrossTrackM);
  EXPECT_LE((position() - square.back()).norm(), 0.15) << "ends at the last waypoint";

  // ROTATE 90 degrees (relative) in place; measured on the ground truth.
  const double yaw0 = stack_.truth().latest()->yaw_rad;
  const std::string rotate =
      client_->start("ROTATE_WITH_PID_CONTROL", "{\"yaw_rad\": 1.5707963, \"relative\": true}");
  const auto rotated = finished(rotate);
  ASSERT_EQ(rotated.finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED)
      << rotated.ShortDebugString();
  const double error = wrap(stack_.truth().latest()->yaw_rad - (yaw0 + M_PI / 2));
  std::printf("PID rotate 90 deg: ground-truth error %.3f deg (%s)\n", degrees(error),
              rotated.finished().message().c_str());
  EXPECT_LE(std::abs(error), kYawToleranceRad);

  // KEEP_HOVERING until deactivated: INTERRUPTED.
  const std::string hover = client_->start("KEEP_HOVERING_WITH_PID_CONTROL", "{}");
  stack_.sleepSim(2.0);
  ASSERT_TRUE(client_->deactivate("KEEP_HOVERING_WITH_PID_CONTROL").ok());
  EXPECT_EQ(finished(hover).finished().cause(), v1::TERMINATION_CAUSE_INTERRUPTED);

  // The controller ends (INTERRUPTED), releasing the lease: LAND can take it.
  ASSERT_TRUE(client_->deactivate("QUADROTOR_PID_MOTION_CONTROL").ok());
  EXPECT_EQ(finished(controller).finished().cause(), v1::TERMINATION_CAUSE_INTERRUPTED);
  EXPECT_EQ(stack_.flightStatus().lease_holder(), "");
  ASSERT_NO_FATAL_FAILURE(stack_.land());
}

// FOLLOW_PATH's Modify with a new path_m while it flies at speed: the path is
// taken up from the reference where it is, so the vehicle neither jumps back
// to where the reference restarted nor stops (measured on the ground truth:
// its speed over the second after the change), and it ends on the new path's
// last point. (Before, the new path started from the vehicle's position at
// rest: the vehicle braked to a near stop.)
TEST_F(MotionPidTest, AModifiedPathIsTakenUpWithoutAJumpOrAStop) {
  ASSERT_NO_FATAL_FAILURE(stack_.localizeAndTakeOff(kAltitude));
  ASSERT_FALSE(client_->start("QUADROTOR_PID_MOTION_CONTROL", "{}").empty());
  const Eigen::Vector3d start = position();
  const double z = start.z();
  const std::string path =
      client_->start("FOLLOW_PATH", pathJson({{start.x() + 8, start.y(), z}}, R"("speed_m_s": 1)"));
  ASSERT_FALSE(path.empty());
  ASSERT_TRUE(FlightStack::waitFor([&] { return position().x() >= start.x() + 3; }, seconds(30)))
      << "the vehicle did not get 3 m along the path";
  const double changed_s = stack_.truth().latest()->t_s;
  // The same line further on, then aside.
  const std::vector<Eigen::Vector3d> new_path = {{start.x() + 6, start.y(), z},
                                                 {start.x() + 6, start.y() + 2, z}};
  const grpc::Status modified = client_->modify("FOLLOW_PATH", pathJson(new_path));
  ASSERT_TRUE(modified.ok()) << describe(modified);
  const auto done = finished(path, seconds(30));
  ASSERT_EQ(done.finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED)
      << done.ShortDebugString();
  EXPECT_LE((position() - new_path.back()).norm(), 0.15) << "ends at the new last point";
  // The ground truth's speed over the second after the change (100 Hz).
  const auto around = stack_.truth().between(changed_s, changed_s + 1.0);
  ASSERT_GT(around.size(), 50u);
  double slowest = 1e9;
  for (size_t i = 5; i < around.size(); i += 5) {
    const double dt = around[i].t_s - around[i - 5].t_s;
    if (dt <= 0) continue;
    slowest = std::min(slowest, (around[i].position_m - around[i - 5].position_m).norm() / dt);
  }
  std::printf("FOLLOW_PATH modified at speed: slowest %.2f m/s over the next second (%s)\n",
              slowest, done.finished().message().c_str());
  EXPECT_GE(slowest, 0.7) << "the vehicle slowed down at the change";
}

TEST_F(MotionPidTest, ThrustControlFollowsAPathAndKeepMovingMovesAtTheRequestedVelocity) {
  ASSERT_NO_FATAL_FAILURE(stack_.localizeAndTakeOff(kAltitude));
  const std::string controller = client_->start("QUADROTOR_PID_THRUST_CONTROL", "{}");
  ASSERT_FALSE(controller.empty());
  const Eigen::Vector3d start = position();
  const std::vector<Eigen::Vector3d> line = {{start.x() + 3, start.y() + 1, start.z() + 0.5}};
  const std::string path = client_->start("FOLLOW_PATH", pathJson(line));
  const auto done = finished(path);
  ASSERT_EQ(done.finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED)
      << done.ShortDebugString();
  const Tracking t =
      tracking(stack_.truth(), client_->activated(path).value(), done, {start, line[0]});
  std::printf("PID thrust + rates, 3.2 m line: RMS cross-track %.4f m, max %.4f m\n", t.rms_m,
              t.max_m);
  EXPECT_LE(t.rms_m, kMaxRmsCrossTrackM);

  // KEEP_MOVING east at 0.5 m/s for about 3 s of simulated time.
  const Eigen::Vector3d before = position();
  const std::string moving =
      client_->start("KEEP_MOVING_WITH_PID_CONTROL", "{\"velocity_x_m_s\": 0.5}");
  stack_.sleepSim(3.0);
  ASSERT_TRUE(client_->deactivate("KEEP_MOVING_WITH_PID_CONTROL").ok());
  const auto stopped = finished(moving);
  EXPECT_EQ(stopped.finished().cause(), v1::TERMINATION_CAUSE_INTERRUPTED)
      << stopped.ShortDebugString();
  const Eigen::Vector3d moved = position() - before;
  std::printf("KEEP_MOVING 0.5 m/s east: moved (%.2f, %.2f, %.2f) m\n", moved.x(), moved.y(),
              moved.z());
  EXPECT_GT(moved.x(), 0.5);
  EXPECT_LT(std::abs(moved.y()), 0.2);
  EXPECT_LT(std::abs(moved.z()), 0.2);
  // Without references the controller brakes and holds where the vehicle is.
  stack_.sleepSim(3.0);
  const Eigen::Vector3d held = position();
  stack_.sleepSim(2.0);
  EXPECT_LT((position() - held).norm(), 0.1) << "holding after the references stopped";
  ASSERT_TRUE(client_->deactivate("QUADROTOR_PID_THRUST_CONTROL").ok());
  EXPECT_EQ(finished(controller).finished().cause(), v1::TERMINATION_CAUSE_INTERRUPTED);
}

TEST_F(MotionPidTest, BadInputIsInvalidArgumentNamingTheParameterBeforeAnythingMoves) {
  ASSERT_NO_FATAL_FAILURE(stack_.localizeAndTakeOff(1.0));
  const std::string controller = client_->start("QUADROTOR_PID_MOTION_CONTROL", "{}");
  ASSERT_FALSE(controller.empty());
  stack_.sleepSim(1.0);
  const Eigen::Vector3d before = position();
  struct Case {
    std::string json, names;
  };
  const std::vector<Case> cases = {
      {"{\"path_m\": []}", "path_m"},
      {"{}", "path_m"},
      {pathJson({{1, 0, 1}, {1, 0, 0.05}}), "path_m[1]"},
      {pathJson({{1, 0, 1}, {1500, 0, 1}}), "path_m"},
      {pathJson({{1, 0, 1}}, "\"speed_m_s\": 50"), "speed_m_s"},
      {pathJson({{1, 0, 1}}, "\"sped_m_s\": 1"), "sped_m_s"},
  };
  for (const auto& c : cases) {
    v1::ActivateResponse response;
    const grpc::Status status = client_->activate("FOLLOW_PATH", c.json, &response);
    EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT)
        << c.json << ": " << describe(status);
    EXPECT_NE(status.error_message().find(c.names), std::string::npos)
        << c.json << ": " << describe(status);
  }
  // A NaN coordinate (JSON cannot carry it: a Struct built in code).
  v1::ActivateResponse response;
  const grpc::Status nan =
      client_->activate("FOLLOW_PATH", pathStruct({{1, 0, 1}, {2, std::nan(""), 1}}), &response);
  EXPECT_EQ(nan.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << describe(nan);
  EXPECT_NE(nan.error_message().find("path_m[1]"), std::string::npos) << describe(nan);
  auto status = client_->activate("ROTATE_WITH_PID_CONTROL", "{\"yaw_rad\": 9}", &response);
  EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << describe(status);
  EXPECT_NE(status.error_message().find("yaw_rad"), std::string::npos) << describe(status);
  status = client_->activate("QUADROTOR_PID_THRUST_CONTROL", "{\"max_tilt_rad\": 2}", &response);
  EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << describe(status);
  EXPECT_NE(status.error_message().find("max_tilt_rad"), std::string::npos) << describe(status);
  // Nothing moved: the controller still holds where it started.
  stack_.sleepSim(2.0);
  EXPECT_LT((position() - before).norm(), 0.1);
  EXPECT_EQ(stack_.flightStatus().lease_holder(), "drone1/QUADROTOR_PID_MOTION_CONTROL")
      << client_->finished(controller, milliseconds(0))
             .value_or(v1::BehaviorEvent())
             .ShortDebugString();
}

TEST_F(MotionPidTest, ProvokedCausesAreTheOnesReported) {
  ASSERT_NO_FATAL_FAILURE(stack_.localizeAndTakeOff(kAltitude));

  // Without a motion controller, FOLLOW_PATH's references are followed by
  // nobody: PROCESS_FAILURE after the grace, naming what to activate.
  const Eigen::Vector3d start = position();
  const std::vector<Eigen::Vector3d> line = {{start.x() + 6, start.y(), start.z()}};
  std::string path = client_->start("FOLLOW_PATH", pathJson(line));
  auto event = finished(path);
  EXPECT_EQ(event.finished().cause(), v1::TERMINATION_CAUSE_PROCESS_FAILURE)
      << event.ShortDebugString();
  EXPECT_NE(event.finished().message().find("QUADROTOR_PID_MOTION_CONTROL"), std::string::npos)
      << event.finished().message();

  // A controller limited to 5 cm/s cannot keep up with a 1 m/s path: the
  // reference waits, the lag stays: WRONG_PROGRESS.
  std::string controller =
      client_->start("QUADROTOR_PID_MOTION_CONTROL", "{\"max_horizontal_speed_m_s\": 0.05}");
  path = client_->start("FOLLOW_PATH", pathJson(line));
  event = finished(path);
  EXPECT_EQ(event.finished().cause(), v1::TERMINATION_CAUSE_WRONG_PROGRESS)
      << event.ShortDebugString();
  std::printf("slow controller: FOLLOW_PATH %s\n", event.finished().message().c_str());
  ASSERT_TRUE(client_->deactivate("QUADROTOR_PID_MOTION_CONTROL").ok());
  ASSERT_TRUE(client_->finished(controller));

  // The controller deactivated while FOLLOW_PATH runs: PROCESS_FAILURE (no
  // controller follows any more); the platform hovers (lease released).
  controller = client_->start("QUADROTOR_PID_MOTION_CONTROL", "{}");
  path = client_->start("FOLLOW_PATH", pathJson({{start.x(), start.y() + 5, start.z()}}));
  stack_.sleepSim(2.0);
  ASSERT_TRUE(client_->deactivate("QUADROTOR_PID_MOTION_CONTROL").ok());
  event = finished(path);
  EXPECT_EQ(event.finished().cause(), v1::TERMINATION_CAUSE_PROCESS_FAILURE)
      << event.ShortDebugString();
  EXPECT_NE(event.finished().message().find("stopped"), std::string::npos)
      << event.finished().message();
  EXPECT_EQ(stack_.flightStatus().state(), v1::FLIGHT_STATE_HOVERING);

  // The pose stream freezes (the localization is deactivated): the
  // controller and KEEP_HOVERING end with PROCESS_FAILURE.
  controller = client_->start("QUADROTOR_PID_MOTION_CONTROL", "{}");
  const std::string hover = client_->start("KEEP_HOVERING_WITH_PID_CONTROL", "{}");
  stack_.sleepSim(2.0);
  ASSERT_TRUE(stack_.basic().deactivate("SELF_LOCALIZE_WITH_GROUND_TRUTH").ok());
  event = finished(controller);
  EXPECT_EQ(event.finished().cause(), v1::TERMINATION_CAUSE_PROCESS_FAILURE)
      << event.ShortDebugString();
  EXPECT_NE(event.finished().message().find("estimate"), std::string::npos)
      << event.finished().message();
  event = finished(hover);
  EXPECT_EQ(event.finished().cause(), v1::TERMINATION_CAUSE_PROCESS_FAILURE)
      << event.ShortDebugString();
  EXPECT_TRUE(FlightStack::waitFor([&] { return stack_.flightStatus().lease_holder().empty(); },
                                   seconds(5)))
      << "the failed controller released the lease";
}

TEST(MotionPidTimeOutTest, ATinyMaximumExecutionTimeIsATimeOut) {
  // The shipped configuration with ROTATE_WITH_PID_CONTROL limited to 0.5 s.
  std::string config = readFile(BEHAVIORLIB_PID_CONFIG_PATH);
  const std::string from =
      "  ROTATE_WITH_PID_CONTROL:\n    frequency_hz: 50\n    maximum_execution_time_s: 60";
  const size_t at = config.find(from);
  ASSERT_NE(at, std::string::npos);
  config.replace(
      at, from.size(),
      "  ROTATE_WITH_PID_CONTROL:\n    frequency_hz: 50\n    maximum_execution_time_s: 0.5");
  const std::string path = writeTempFile("motion_pid_time_out.yaml", config);

  FlightStack stack;
  std::string error;
  ASSERT_TRUE(stack.start(&error)) << error;
  auto pid = stack.startSystem(BEHAVIORLIB_PID_SYSTEM_PATH, path, &error);
  ASSERT_TRUE(pid) << error;
  SystemClient client(pid->address());
  ASSERT_NO_FATAL_FAILURE(stack.localizeAndTakeOff(1.0));
  ASSERT_FALSE(client.start("QUADROTOR_PID_MOTION_CONTROL", "{}").empty());
  const std::string rotate = client.start("ROTATE_WITH_PID_CONTROL", "{\"yaw_rad\": 3}");
  const auto event = client.finished(rotate);
  ASSERT_TRUE(event);
  EXPECT_EQ(event->finished().cause(), v1::TERMINATION_CAUSE_TIME_OUT) << event->ShortDebugString();
  const double active =
      static_cast<double>(TimeUtil::DurationToMilliseconds(event->finished().active_duration())) /
      1e3;
  EXPECT_GE(active, 0.5);
  EXPECT_LT(active, 1.0) << "simulated time";

  // An orderly shutdown with a controller active: it ends INTERRUPTED and
  // releases the lease; the process exits 0.
  const auto t0 = WallClock::now();
  EXPECT_EQ(pid->terminate(), 0);
  std::printf("quadrotor_motion_with_pid_control: SIGTERM to exit %.2f s (wall)\n",
              std::chrono::duration<double>(WallClock::now() - t0).count());
  EXPECT_TRUE(FlightStack::waitFor([&] { return stack.flightStatus().lease_holder().empty(); },
                                   seconds(5)));
  stack.stop();
}

}  // namespace
}  // namespace motion_test
