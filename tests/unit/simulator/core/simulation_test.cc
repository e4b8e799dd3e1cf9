#include "simulator/core/simulation.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <thread>

namespace behaviorlib::sim {
namespace {

using std::chrono::milliseconds;
using std::chrono::seconds;

// A kinematic stand-in for the physics: follows velocity and position
// commands exactly (speed-limited) and falls when its motors are off. Enough
// to test time, stepping and the platform logic in closed loop.
class KinematicModel final : public VehicleModel {
 public:
  void command(const PlatformCommand& command) override { command_ = command; }
  void step(double dt) override {
    Eigen::Vector3d v = Eigen::Vector3d::Zero();
    switch (command_.kind) {
      case PlatformCommand::Kind::kVelocityYawRate:
        v = command_.vector;
        break;
      case PlatformCommand::Kind::kPositionYaw:
        v = 2.0 * (command_.vector - state_.position_m);
        if (v.norm() > 3.0) v = v.normalized() * 3.0;
        break;
      case PlatformCommand::Kind::kIdle:
        v = state_.velocity_m_s + Eigen::Vector3d(0, 0, -9.81 * dt);
        break;
      default:
        break;
    }
    state_.velocity_m_s = v;
    state_.position_m += v * dt;
    state_.on_ground = state_.position_m.z() <= 0.0 && v.z() <= 0.0;
    if (state_.position_m.z() < 0.0) {
      state_.position_m.z() = 0.0;
      state_.velocity_m_s.setZero();
    }
    ++steps_;
  }
  VehicleSnapshot snapshot() const override { return state_; }
  int steps_ = 0;

 private:
  PlatformCommand command_;
  VehicleSnapshot state_;
};

class SimulationTest : public ::testing::Test {
 protected:
  void SetUp() override {
    auto model = std::make_unique<KinematicModel>();
    model_ = model.get();
    ASSERT_TRUE(sim_.addVehicle("drone1", std::move(model)).ok());
  }
  std::string lease(SimDuration ttl = milliseconds(500)) {
    auto r = sim_.withPlatform("drone1", [&](VehiclePlatform& p, SimTime now) {
      return p.acquireLease("test", ttl, false, now);
    });
    EXPECT_TRUE(r.ok() && r->ok());
    return (*r)->lease_id();
  }
  v1::FlightState state() { return sim_.vehicleState("drone1")->second; }
  double altitude() { return sim_.vehicleState("drone1")->first.position_m.z(); }

  Simulation sim_{SimulationOptions{}};
  KinematicModel* model_ = nullptr;
};

TEST_F(SimulationTest, AdvanceStepsAtTheFixedPhysicsRateAndNotifiesListeners) {
  std::vector<SimTime> stamps;
  size_t reported = 0;
  sim_.addStepListener([&](SimTime now, const std::vector<VehicleReport>& vehicles) {
    stamps.push_back(now);
    reported = vehicles.size();
  });
  sim_.advance(milliseconds(250));
  EXPECT_EQ(sim_.now(), milliseconds(250));
  EXPECT_EQ(model_->steps_, 250);
  ASSERT_EQ(stamps.size(), 250u);
  EXPECT_EQ(stamps.front(), milliseconds(1));
  EXPECT_EQ(stamps.back(), milliseconds(250));
  EXPECT_EQ(reported, 1u);
}

TEST_F(SimulationTest, TakeOffInClosedLoopReachesHoveringAtTheTargetAltitude) {
  const std::string id = lease(seconds(10));
  auto r = sim_.withPlatform("drone1", [&](VehiclePlatform& p, SimTime now) {
    return p.executeAction(v1::FLIGHT_ACTION_TAKE_OFF, id, 2.0, false, now);
  });
  ASSERT_TRUE(r.ok() && r->ok());
  sim_.advance(milliseconds(500));
  EXPECT_EQ(state(), v1::FLIGHT_STATE_TAKING_OFF);
  EXPECT_NEAR(altitude(), 0.5, 0.01) << "climbs at the take-off speed of 1 m/s";
  sim_.advance(seconds(3));
  EXPECT_EQ(state(), v1::FLIGHT_STATE_HOVERING);
  EXPECT_NEAR(altitude(), 2.0, 0.11);
}

TEST_F(SimulationTest, SilentCommanderTriggersHoverThenLandingInClosedLoop) {
  const std::string id = lease(seconds(10));
  ASSERT_TRUE(sim_.withPlatform("drone1",
                                [&](VehiclePlatform& p, SimTime now) {
                                  return p.executeAction(v1::FLIGHT_ACTION_TAKE_OFF, id, 1.0, false,
                                                         now);
                                })
                  ->ok());
  sim_.advance(seconds(2));
  ASSERT_EQ(state(), v1::FLIGHT_STATE_HOVERING);
  // A short lease, one setpoint, then silence.
  const std::string short_lease = lease(milliseconds(200));
  v1::SetpointRequest setpoint;
  setpoint.set_lease_id(short_lease);
  setpoint.mutable_velocity_yaw_rate()->mutable_velocity_m_s()->set_x(1.0);
  ASSERT_TRUE(sim_.withPlatform("drone1", [&](VehiclePlatform& p,
                                              SimTime now) { return p.setpoint(setpoint, now); })
                  ->ok());
  sim_.advance(milliseconds(150));
  EXPECT_EQ(state(), v1::FLIGHT_STATE_FLYING);
  sim_.advance(milliseconds(100));
  EXPECT_EQ(state(), v1::FLIGHT_STATE_HOVERING) << "lease lost: hold position";
  const double x_at_loss = sim_.vehicleState("drone1")->first.position_m.x();
  sim_.advance(seconds(4));
  EXPECT_EQ(state(), v1::FLIGHT_STATE_HOVERING);
  EXPECT_NEAR(sim_.vehicleState("drone1")->first.position_m.x(), x_at_loss, 0.05)
      << "the failsafe holds position, it does not keep the last velocity";
  sim_.advance(seconds(2));
  EXPECT_EQ(state(), v1::FLIGHT_STATE_LANDING);
  sim_.advance(seconds(3));
  EXPECT_EQ(state(), v1::FLIGHT_STATE_LANDED);
  EXPECT_DOUBLE_EQ(altitude(), 0.0);
}

TEST_F(SimulationTest, UnknownAndDuplicateVehiclesAreReported) {
  auto r = sim_.withPlatform("drone7", [](VehiclePlatform& p, SimTime) { return p.state(); });
  EXPECT_EQ(r.status().code(), absl::StatusCode::kNotFound);
  EXPECT_THAT(std::string(r.status().message()), ::testing::HasSubstr("drone1"));
  EXPECT_EQ(sim_.addVehicle("drone1", std::make_unique<KinematicModel>()).code(),
            absl::StatusCode::kAlreadyExists);
}

TEST_F(SimulationTest, RealTimeRunNeverGetsAheadOfTheScaledWallClock) {
  std::atomic<double> scale{20.0};
  std::atomic<bool> stop{false}, paused{false};
  const auto wall_start = std::chrono::steady_clock::now();
  std::thread runner([&] { sim_.runRealTime(scale, paused, stop); });
  std::this_thread::sleep_for(milliseconds(200));
  stop = true;
  runner.join();
  const double wall_s =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - wall_start).count();
  const double sim_s = std::chrono::duration<double>(sim_.now()).count();
  EXPECT_GT(sim_s, 0.0);
  EXPECT_LE(sim_s, 20.0 * wall_s + 0.01);
}

}  // namespace
}  // namespace behaviorlib::sim
