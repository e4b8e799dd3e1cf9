// quadrotor_motion_with_platform_control flown against the real simulator (the
// broker, the simulator at 5x with a fixed seed, basic_quadrotor_behaviors,
// and the platform-control system), driven over gRPC; results checked on the
// simulator's ground truth in simulated time.

#include "motion_test_support.h"

namespace motion_test {
namespace {

constexpr double kYawToleranceRad = 2.0 * M_PI / 180.0;

class MotionPlatformTest : public ::testing::Test {
 protected:
  void SetUp() override {
    std::string error;
    ASSERT_TRUE(stack_.start(&error)) << error;
    system_ = stack_.startSystem(BEHAVIORLIB_PLATFORM_SYSTEM_PATH, BEHAVIORLIB_PLATFORM_CONFIG_PATH,
                                 &error);
    ASSERT_TRUE(system_) << error;
    client_ = std::make_unique<SystemClient>(system_->address());
  }

  void TearDown() override {
    client_.reset();
    if (system_ && system_->running()) system_->kill();
    stack_.stop();
  }

  v1::BehaviorEvent finished(const std::string& activation_id, milliseconds timeout = seconds(20)) {
    auto event = client_->finished(activation_id, timeout);
    EXPECT_TRUE(event) << activation_id << " did not finish";
    return event.value_or(v1::BehaviorEvent());
  }

  TruthSample truth() { return stack_.truth().latest().value(); }

  FlightStack stack_;
  std::unique_ptr<support::ServerProcess> system_;
  std::unique_ptr<SystemClient> client_;
};

TEST_F(MotionPlatformTest, MovesVerticallyRotatesMovesAtSpeedAndLands) {
  ASSERT_NO_FATAL_FAILURE(stack_.localizeAndTakeOff(1.0));

  // To an altitude, then by a distance.
  const Eigen::Vector3d start = truth().position_m;
  std::string id = client_->start("MOVE_VERTICAL_WITH_PLATFORM_CONTROL", "{\"altitude_m\": 2.5}");
  auto event = finished(id);
  ASSERT_EQ(event.finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED)
      << event.ShortDebugString();
  EXPECT_NEAR(truth().position_m.z(), 2.5, 0.1);
  EXPECT_LT((truth().position_m - start).head<2>().norm(), 0.2) << "held its horizontal position";
  std::printf(
      "MOVE_VERTICAL to 2.5 m: ground truth %.3f m in %.2f s (%s)\n", truth().position_m.z(),
      static_cast<double>(TimeUtil::DurationToMilliseconds(event.finished().active_duration())) /
          1e3,
      event.finished().message().c_str());
  EXPECT_EQ(stack_.flightStatus().lease_holder(), "") << "released when it ended";
  id = client_->start("MOVE_VERTICAL_WITH_PLATFORM_CONTROL", "{\"distance_m\": -1.0}");
  event = finished(id);
  ASSERT_EQ(event.finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED)
      << event.ShortDebugString();
  EXPECT_NEAR(truth().position_m.z(), 1.5, 0.1);

  // ROTATE 90 degrees.
  const double yaw0 = truth().yaw_rad;
  id = client_->start("ROTATE_WITH_PLATFORM_CONTROL",
                      "{\"yaw_rad\": " + std::to_string(wrap(yaw0 + M_PI / 2)) + "}");
  event = finished(id);
  ASSERT_EQ(event.finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED)
      << event.ShortDebugString();
  const double error = wrap(truth().yaw_rad - (yaw0 + M_PI / 2));
  std::printf("ROTATE_WITH_PLATFORM_CONTROL 90 deg: ground-truth error %.3f deg\n", degrees(error));
  EXPECT_LE(std::abs(error), kYawToleranceRad);

  // MOVE_AT_SPEED north at 0.5 m/s for 2 s: GOAL_ACHIEVED, about 1 m.
  const Eigen::Vector3d before = truth().position_m;
  id = client_->start("MOVE_AT_SPEED_WITH_PLATFORM_CONTROL",
                      "{\"velocity_y_m_s\": 0.5, \"duration_s\": 2}");
  event = finished(id);
  ASSERT_EQ(event.finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED)
      << event.ShortDebugString();
  stack_.sleepSim(2.0);  // it stops and hovers
  const Eigen::Vector3d moved = truth().position_m - before;
  std::printf("MOVE_AT_SPEED 0.5 m/s north for 2 s: moved (%.2f, %.2f, %.2f) m\n", moved.x(),
              moved.y(), moved.z());
  EXPECT_GT(moved.y(), 0.6);
  EXPECT_LT(moved.y(), 1.5);
  EXPECT_LT(std::abs(moved.x()), 0.2);
  EXPECT_EQ(stack_.flightStatus().state(), v1::FLIGHT_STATE_HOVERING);

  // Until deactivated: INTERRUPTED; the vehicle hovers.
  id = client_->start("MOVE_AT_SPEED_WITH_PLATFORM_CONTROL", "{\"velocity_x_m_s\": -0.3}");
  stack_.sleepSim(2.0);
  ASSERT_TRUE(client_->deactivate("MOVE_AT_SPEED_WITH_PLATFORM_CONTROL").ok());
  EXPECT_EQ(finished(id).finished().cause(), v1::TERMINATION_CAUSE_INTERRUPTED);
  EXPECT_EQ(stack_.flightStatus().lease_holder(), "");
  ASSERT_NO_FATAL_FAILURE(stack_.land());

  // Landed: the behaviors say why they cannot run.
  const auto situation = client_->checkSituation("MOVE_VERTICAL_WITH_PLATFORM_CONTROL");
  EXPECT_FALSE(situation.feasible());
  ASSERT_GT(situation.reasons_size(), 0);
  EXPECT_NE(situation.reasons(0).find("LANDED"), std::string::npos) << situation.reasons(0);

  // SIGTERM: the process exits 0 (the time it takes is printed).
  const auto t0 = WallClock::now();
  EXPECT_EQ(system_->terminate(), 0);
  std::printf("quadrotor_motion_with_platform_control: SIGTERM to exit %.2f s (wall)\n",
              std::chrono::duration<double>(WallClock::now() - t0).count());
}

TEST_F(MotionPlatformTest, BadInputAndProvokedCauses) {
  ASSERT_NO_FATAL_FAILURE(stack_.localizeAndTakeOff(1.0));
  struct Case {
    std::string behavior, json, names;
  };
  const std::vector<Case> cases = {
      {"MOVE_VERTICAL_WITH_PLATFORM_CONTROL", "{}", "altitude_m"},
      {"MOVE_VERTICAL_WITH_PLATFORM_CONTROL", "{\"altitude_m\": 2, \"distance_m\": 1}",
       "distance_m"},
      {"MOVE_VERTICAL_WITH_PLATFORM_CONTROL", "{\"altitude_m\": 500}", "altitude_m"},
      {"MOVE_VERTICAL_WITH_PLATFORM_CONTROL", "{\"distance_m\": -5}", "distance_m"},
      {"MOVE_AT_SPEED_WITH_PLATFORM_CONTROL", "{\"velocity_x_m_s\": 9}", "velocity_x_m_s"},
      {"ROTATE_WITH_PLATFORM_CONTROL", "{\"relative\": true}", "yaw_rad"},
  };
  for (const auto& c : cases) {
    v1::ActivateResponse response;
    const grpc::Status status = client_->activate(c.behavior, c.json, &response);
    EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT)
        << c.behavior << " " << c.json << ": " << describe(status);
    EXPECT_NE(status.error_message().find(c.names), std::string::npos)
        << c.behavior << " " << c.json << ": " << describe(status);
  }
  EXPECT_EQ(stack_.flightStatus().lease_holder(), "") << "nothing took the lease";

  // The pose stream freezes (the localization is deactivated) while moving
  // up: PROCESS_FAILURE, and the platform hovers.
  std::string id = client_->start("MOVE_VERTICAL_WITH_PLATFORM_CONTROL",
                                  "{\"altitude_m\": 5, \"speed_m_s\": 0.3}");
  stack_.sleepSim(1.0);
  ASSERT_TRUE(stack_.basic().deactivate("SELF_LOCALIZE_WITH_GROUND_TRUTH").ok());
  auto event = finished(id);
  EXPECT_EQ(event.finished().cause(), v1::TERMINATION_CAUSE_PROCESS_FAILURE)
      << event.ShortDebugString();
  EXPECT_NE(event.finished().message().find("estimate"), std::string::npos)
      << event.finished().message();
  EXPECT_EQ(stack_.flightStatus().state(), v1::FLIGHT_STATE_HOVERING);
  EXPECT_EQ(stack_.flightStatus().lease_holder(), "");
}

}  // namespace
}  // namespace motion_test
