// The cascaded autopilot flying the Quadrotor model closed-loop at 1 kHz:
// each setpoint level converges, and the mixer keeps its priorities.

#include "simulator/dynamics/autopilot.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <numbers>

#include "simulator/dynamics/quadrotor.h"

namespace behaviorlib::sim {
namespace {

constexpr double kDt = 0.001;
constexpr double kG = kStandardGravity;

QuadrotorState hoveringAt(const QuadrotorParams& p, const Eigen::Vector3d& position_m,
                          double yaw_rad = 0.0) {
  QuadrotorState s;
  s.position_m = position_m;
  s.orientation = yawOnly(yaw_rad);
  s.motor_speeds_rad_s.fill(p.hoverMotorSpeedRadS());
  return s;
}

double angleDiff(double a, double b) { return std::remainder(a - b, 2.0 * std::numbers::pi); }

class AutopilotTest : public ::testing::Test {
 protected:
  // Flies `seconds` under `setpoint`, calling `each` after every step.
  template <typename F>
  void fly(const Setpoint& setpoint, double seconds, F each) {
    const long n = std::lround(seconds / kDt);
    for (long i = 0; i < n; ++i) {
      quad_.step(kDt, autopilot_.update(quad_.state(), setpoint, kDt));
      each(quad_.state());
    }
  }
  void fly(const Setpoint& setpoint, double seconds) {
    fly(setpoint, seconds, [](const QuadrotorState&) {});
  }
  const QuadrotorState& state() const { return quad_.state(); }

  QuadrotorParams params_;
  Quadrotor quad_{params_, hoveringAt(params_, {0.0, 0.0, 10.0})};
  Autopilot autopilot_{params_};
};

TEST_F(AutopilotTest, HoldsHoverAtTheHoverCommand) {
  const Setpoint hold = PositionYaw{{0.0, 0.0, 10.0}, 0.0};
  fly(hold, 3.0);
  EXPECT_NEAR((state().position_m - Eigen::Vector3d(0, 0, 10)).norm(), 0.0, 1e-3);
  // u = sqrt(m g / 4 k_f) / (w_max V / V_full): the hover command, scaled
  // up for the battery's terminal voltage.
  const MotorCommands u = autopilot_.update(state(), hold, kDt);
  const double expected =
      params_.hoverMotorCommand() * params_.battery_full_voltage_v / state().battery_voltage_v;
  for (double c : u) EXPECT_NEAR(c, expected, 2e-3 * expected);
  EXPECT_NEAR(autopilot_.status().thrust_n, params_.mass_kg * kG, 0.01);
}

TEST_F(AutopilotTest, VelocitySetpointConvergesWithLittleOvershoot) {
  const Setpoint east = VelocityYawRate{{2.0, 0.0, 0.0}, 0.0};
  double max_vx = 0.0;
  double max_altitude_error = 0.0;
  double t90 = -1.0;
  double t = 0.0;
  fly(east, 3.0, [&](const QuadrotorState& s) {
    t += kDt;
    max_vx = std::max(max_vx, s.velocity_m_s.x());
    max_altitude_error = std::max(max_altitude_error, std::abs(s.position_m.z() - 10.0));
    if (t90 < 0.0 && s.velocity_m_s.x() >= 1.8) t90 = t;
  });
  EXPECT_GT(t90, 0.0);
  EXPECT_LT(t90, 1.5);  // velocity loop P = 2.5 /s: ~0.4 s time constant plus tilt lag
  EXPECT_NEAR(state().velocity_m_s.x(), 2.0, 0.05);
  EXPECT_LT(max_vx, 2.0 * 1.05);  // < 5 % overshoot
  EXPECT_NEAR(state().velocity_m_s.y(), 0.0, 1e-3);
  EXPECT_NEAR(state().velocity_m_s.z(), 0.0, 0.05);
  EXPECT_LT(max_altitude_error, 0.1);
  EXPECT_NEAR(yawOf(state().orientation), 0.0, 1e-3);
  // Steady flight at 2 m/s: the pitch that balances drag, tan(theta) = D / (m g).
  fly(east, 5.0, [&](const QuadrotorState& s) { max_vx = std::max(max_vx, s.velocity_m_s.x()); });
  EXPECT_NEAR(state().velocity_m_s.x(), 2.0, 0.03);
  EXPECT_LT(max_vx, 2.0 * 1.05);
}

TEST_F(AutopilotTest, VelocityUpTakesOffFromTheGround) {
  quad_.reset(QuadrotorState{});  // landed at the origin, motors stopped
  ASSERT_TRUE(state().landed);
  const Setpoint up = VelocityYawRate{{0.0, 0.0, 1.0}, 0.0};
  fly(up, 4.0);
  EXPECT_FALSE(state().landed);
  EXPECT_NEAR(state().velocity_m_s.z(), 1.0, 0.03);
  EXPECT_GT(state().position_m.z(), 3.0);
  EXPECT_NEAR(state().position_m.head<2>().norm(), 0.0, 1e-3);
}

TEST_F(AutopilotTest, VelocityModeYawRate) {
  const Setpoint turn = VelocityYawRate{{0.0, 0.0, 0.0}, 0.5};
  fly(turn, 3.0);
  EXPECT_NEAR(state().angular_velocity_rad_s.z(), 0.5, 0.01);
  // Tracks the integrated reference: yaw(t) ~ 0.5 t after the lag.
  EXPECT_NEAR(angleDiff(yawOf(state().orientation), 1.5), 0.0, 0.05);
  EXPECT_NEAR((state().position_m - Eigen::Vector3d(0, 0, 10)).norm(), 0.0, 0.05);
  // Yaw rate 0 again: the heading is held.
  const Setpoint stop = VelocityYawRate{{0.0, 0.0, 0.0}, 0.0};
  fly(stop, 2.0);
  const double yaw = yawOf(state().orientation);
  fly(stop, 2.0);
  EXPECT_NEAR(angleDiff(yawOf(state().orientation), yaw), 0.0, 1e-3);
}

TEST_F(AutopilotTest, PositionSetpointIsReached) {
  quad_.reset(hoveringAt(params_, {0.0, 0.0, 2.0}));
  const Eigen::Vector3d target(5.0, -3.0, 4.0);
  const Setpoint go = PositionYaw{target, 1.5};
  double min_z = 10.0;
  fly(go, 10.0, [&](const QuadrotorState& s) { min_z = std::min(min_z, s.position_m.z()); });
  EXPECT_LT((state().position_m - target).norm(), 0.1);
  EXPECT_LT(state().velocity_m_s.norm(), 0.05);
  EXPECT_NEAR(angleDiff(yawOf(state().orientation), 1.5), 0.0, 0.01);
  EXPECT_GT(min_z, 1.9);  // climbing to 4 m never dips
}

TEST_F(AutopilotTest, PositionHoldRejectsWind) {
  quad_.setWindVelocity({5.0, 0.0, 0.0});
  const Setpoint hold = PositionYaw{{0.0, 0.0, 10.0}, 0.0};
  double max_error = 0.0;
  fly(hold, 30.0, [&](const QuadrotorState& s) {
    max_error = std::max(max_error, (s.position_m - Eigen::Vector3d(0, 0, 10)).norm());
  });
  EXPECT_LT(max_error, 1.0);
  EXPECT_LT((state().position_m - Eigen::Vector3d(0, 0, 10)).norm(), 0.05);
  // Leaning into the wind: drag of 5 m/s air balanced by tilting towards -x.
  EXPECT_LT((state().orientation * Eigen::Vector3d::UnitZ()).x(), -0.05);
}

TEST_F(AutopilotTest, AttitudeSetpointIsTracked) {
  const double roll = 0.2;
  const Eigen::Quaterniond q(Eigen::AngleAxisd(roll, Eigen::Vector3d::UnitX()));
  // Thrust that keeps the vertical component at m g.
  const Setpoint tilt = AttitudeThrust{q, params_.hoverThrustRatio() / std::cos(roll)};
  fly(tilt, 0.5);
  EXPECT_LT(state().orientation.angularDistance(q), 0.01);
  // Rolling right (positive roll about forward) tilts the thrust to -y
  // (south with yaw 0): a = -g tan(roll), less the drag at < 1.6 m/s.
  const double vy0 = state().velocity_m_s.y();
  fly(tilt, 0.5);
  const double ay = (state().velocity_m_s.y() - vy0) / 0.5;
  const double max_drag_accel = (0.25 * 1.6 + 0.04 * 1.6 * 1.6) / params_.mass_kg;
  EXPECT_LT(ay, -kG * std::tan(roll) + max_drag_accel);
  EXPECT_GT(ay, -kG * std::tan(roll) - 1e-3);
  EXPECT_NEAR(state().velocity_m_s.z(), 0.0, 0.05);

  // A level attitude with a heading: yaw converges.
  const Setpoint heading = AttitudeThrust{yawOnly(1.0), params_.hoverThrustRatio()};
  fly(heading, 2.0);
  EXPECT_NEAR(yawOf(state().orientation), 1.0, 0.01);
}

TEST_F(AutopilotTest, ThrustRatesTracksBodyRates) {
  fly(ThrustRates{params_.hoverThrustRatio(), {0.0, 0.0, 1.0}}, 1.0);
  EXPECT_NEAR(state().angular_velocity_rad_s.z(), 1.0, 0.02);
  EXPECT_NEAR(state().angular_velocity_rad_s.head<2>().norm(), 0.0, 1e-3);
  // A roll rate: the rate loop (P = 20 /s, motor lag 30 ms) settles in ~0.2 s.
  quad_.reset(hoveringAt(params_, {0.0, 0.0, 10.0}));
  autopilot_.reset();
  fly(ThrustRates{params_.hoverThrustRatio(), {1.0, 0.0, 0.0}}, 0.3);
  EXPECT_NEAR(state().angular_velocity_rad_s.x(), 1.0, 0.05);
}

TEST_F(AutopilotTest, IdleAndCrashGiveZeroCommands) {
  const MotorCommands off{};
  EXPECT_EQ(autopilot_.update(state(), Idle{}, kDt), off);
  QuadrotorState crashed = state();
  crashed.crashed = true;
  EXPECT_EQ(autopilot_.update(crashed, PositionYaw{{0, 0, 10}, 0}, kDt), off);
}

TEST_F(AutopilotTest, DescendingToTheGroundLandsAndStays) {
  quad_.reset(hoveringAt(params_, {0.0, 0.0, 2.0}));
  const Setpoint down = VelocityYawRate{{0.0, 0.0, -0.6}, 0.0};
  fly(down, 6.0);
  EXPECT_TRUE(state().landed);
  EXPECT_FALSE(state().crashed);
  EXPECT_DOUBLE_EQ(state().position_m.z(), 0.0);
  fly(down, 2.0);
  EXPECT_TRUE(state().landed);
}

// --- Mixer -------------------------------------------------------------------

double sum(const std::array<double, kMotorCount>& t) { return t[0] + t[1] + t[2] + t[3]; }

TEST(MixerTest, ExactWhenNothingSaturates) {
  const QuadrotorParams p;
  const Mixer mixer(p);
  const Eigen::Vector3d torque(0.1, -0.2, 0.02);
  const auto t = mixer.allocate(p.mass_kg * kG, torque, p.maxMotorThrustN());
  const Eigen::Vector4d w = mixer.wrench(t);
  EXPECT_NEAR(w(0), p.mass_kg * kG, 1e-9);
  EXPECT_NEAR((w.tail<3>() - torque).norm(), 0.0, 1e-9);
}

TEST(MixerTest, RollPitchKeepPriorityOverThrust) {
  const QuadrotorParams p;
  const Mixer mixer(p);
  const double t_max = p.maxMotorThrustN();
  // Full thrust asked with a roll torque: thrust gives way, the roll is exact.
  const auto full = mixer.allocate(p.maxThrustN(), {0.5, 0.0, 0.0}, t_max);
  const Eigen::Vector4d w = mixer.wrench(full);
  EXPECT_NEAR(w(1), 0.5, 1e-9);
  EXPECT_LT(w(0), p.maxThrustN());
  EXPECT_NEAR(*std::max_element(full.begin(), full.end()), t_max, 1e-9);
  // Zero thrust asked with a pitch torque: thrust is raised to deliver it.
  const auto zero = mixer.allocate(0.0, {0.0, 0.3, 0.0}, t_max);
  EXPECT_NEAR(mixer.wrench(zero)(2), 0.3, 1e-9);
  EXPECT_NEAR(*std::min_element(zero.begin(), zero.end()), 0.0, 1e-12);
}

TEST(MixerTest, YawGivesWayFirst) {
  const QuadrotorParams p;
  const Mixer mixer(p);
  const double thrust = p.mass_kg * kG;
  const auto t = mixer.allocate(thrust, {0.05, 0.0, 5.0}, p.maxMotorThrustN());
  const Eigen::Vector4d w = mixer.wrench(t);
  EXPECT_NEAR(w(0), thrust, 1e-9);  // thrust kept
  EXPECT_NEAR(w(1), 0.05, 1e-9);    // roll kept
  EXPECT_GT(w(3), 0.0);             // yaw: as much as fits, in the right direction
  EXPECT_LT(w(3), 5.0);
  EXPECT_NEAR(sum(t), thrust, 1e-9);
  for (double ti : t) {
    EXPECT_GE(ti, 0.0);
    EXPECT_LE(ti, p.maxMotorThrustN());
  }
}

}  // namespace
}  // namespace behaviorlib::sim
