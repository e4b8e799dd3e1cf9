// WorldSim: several vehicles by robot id, stepped together, deterministic.

#include "simulator/dynamics/world_sim.h"

#include <gtest/gtest.h>

#include <cmath>

namespace behaviorlib::sim {
namespace {

QuadrotorState hoveringAt(const Eigen::Vector3d& position_m) {
  QuadrotorState s;
  s.position_m = position_m;
  s.motor_speeds_rad_s.fill(QuadrotorParams{}.hoverMotorSpeedRadS());
  return s;
}

void expectSameState(const QuadrotorState& a, const QuadrotorState& b) {
  EXPECT_EQ(a.position_m, b.position_m);
  EXPECT_EQ(a.velocity_m_s, b.velocity_m_s);
  EXPECT_EQ(a.orientation.coeffs(), b.orientation.coeffs());
  EXPECT_EQ(a.angular_velocity_rad_s, b.angular_velocity_rad_s);
  EXPECT_EQ(a.motor_speeds_rad_s, b.motor_speeds_rad_s);
  EXPECT_EQ(a.battery_soc, b.battery_soc);
}

TEST(WorldSimTest, VehiclesAreKeyedByRobotId) {
  WorldSim world;
  SimVehicle* b = world.addVehicle("drone_b");
  SimVehicle* a = world.addVehicle("drone_a", hoveringAt({0, 0, 5}));
  ASSERT_NE(a, nullptr);
  ASSERT_NE(b, nullptr);
  EXPECT_EQ(world.addVehicle("drone_a"), nullptr);  // taken
  EXPECT_EQ(world.addVehicle(""), nullptr);
  EXPECT_EQ(world.vehicleCount(), 2u);
  EXPECT_EQ(world.robotIds(), (std::vector<std::string>{"drone_a", "drone_b"}));
  EXPECT_EQ(world.vehicle("drone_a"), a);
  EXPECT_EQ(a->robotId(), "drone_a");
  EXPECT_EQ(world.vehicle("nobody"), nullptr);
  EXPECT_TRUE(std::holds_alternative<Idle>(b->setpoint()));
  EXPECT_TRUE(b->state().landed);
  EXPECT_FALSE(world.setSetpoint("nobody", Idle{}));
  EXPECT_TRUE(world.removeVehicle("drone_b"));
  EXPECT_FALSE(world.removeVehicle("drone_b"));
  EXPECT_EQ(world.robotIds(), (std::vector<std::string>{"drone_a"}));
}

TEST(WorldSimTest, StepsEveryVehicleTowardsItsOwnSetpoint) {
  WorldSim world;
  world.addVehicle("drone1", hoveringAt({0, 0, 3}));
  world.addVehicle("drone2", hoveringAt({10, 0, 3}));
  world.addVehicle("drone3");  // on the ground, idle
  ASSERT_TRUE(world.setSetpoint("drone1", PositionYaw{{2, 2, 4}, 0.0}));
  ASSERT_TRUE(world.setSetpoint("drone2", VelocityYawRate{{0, 1, 0}, 0.0}));
  world.advance(8.0);
  EXPECT_EQ(world.stepCount(), 8000u);
  EXPECT_EQ(world.timeNs(), 8'000'000'000);
  EXPECT_DOUBLE_EQ(world.timeS(), 8.0);
  EXPECT_LT((world.vehicle("drone1")->state().position_m - Eigen::Vector3d(2, 2, 4)).norm(), 0.1);
  EXPECT_NEAR(world.vehicle("drone2")->state().velocity_m_s.y(), 1.0, 0.05);
  EXPECT_NEAR(world.vehicle("drone2")->state().position_m.z(), 3.0, 0.05);
  const QuadrotorState& idle = world.vehicle("drone3")->state();
  EXPECT_TRUE(idle.landed);
  EXPECT_EQ(idle.position_m, Eigen::Vector3d::Zero());
}

WorldSimOptions gusty(std::uint64_t seed) {
  WorldSimOptions options;
  options.seed = seed;
  options.wind_m_s = {2.0, 1.0, 0.0};
  options.gust_std_m_s = 1.5;
  options.gust_time_constant_s = 1.0;
  return options;
}

void flyCircuit(WorldSim& world) {
  world.setSetpoint("drone1", PositionYaw{{5, 0, 5}, 1.0});
  world.advance(3.0);
  world.setSetpoint("drone1", VelocityYawRate{{-1, 1, 0}, 0.3});
  world.advance(3.0);
}

TEST(WorldSimTest, SameSeedSameTrajectoryBitForBit) {
  WorldSim a(gusty(42)), b(gusty(42)), c(gusty(43));
  for (WorldSim* w : {&a, &b, &c}) w->addVehicle("drone1", hoveringAt({0, 0, 5}));
  // Another vehicle in one world does not change drone1's wind.
  b.addVehicle("drone0", hoveringAt({20, 0, 5}));
  b.setSetpoint("drone0", PositionYaw{{20, 5, 5}, 0.0});
  flyCircuit(a);
  flyCircuit(b);
  flyCircuit(c);
  expectSameState(a.vehicle("drone1")->state(), b.vehicle("drone1")->state());
  EXPECT_EQ(a.vehicle("drone1")->gust(), b.vehicle("drone1")->gust());
  EXPECT_NE(a.vehicle("drone1")->state().position_m, c.vehicle("drone1")->state().position_m);
}

TEST(WorldSimTest, TurbulenceHasTheRequestedSpread) {
  WorldSimOptions options = gusty(7);
  WorldSim world(options);
  SimVehicle* v = world.addVehicle("drone1");  // stays idle on the ground
  double sum = 0.0, sum_sq = 0.0;
  const int n = 400000;  // 400 s: ~200 correlation times per axis
  for (int i = 0; i < n; ++i) {
    world.step();
    sum += v->gust().x();
    sum_sq += v->gust().x() * v->gust().x();
  }
  const double mean = sum / n;
  const double std = std::sqrt(sum_sq / n - mean * mean);
  // ~200 independent samples: the estimate's spread is ~5 % (std) and
  // ~0.1 m/s (mean); allow four times that.
  EXPECT_NEAR(std, options.gust_std_m_s, 0.2 * options.gust_std_m_s);
  EXPECT_NEAR(mean, 0.0, 0.45);
  EXPECT_EQ(v->quadrotor().windVelocity(), options.wind_m_s + v->gust());
}

class Floor : public world::CollisionWorld {
 public:
  explicit Floor(double z) : z_(z) {}
  bool collides(const Eigen::Vector3d& p, double radius_m) const override {
    return p.z() - radius_m <= z_;
  }

 private:
  double z_;
};

TEST(WorldSimTest, CollisionWorldAppliesToEveryVehicle) {
  WorldSim world;
  Floor roof_of_a_building(4.0);
  world.addVehicle("before", hoveringAt({0, 0, 6}));
  world.setCollisionWorld(&roof_of_a_building);
  world.addVehicle("after", hoveringAt({5, 0, 6}));
  for (const std::string& id : world.robotIds()) {
    world.setSetpoint(id, VelocityYawRate{{0, 0, -1}, 0.0});
  }
  world.advance(3.0);
  for (const std::string& id : world.robotIds()) {
    const QuadrotorState& s = world.vehicle(id)->state();
    EXPECT_TRUE(s.crashed) << id;
    EXPECT_EQ(s.crash_cause, CrashCause::kCollision) << id;
    EXPECT_NEAR(s.position_m.z(), 4.0 + QuadrotorParams{}.collision_radius_m, 0.01) << id;
  }
}

}  // namespace
}  // namespace behaviorlib::sim
