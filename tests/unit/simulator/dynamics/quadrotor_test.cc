// Physics of the Quadrotor model: each expectation is a closed-form result
// (free fall, hover balance, the motor lag, drag balance) with a tolerance
// derived from the integrator's known error, or a contact / battery rule.

#include "simulator/dynamics/quadrotor.h"

#include <gtest/gtest.h>

#include <cmath>

#include "simulator/dynamics/autopilot.h"
#include "simulator/dynamics/vehicle_params.h"

namespace behaviorlib::sim {
namespace {

constexpr double kDt = 0.001;  // 1 kHz
constexpr double kG = kStandardGravity;

MotorCommands all(double u) { return {u, u, u, u}; }

QuadrotorParams noDrag() {
  QuadrotorParams p;
  p.linear_drag_n_s_m.setZero();
  p.quadratic_drag_n_s2_m2.setZero();
  p.angular_drag_n_m_s_rad = 0.0;
  return p;
}

QuadrotorState airborne(const Eigen::Vector3d& position_m, double motor_speed_rad_s = 0.0) {
  QuadrotorState s;
  s.position_m = position_m;
  s.motor_speeds_rad_s.fill(motor_speed_rad_s);
  return s;
}

void run(Quadrotor& q, double seconds, const MotorCommands& u) {
  const long n = std::lround(seconds / kDt);
  for (long i = 0; i < n; ++i) q.step(kDt, u);
}

double tiltOf(const Eigen::Quaterniond& q) {
  return std::acos(std::clamp((q * Eigen::Vector3d::UnitZ()).z(), -1.0, 1.0));
}

TEST(QuadrotorTest, DefaultsHoverNearHalfThrottle) {
  const QuadrotorParams p;
  // u_hover = sqrt(m g / (4 k_f)) / w_max.
  EXPECT_DOUBLE_EQ(
      p.hoverMotorCommand(),
      std::sqrt(p.mass_kg * kG / (4.0 * p.thrust_coefficient_n_s2)) / p.max_motor_speed_rad_s);
  EXPECT_GT(p.hoverMotorCommand(), 0.5);
  EXPECT_LT(p.hoverMotorCommand(), 0.6);
  EXPECT_NEAR(p.hoverThrustRatio(), p.hoverMotorCommand() * p.hoverMotorCommand(), 1e-12);
}

TEST(QuadrotorTest, FreeFallFollowsGravityThenCrashesOnTheGround) {
  const double z0 = 20.0;
  Quadrotor q(noDrag(), airborne({1.0, 2.0, z0}));
  const int n = 1500;
  run(q, n * kDt, all(0.0));
  const double t = n * kDt;
  // Semi-implicit Euler from rest: z_n = z0 - g dt^2 n (n + 1) / 2 exactly,
  // i.e. the continuous -g t^2 / 2 with an O(dt) offset of -g t dt / 2.
  const double z_discrete = z0 - kG * kDt * kDt * n * (n + 1) / 2.0;
  const double z_continuous = z0 - 0.5 * kG * t * t;
  EXPECT_NEAR(q.state().position_m.z(), z_discrete, 1e-9);
  EXPECT_NEAR(q.state().position_m.z(), z_continuous, 0.5 * kG * t * kDt + 1e-9);
  EXPECT_NEAR(q.state().velocity_m_s.z(), -kG * t, 1e-9);
  EXPECT_DOUBLE_EQ(q.state().position_m.x(), 1.0);
  EXPECT_DOUBLE_EQ(q.state().position_m.y(), 2.0);
  // An ideal accelerometer reads nothing in free fall.
  EXPECT_NEAR(q.specificForceBody().norm(), 0.0, 1e-9);
  EXPECT_FALSE(q.state().landed);
  // Impact at sqrt(2 g z0) ~ 19.8 m/s > 3 m/s.
  run(q, 1.0, all(0.0));
  EXPECT_TRUE(q.state().crashed);
  EXPECT_EQ(q.state().crash_cause, CrashCause::kHardImpact);
  EXPECT_DOUBLE_EQ(q.state().position_m.z(), 0.0);
}

TEST(QuadrotorTest, HoverCommandBalancesGravity) {
  QuadrotorParams p = noDrag();
  p.simulate_battery = false;  // full voltage, so the command maps to w exactly
  const double w_hover = p.hoverMotorSpeedRadS();
  Quadrotor q(p, airborne({0.0, 0.0, 10.0}, w_hover));
  run(q, 5.0, all(p.hoverMotorCommand()));
  // Equilibrium: 4 k_f w^2 = m g to round-off.
  EXPECT_NEAR(q.collectiveThrustN(), p.mass_kg * kG, 1e-9);
  EXPECT_NEAR(q.state().velocity_m_s.norm(), 0.0, 1e-9);
  EXPECT_NEAR(q.state().position_m.z(), 10.0, 1e-9);
  EXPECT_NEAR(q.state().angular_velocity_rad_s.norm(), 0.0, 1e-12);
  // Resting or hovering, the accelerometer reads +g along body z.
  EXPECT_NEAR(q.specificForceBody().z(), kG, 1e-9);
}

TEST(QuadrotorTest, OnePercentMoreCommandClimbsAtTheForceBalance) {
  QuadrotorParams p = noDrag();
  p.simulate_battery = false;
  Quadrotor q(p, airborne({0.0, 0.0, 10.0}, p.hoverMotorSpeedRadS()));
  const double t = 2.0;
  run(q, t, all(1.01 * p.hoverMotorCommand()));
  // a = (4 k_f (1.01 w_h)^2 - m g) / m = g (1.01^2 - 1). The motors reach the
  // new speed with a lag tau, so v ~ a (t - tau); allow 1 % of a t.
  const double a = kG * (1.01 * 1.01 - 1.0);
  EXPECT_NEAR(q.state().acceleration_m_s2.z(), a, 1e-9);
  EXPECT_NEAR(q.state().velocity_m_s.z(), a * (t - p.motor_time_constant_s), 0.01 * a * t);
}

TEST(QuadrotorTest, MotorsFollowAFirstOrderLag) {
  QuadrotorParams p;
  p.simulate_battery = false;
  Quadrotor q(p);  // on the ground, motors stopped
  const double tau = p.motor_time_constant_s;
  run(q, tau, all(0.5));
  // The exact discretization: w(tau) = w_target (1 - e^-1).
  const double target = 0.5 * p.max_motor_speed_rad_s;
  for (double w : q.state().motor_speeds_rad_s) {
    EXPECT_NEAR(w, target * (1.0 - std::exp(-1.0)), 1e-9);
  }
  run(q, 10 * tau, all(0.5));
  EXPECT_NEAR(q.state().motor_speeds_rad_s[0], target, target * std::exp(-10.0) * 1.01);
}

TEST(QuadrotorTest, MotorTorquesHaveTheDocumentedSigns) {
  QuadrotorParams p = noDrag();
  p.simulate_battery = false;
  const double u = p.hoverMotorCommand();
  const double w = p.hoverMotorSpeedRadS();
  struct Case {
    MotorCommands commands;
    int axis;
    double sign;
  };
  const Case cases[] = {
      {{u, u * 1.05, u * 1.05, u}, 0, +1.0},  // left motors (1, 2) faster: roll left side up
      {{u * 1.05, u, u * 1.05, u}, 1, -1.0},  // front motors (0, 2) faster: nose up
      {{u, u, u * 1.05, u * 1.05}, 2, +1.0},  // clockwise motors (2, 3): yaw counter-clockwise
      {{u * 1.05, u * 1.05, u, u}, 2, -1.0},  // counter-clockwise motors (0, 1): yaw clockwise
  };
  for (const Case& c : cases) {
    Quadrotor q(p, airborne({0.0, 0.0, 10.0}, w));
    run(q, 0.05, c.commands);
    const Eigen::Vector3d rate = q.state().angular_velocity_rad_s;
    EXPECT_GT(c.sign * rate(c.axis), 1e-3) << "axis " << c.axis;
    for (int other = 0; other < 3; ++other) {
      if (other != c.axis) {
        EXPECT_NEAR(rate(other), 0.0, 1e-9) << "axis " << other;
      }
    }
  }
}

TEST(QuadrotorTest, DragGivesTheTerminalVelocity) {
  const QuadrotorParams p;
  Quadrotor q(p, airborne({0.0, 0.0, 3000.0}));
  run(q, 25.0, all(0.0));
  // c1 v + c2 v^2 = m g on body z (the vehicle stays level: no torques).
  const double c1 = p.linear_drag_n_s_m.z();
  const double c2 = p.quadratic_drag_n_s2_m2.z();
  const double v_terminal = (-c1 + std::sqrt(c1 * c1 + 4.0 * c2 * p.mass_kg * kG)) / (2.0 * c2);
  // The relaxation time m / (c1 + 2 c2 v) < 1 s: after 25 s the error is
  // below e^-25; semi-implicit Euler's fixed point is the exact balance.
  EXPECT_NEAR(q.state().velocity_m_s.z(), -v_terminal, 1e-6 * v_terminal);
  EXPECT_NEAR(tiltOf(q.state().orientation), 0.0, 1e-12);
  EXPECT_GT(v_terminal, 10.0);
  EXPECT_LT(v_terminal, 25.0);
}

TEST(QuadrotorTest, WindCarriesAFallingVehicleAtTheWindSpeed) {
  Quadrotor q(QuadrotorParams{}, airborne({0.0, 0.0, 3000.0}));
  q.setWindVelocity({3.0, -2.0, 0.0});
  // Near the wind speed the linear drag dominates: the relative velocity
  // decays as exp(-c1 t / m), 6 s with the defaults: e^-25 after 150 s.
  run(q, 150.0, all(0.0));
  EXPECT_NEAR(q.state().velocity_m_s.x(), 3.0, 1e-6);
  EXPECT_NEAR(q.state().velocity_m_s.y(), -2.0, 1e-6);
}

TEST(QuadrotorTest, LandedVehicleNeitherSinksNorSlides) {
  Quadrotor q(QuadrotorParams{}, airborne({1.0, 2.0, 0.0}));
  ASSERT_TRUE(q.state().landed);
  run(q, 5.0, all(0.0));
  // Thrust below the weight, a sideways push, wind: the ground holds it.
  q.setExternalForce({2.0, -1.0, -5.0});
  q.setWindVelocity({4.0, 0.0, 0.0});
  run(q, 5.0, all(0.4));  // 4 k_f (0.4 w_max)^2 ~ 7.7 N < m g
  const QuadrotorState& s = q.state();
  EXPECT_TRUE(s.landed);
  EXPECT_FALSE(s.crashed);
  EXPECT_EQ(s.position_m, Eigen::Vector3d(1.0, 2.0, 0.0));
  EXPECT_EQ(s.velocity_m_s, Eigen::Vector3d::Zero());
  EXPECT_NEAR(tiltOf(s.orientation), 0.0, 1e-12);
  EXPECT_NEAR(q.specificForceBody().z(), kG, 1e-12);
}

TEST(QuadrotorTest, LiftsOffWhenThrustExceedsWeight) {
  Quadrotor q(QuadrotorParams{});
  ASSERT_TRUE(q.state().landed);
  run(q, 1.0, all(0.7));  // thrust ~ 1.6 m g
  EXPECT_FALSE(q.state().landed);
  EXPECT_GT(q.state().position_m.z(), 0.5);
  EXPECT_GT(q.state().velocity_m_s.z(), 0.5);
}

TEST(QuadrotorTest, SoftTouchdownLands) {
  Quadrotor q(noDrag(), airborne({0.0, 0.0, 0.05}));
  QuadrotorState s = q.state();
  s.velocity_m_s = {0.5, 0.0, -1.0};
  s.orientation = Eigen::Quaterniond(Eigen::AngleAxisd(0.2, Eigen::Vector3d::UnitX()));
  q.reset(s);
  run(q, 0.5, all(0.0));
  EXPECT_TRUE(q.state().landed);
  EXPECT_FALSE(q.state().crashed);
  EXPECT_DOUBLE_EQ(q.state().position_m.z(), 0.0);
  EXPECT_EQ(q.state().velocity_m_s, Eigen::Vector3d::Zero());
  EXPECT_NEAR(tiltOf(q.state().orientation), 0.0, 1e-12);  // settled on its gear
}

TEST(QuadrotorTest, HardImpactCrashesAndTheWreckStaysPut) {
  QuadrotorState s = airborne({3.0, 4.0, 0.05});
  s.velocity_m_s = {0.0, 0.0, -5.0};
  Quadrotor q(noDrag(), s);
  run(q, 0.1, all(0.0));
  ASSERT_TRUE(q.state().crashed);
  EXPECT_EQ(q.state().crash_cause, CrashCause::kHardImpact);
  EXPECT_FALSE(q.state().landed);
  const Eigen::Vector3d wreck = q.state().position_m;
  EXPECT_DOUBLE_EQ(wreck.z(), 0.0);
  // Full commands do nothing: motors off, no motion.
  run(q, 2.0, all(1.0));
  EXPECT_EQ(q.state().position_m, wreck);
  for (double w : q.state().motor_speeds_rad_s) EXPECT_EQ(w, 0.0);
}

TEST(QuadrotorTest, ImpactJustBelowTheThresholdLands) {
  QuadrotorParams p = noDrag();
  QuadrotorState s = airborne({0.0, 0.0, 1e-3});
  s.velocity_m_s = {0.0, 0.0, -(p.crash_speed_m_s - 0.1)};
  Quadrotor q(p, s);
  run(q, 0.01, all(0.0));
  EXPECT_TRUE(q.state().landed);
  EXPECT_FALSE(q.state().crashed);
}

TEST(QuadrotorTest, TouchingDownTiltedTipsOver) {
  QuadrotorState s = airborne({0.0, 0.0, 0.05});
  s.velocity_m_s = {0.0, 0.0, -1.0};
  s.orientation = Eigen::Quaterniond(Eigen::AngleAxisd(1.3, Eigen::Vector3d::UnitY()));
  Quadrotor q(noDrag(), s);
  run(q, 0.1, all(0.0));
  EXPECT_TRUE(q.state().crashed);
  EXPECT_EQ(q.state().crash_cause, CrashCause::kTipOver);
}

// A wall filling x >= 5 m.
class Wall : public world::CollisionWorld {
 public:
  bool collides(const Eigen::Vector3d& position_m, double radius_m) const override {
    return position_m.x() + radius_m >= 5.0;
  }
};

TEST(QuadrotorTest, CollisionWithTheWorldCrashes) {
  const QuadrotorParams p;
  QuadrotorState s = airborne({0.0, 0.0, 3.0}, p.hoverMotorSpeedRadS());
  Quadrotor q(p, s);
  Wall wall;
  q.setCollisionWorld(&wall);
  Autopilot autopilot(p);
  const Setpoint east = VelocityYawRate{{2.0, 0.0, 0.0}, 0.0};
  for (int i = 0; i < 10000 && !q.state().crashed; ++i) {
    q.step(kDt, autopilot.update(q.state(), east, kDt));
  }
  ASSERT_TRUE(q.state().crashed);
  EXPECT_EQ(q.state().crash_cause, CrashCause::kCollision);
  // Detected within one step of the sphere touching the wall (< 1 cm at 2 m/s).
  EXPECT_NEAR(q.state().position_m.x(), 5.0 - p.collision_radius_m, 0.01);
  const Eigen::Vector3d wreck = q.state().position_m;
  for (int i = 0; i < 1000; ++i) q.step(kDt, autopilot.update(q.state(), east, kDt));
  EXPECT_EQ(q.state().position_m, wreck);
}

// Electrical power for steady motor speeds: sum(k_m w^3) / efficiency + avionics.
double expectedPowerW(const QuadrotorParams& p, const QuadrotorState& s) {
  double shaft = 0.0;
  for (double w : s.motor_speeds_rad_s) shaft += p.torque_coefficient_n_m_s2 * w * w * w;
  return shaft / p.propulsion_efficiency + p.avionics_power_w;
}

TEST(QuadrotorTest, BatteryDrainsFasterAtHigherThrust) {
  const QuadrotorParams p;
  Quadrotor low(p), high(p);  // both stay landed: thrust < weight
  const double t = 20.0;
  run(low, t, all(0.3));
  run(high, t, all(0.5));
  ASSERT_TRUE(high.state().landed);
  const double drain_low = 1.0 - low.state().battery_soc;
  const double drain_high = 1.0 - high.state().battery_soc;
  // Shaft power grows with w^3: (0.5 / 0.3)^3 ~ 4.6 for the motors alone.
  EXPECT_GT(drain_high, 3.0 * drain_low);
  // And each matches the energy drawn, E = P t, to the spin-up transient.
  const double capacity_j = p.battery_capacity_wh * 3600.0;
  EXPECT_NEAR(drain_low, expectedPowerW(p, low.state()) * t / capacity_j, 0.01 * drain_low);
  EXPECT_NEAR(drain_high, expectedPowerW(p, high.state()) * t / capacity_j, 0.01 * drain_high);
  // The terminal voltage sags below the open-circuit voltage under load.
  EXPECT_LT(high.state().battery_voltage_v, high.openCircuitVoltage(high.state().battery_soc));
}

TEST(QuadrotorTest, LowBatteryWeakensTheMotors) {
  QuadrotorParams p;
  p.battery_internal_resistance_ohm = 0.0;
  Quadrotor full(p);
  Quadrotor low(p);
  low.setBatteryStateOfCharge(0.1);
  run(full, 0.5, all(1.0));
  run(low, 0.5, all(1.0));
  // Full-command speed scales with the voltage: w_max V / V_full.
  const double v_low =
      p.battery_empty_voltage_v + 0.1 * (p.battery_full_voltage_v - p.battery_empty_voltage_v);
  EXPECT_LT(low.state().motor_speeds_rad_s[0], full.state().motor_speeds_rad_s[0]);
  EXPECT_NEAR(low.state().motor_speeds_rad_s[0] / full.state().motor_speeds_rad_s[0],
              v_low / p.battery_full_voltage_v, 1e-3);
}

TEST(QuadrotorTest, EmptyBatteryStopsTheMotorsAndTheVehicleFalls) {
  QuadrotorParams p;
  p.battery_capacity_wh = 0.3;  // ~1 kJ: about 6 s of hover at ~190 W
  Quadrotor q(p, airborne({0.0, 0.0, 3.0}, p.hoverMotorSpeedRadS()));
  Autopilot autopilot(p);
  const Setpoint hold = PositionYaw{{0.0, 0.0, 3.0}, 0.0};
  // While charged, the autopilot compensates the falling voltage: altitude held.
  for (int i = 0; i < 4000; ++i) q.step(kDt, autopilot.update(q.state(), hold, kDt));
  EXPECT_GT(q.state().battery_soc, 0.0);
  EXPECT_LT(q.state().battery_soc, 0.5);
  EXPECT_NEAR(q.state().position_m.z(), 3.0, 0.05);
  double soc_zero_at = -1.0;
  for (int i = 0; i < 10000 && !q.state().crashed; ++i) {
    q.step(kDt, autopilot.update(q.state(), hold, kDt));
    if (soc_zero_at < 0.0 && q.state().battery_soc == 0.0) soc_zero_at = i * kDt;
  }
  ASSERT_GE(soc_zero_at, 0.0);
  // Motors cut: it falls 3 m and hits at ~7 m/s > 3 m/s.
  EXPECT_TRUE(q.state().crashed);
  EXPECT_EQ(q.state().crash_cause, CrashCause::kHardImpact);
  for (double w : q.state().motor_speeds_rad_s) EXPECT_LT(w, 0.2 * p.hoverMotorSpeedRadS());
}

TEST(QuadrotorTest, DeadMotorLosesAttitudeAndAltitude) {
  const QuadrotorParams p;
  Quadrotor q(p, airborne({0.0, 0.0, 20.0}, p.hoverMotorSpeedRadS()));
  Autopilot autopilot(p);
  const Setpoint hold = PositionYaw{{0.0, 0.0, 20.0}, 0.0};
  for (int i = 0; i < 1000; ++i) q.step(kDt, autopilot.update(q.state(), hold, kDt));
  ASSERT_NEAR(q.state().position_m.z(), 20.0, 0.01);
  q.setMotorEfficiency(0, 0.0);
  double max_tilt = 0.0;
  for (int i = 0; i < 3000 && !q.state().crashed; ++i) {
    q.step(kDt, autopilot.update(q.state(), hold, kDt));
    max_tilt = std::max(max_tilt, tiltOf(q.state().orientation));
  }
  EXPECT_LT(q.state().motor_speeds_rad_s[0], 1e-6);  // spun down
  EXPECT_GT(max_tilt, 0.5);
  EXPECT_TRUE(q.state().crashed || q.state().position_m.z() < 19.0);
}

TEST(QuadrotorTest, ResetRespawnsAWreck) {
  QuadrotorState s = airborne({0.0, 0.0, 0.01});
  s.velocity_m_s.z() = -10.0;
  Quadrotor q(noDrag(), s);
  run(q, 0.01, all(0.0));
  ASSERT_TRUE(q.state().crashed);
  q.reset(airborne({5.0, 5.0, 0.0}));
  EXPECT_FALSE(q.state().crashed);
  EXPECT_TRUE(q.state().landed);
  run(q, 1.0, all(0.7));
  EXPECT_GT(q.state().position_m.z(), 0.5);
}

}  // namespace
}  // namespace behaviorlib::sim
