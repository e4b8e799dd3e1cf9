// quadrotor_motion_with_mpc_control flown against the real simulator (the
// broker, the simulator at 5x with a fixed seed, basic_quadrotor_behaviors,
// and the MPC system; the PID system too where two controllers compete for
// the lease), driven over gRPC, tracking measured on the simulator's ground
// truth in simulated time.

#include "motion_test_support.h"

namespace motion_test {
namespace {

// The same bound as the PID's (the issue asks for the MPC's figure beside it;
// docs/benchmarks.md has both).
constexpr double kMaxRmsCrossTrackM = 0.15;
constexpr double kYawToleranceRad = 2.0 * M_PI / 180.0;

class MotionMpcTest : public ::testing::Test {
 protected:
  void SetUp() override {
    std::string error;
    ASSERT_TRUE(stack_.start(&error)) << error;
    mpc_ = stack_.startSystem(BEHAVIORLIB_MPC_SYSTEM_PATH, BEHAVIORLIB_MPC_CONFIG_PATH, &error);
    ASSERT_TRUE(mpc_) << error;
    client_ = std::make_unique<SystemClient>(mpc_->address());
  }

  void TearDown() override {
    client_.reset();
    if (mpc_ && mpc_->running()) mpc_->kill();
    stack_.stop();
  }

  v1::BehaviorEvent finished(SystemClient& client, const std::string& activation_id,
                             milliseconds timeout = seconds(20)) {
    auto event = client.finished(activation_id, timeout);
    EXPECT_TRUE(event) << activation_id << " did not finish";
    return event.value_or(v1::BehaviorEvent());
  }

  Eigen::Vector3d position() { return stack_.truth().latest().value().position_m; }

  FlightStack stack_;
  std::unique_ptr<support::ServerProcess> mpc_;
  std::unique_ptr<SystemClient> client_;
};

TEST_F(MotionMpcTest, FollowsA4mSquareWithinTheCrossTrackBoundAndRotates90Degrees) {
  ASSERT_NO_FATAL_FAILURE(stack_.localizeAndTakeOff(1.5));
  const std::string controller = client_->start("QUADROTOR_MPC_MOTION_CONTROL", "{}");
  ASSERT_FALSE(controller.empty());
  const Eigen::Vector3d start = position();
  const double z = start.z();
  const std::vector<Eigen::Vector3d> square = {{start.x() + 4, start.y(), z},
                                               {start.x() + 4, start.y() + 4, z},
                                               {start.x(), start.y() + 4, z},
                                               {start.x(), start.y(), z}};
  const std::string path = client_->start("FOLLOW_PATH_WITH_MPC_CONTROL", pathJson(square));
  ASSERT_FALSE(path.empty());
  const auto done = finished(*client_, path, seconds(30));
  ASSERT_EQ(done.finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED)
      << done.ShortDebugString();
  std::vector<Eigen::Vector3d> polyline = {start};
  polyline.insert(polyline.end(), square.begin(), square.end());
  const Tracking t = tracking(stack_.truth(), client_->activated(path).value(), done, polyline);
  std::printf(
      "MPC square 4 m at 1 m/s: RMS cross-track %.4f m, max %.4f m, %zu samples, %.1f s "
      "(%s)\n",
      t.rms_m, t.max_m, t.samples, t.duration_s, done.finished().message().c_str());
  EXPECT_GT(t.samples, 1000u);
  EXPECT_LE(t.rms_m, kMaxRmsCrossTrackM);

  const double yaw0 = stack_.truth().latest()->yaw_rad;
  const std::string rotate =
      client_->start("ROTATE_WITH_MPC_CONTROL", "{\"yaw_rad\": 1.5707963, \"relative\": true}");
  const auto rotated = finished(*client_, rotate);
  ASSERT_EQ(rotated.finished().cause(), v1::TERMINATION_CAUSE_GOAL_ACHIEVED)
      << rotated.ShortDebugString();
  const double error = wrap(stack_.truth().latest()->yaw_rad - (yaw0 + M_PI / 2));
  std::printf("MPC rotate 90 deg: ground-truth error %.3f deg\n", degrees(error));
  EXPECT_LE(std::abs(error), kYawToleranceRad);

  // HOVER_WITH_MPC_CONTROL holds the point until deactivated.
  const Eigen::Vector3d here = position();
  const std::string hover = client_->start("HOVER_WITH_MPC_CONTROL", "{\"max_drift_m\": 0.2}");
  stack_.sleepSim(3.0);
  EXPECT_LT((position() - here).norm(), 0.1);
  ASSERT_TRUE(client_->deactivate("HOVER_WITH_MPC_CONTROL").ok());
  EXPECT_EQ(finished(*client_, hover).finished().cause(), v1::TERMINATION_CAUSE_INTERRUPTED);
  ASSERT_TRUE(client_->deactivate("QUADROTOR_MPC_MOTION_CONTROL").ok());
  EXPECT_EQ(finished(*client_, controller).finished().cause(), v1::TERMINATION_CAUSE_INTERRUPTED);
  ASSERT_NO_FATAL_FAILURE(stack_.land());
}

TEST_F(MotionMpcTest, BadInputIsInvalidArgumentNamingTheParameterBeforeAnythingMoves) {
  ASSERT_NO_FATAL_FAILURE(stack_.localizeAndTakeOff(1.0));
  const std::string controller = client_->start("QUADROTOR_MPC_MOTION_CONTROL", "{}");
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
      {pathJson({{1, 0, 1}}, "\"speed_m_s\": 0.01"), "speed_m_s"},
      {pathJson({{1, 0, 1}}, "\"sped_m_s\": 1"), "sped_m_s"},
  };
  for (const auto& c : cases) {
    v1::ActivateResponse response;
    const grpc::Status status =
        client_->activate("FOLLOW_PATH_WITH_MPC_CONTROL", c.json, &response);
    EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT)
        << c.json << ": " << describe(status);
    EXPECT_NE(status.error_message().find(c.names), std::string::npos)
        << c.json << ": " << describe(status);
  }
  // A NaN coordinate (JSON cannot carry it: a Struct built in code), and a
  // path longer than max_path_points (1000) of points 1 mm apart.
  v1::ActivateResponse response;
  grpc::Status status = client_->activate("FOLLOW_PATH_WITH_MPC_CONTROL",
                                          pathStruct({{std::nan(""), 0, 1}, {2, 0, 1}}), &response);
  EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << describe(status);
  EXPECT_NE(status.error_message().find("path_m[0]"), std::string::npos) << describe(status);
  std::vector<Eigen::Vector3d> many;
  for (int i = 0; i < 1001; ++i) many.push_back({before.x() + 0.001 * i, before.y(), 1.0});
  status = client_->activate("FOLLOW_PATH_WITH_MPC_CONTROL", pathStruct(many), &response);
  EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << describe(status);
  EXPECT_NE(status.error_message().find("path_m"), std::string::npos) << describe(status);
  EXPECT_NE(status.error_message().find("max_path_points"), std::string::npos) << describe(status);
  status = client_->activate("ROTATE_WITH_MPC_CONTROL", "{\"yaw_rad\": 9}", &response);
  EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT) << describe(status);
  EXPECT_NE(status.error_message().find("yaw_rad"), std::string::npos) << describe(status);
  // Nothing moved: the controller still holds where it started.
  stack_.sleepSim(2.0);
  EXPECT_LT((position() - before).norm(), 0.1);
  EXPECT_EQ(stack_.flightStatus().lease_holder(), "drone1/QUADROTOR_MPC_MOTION_CONTROL")
      << client_->finished(controller, milliseconds(0))
             .value_or(v1::BehaviorEvent())
             .ShortDebugString();
}

TEST_F(MotionMpcTest, TheLeaseRefusesASecondMotionControllerAndTheVehicleStaysControlled) {
  std::string error;
  auto pid = stack_.startSystem(BEHAVIORLIB_PID_SYSTEM_PATH, BEHAVIORLIB_PID_CONFIG_PATH, &error);
  ASSERT_TRUE(pid) << error;
  SystemClient pid_client(pid->address());
  ASSERT_NO_FATAL_FAILURE(stack_.localizeAndTakeOff(1.0));

  // Both controllers activated directly on their systems, bypassing the
  // coordinator: the PID takes the lease first.
  const std::string pid_controller = pid_client.start("QUADROTOR_PID_MOTION_CONTROL", "{}");
  ASSERT_FALSE(pid_controller.empty());
  const std::string hover = pid_client.start("KEEP_HOVERING_WITH_PID_CONTROL", "{}");
  ASSERT_FALSE(hover.empty());
  // The MPC system learns of the lease from its flight-state stream, which
  // may lag the PID's activation reply.
  v1::CheckSituationResponse situation;
  EXPECT_TRUE(FlightStack::waitFor(
      [&] {
        situation = client_->checkSituation("QUADROTOR_MPC_MOTION_CONTROL");
        return !situation.feasible();
      },
      seconds(5)));
  ASSERT_GT(situation.reasons_size(), 0);
  EXPECT_NE(situation.reasons(0).find("drone1/QUADROTOR_PID_MOTION_CONTROL"), std::string::npos)
      << situation.reasons(0);
  v1::ActivateResponse response;
  const grpc::Status refused = client_->activate("QUADROTOR_MPC_MOTION_CONTROL", "{}", &response);
  EXPECT_EQ(refused.error_code(), grpc::StatusCode::FAILED_PRECONDITION) << describe(refused);
  EXPECT_NE(refused.error_message().find("QUADROTOR_PID_MOTION_CONTROL"), std::string::npos)
      << describe(refused);

  // The vehicle stays under the PID controller's control.
  const Eigen::Vector3d here = position();
  stack_.sleepSim(3.0);
  EXPECT_EQ(stack_.flightStatus().lease_holder(), "drone1/QUADROTOR_PID_MOTION_CONTROL");
  EXPECT_EQ(stack_.flightStatus().state(), v1::FLIGHT_STATE_FLYING);
  EXPECT_LT((position() - here).norm(), 0.1);
  EXPECT_FALSE(pid_client.finished(pid_controller, milliseconds(0)));
  EXPECT_FALSE(pid_client.finished(hover, milliseconds(0)));

  // The MPC system's high-level behaviors follow whichever controller is
  // active: HOVER_WITH_MPC_CONTROL's references are followed by the PID.
  ASSERT_TRUE(pid_client.deactivate("KEEP_HOVERING_WITH_PID_CONTROL").ok());
  const std::string mpc_hover = client_->start("HOVER_WITH_MPC_CONTROL", "{}");
  stack_.sleepSim(3.0);
  EXPECT_FALSE(client_->finished(mpc_hover, milliseconds(0)))
      << "followed by QUADROTOR_PID_MOTION_CONTROL";
  ASSERT_TRUE(client_->deactivate("HOVER_WITH_MPC_CONTROL").ok());
  EXPECT_EQ(finished(*client_, mpc_hover).finished().cause(), v1::TERMINATION_CAUSE_INTERRUPTED);

  // Once the PID controller is gone the MPC controller takes over.
  ASSERT_TRUE(pid_client.deactivate("QUADROTOR_PID_MOTION_CONTROL").ok());
  ASSERT_TRUE(pid_client.finished(pid_controller));
  const std::string mpc_controller = client_->start("QUADROTOR_MPC_MOTION_CONTROL", "{}");
  ASSERT_FALSE(mpc_controller.empty());
  EXPECT_EQ(stack_.flightStatus().lease_holder(), "drone1/QUADROTOR_MPC_MOTION_CONTROL");
  pid->kill();
}

}  // namespace
}  // namespace motion_test
