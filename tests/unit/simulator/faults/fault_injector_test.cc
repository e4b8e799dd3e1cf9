// FaultInjector with the real simulation core, quadrotor models and sensors,
// in lock-step (Simulation::advance): what each request is refused with, and
// the physical effect of motor, battery and wind faults.

#include "simulator/faults/fault_injector.h"

#include <gmock/gmock.h>
#include <google/protobuf/util/time_util.h>
#include <gtest/gtest.h>

#include <cmath>
#include <mutex>
#include <vector>

#include "simulator/service/vehicle_models.h"

namespace behaviorlib::sim {
namespace {

using google::protobuf::util::TimeUtil;
using std::chrono::milliseconds;
using std::chrono::seconds;
using ::testing::HasSubstr;

v1::InjectFailureRequest request(v1::FailureComponent component, v1::FailureType type,
                                 const std::string& robot_id = "drone1") {
  v1::InjectFailureRequest r;
  r.set_robot_id(robot_id);
  r.set_component(component);
  r.set_type(type);
  return r;
}

class FaultInjectorTest : public ::testing::Test {
 protected:
  FaultInjectorTest() {
    SensorConfig config;
    config.lidar.rate_hz = 0;
    config.camera.rate_hz = 0;
    sensors_ = std::make_unique<SensorSystem>(config, [this](SensorSample s) {
      std::lock_guard lock(mutex_);
      samples_.push_back(std::move(s));
    });
    faults_ = std::make_unique<FaultInjector>(simulation_, sensors_.get());
    simulation_.addStepListener([this](SimTime now, const std::vector<VehicleReport>& vehicles) {
      sensors_->onStep(now, vehicles, true);
    });
    reset(1);
  }

  void reset(uint64_t seed) {
    simulation_.resetVehicles(makeVehicles(world_, {"drone1", "drone2"}, seed), [&] {
      sensors_->reset(nullptr, seed);
      faults_->reset();
    });
    std::lock_guard lock(mutex_);
    samples_.clear();
  }

  /// Takes `id` off to `altitude` and leaves it hovering with no lease.
  void hover(const std::string& id, double altitude) {
    auto lease = simulation_.withPlatform(id, [](VehiclePlatform& p, SimTime now) {
      return p.acquireLease("test", seconds(10), false, now);
    });
    ASSERT_TRUE(lease.ok() && lease->ok());
    const std::string lease_id = (*lease)->lease_id();
    auto took_off = simulation_.withPlatform(id, [&](VehiclePlatform& p, SimTime now) {
      return p.executeAction(v1::FLIGHT_ACTION_TAKE_OFF, lease_id, altitude, false, now);
    });
    ASSERT_TRUE(took_off.ok() && took_off->ok());
    for (int i = 0; i < 200 && state(id).second != v1::FLIGHT_STATE_HOVERING; ++i) {
      simulation_.advance(milliseconds(50));
    }
    ASSERT_EQ(state(id).second, v1::FLIGHT_STATE_HOVERING);
    auto released = simulation_.withPlatform(
        id, [&](VehiclePlatform& p, SimTime now) { return p.releaseLease(lease_id, now); });
    ASSERT_TRUE(released.ok() && released->ok());
    simulation_.advance(seconds(3));  // settle
  }

  std::pair<VehicleSnapshot, v1::FlightState> state(const std::string& id = "drone1") {
    auto s = simulation_.vehicleState(id);
    EXPECT_TRUE(s.ok()) << s.status();
    return s.ok() ? *s : std::pair<VehicleSnapshot, v1::FlightState>{};
  }

  std::vector<SensorSample> samples(SensorKind kind) {
    std::lock_guard lock(mutex_);
    std::vector<SensorSample> out;
    for (const auto& s : samples_) {
      if (s.kind == kind && s.robot_id == "drone1") out.push_back(s);
    }
    return out;
  }

  world::World world_;
  Simulation simulation_{SimulationOptions{}};
  std::mutex mutex_;
  std::vector<SensorSample> samples_;
  std::unique_ptr<SensorSystem> sensors_;
  std::unique_ptr<FaultInjector> faults_;
};

struct Refused {
  std::string what;
  std::function<void(v1::InjectFailureRequest&)> change;
  absl::StatusCode code;
  std::string message;
};

TEST_F(FaultInjectorTest, BadRequestsAreRefusedSayingWhatIsAccepted) {
  const std::vector<Refused> cases = {
      {"no component", [](auto& r) { r.set_component(v1::FAILURE_COMPONENT_UNSPECIFIED); },
       absl::StatusCode::kInvalidArgument, "component must be one of FAILURE_COMPONENT_GPS"},
      {"unknown component", [](auto& r) { r.set_component(static_cast<v1::FailureComponent>(42)); },
       absl::StatusCode::kInvalidArgument, "got 42"},
      {"no type", [](auto& r) { r.set_type(v1::FAILURE_TYPE_UNSPECIFIED); },
       absl::StatusCode::kInvalidArgument, "FAILURE_TYPE_OK clears a failure"},
      {"unknown type", [](auto& r) { r.set_type(static_cast<v1::FailureType>(77)); },
       absl::StatusCode::kInvalidArgument, "got 77"},
      {"unknown vehicle", [](auto& r) { r.set_robot_id("drone9"); }, absl::StatusCode::kNotFound,
       "the world has: drone1, drone2"},
      {"no vehicle", [](auto& r) { r.clear_robot_id(); }, absl::StatusCode::kInvalidArgument,
       "robot_id is required"},
      {"intensity above 1", [](auto& r) { r.set_intensity(1.5); },
       absl::StatusCode::kInvalidArgument, "intensity must be within [0, 1], got 1.5"},
      {"negative intensity", [](auto& r) { r.set_intensity(-0.1); },
       absl::StatusCode::kInvalidArgument, "intensity must be within [0, 1]"},
      {"NaN intensity", [](auto& r) { r.set_intensity(std::nan("")); },
       absl::StatusCode::kInvalidArgument, "intensity must be within [0, 1]"},
      {"noisy without intensity", [](auto& r) { r.set_type(v1::FAILURE_TYPE_NOISY); },
       absl::StatusCode::kInvalidArgument, "FAILURE_TYPE_NOISY needs an intensity in (0, 1]"},
      {"intermittent without intensity", [](auto& r) { r.set_type(v1::FAILURE_TYPE_INTERMITTENT); },
       absl::StatusCode::kInvalidArgument, "FAILURE_TYPE_INTERMITTENT needs an intensity"},
      {"negative delay",
       [](auto& r) {
         r.set_type(v1::FAILURE_TYPE_DELAYED);
         *r.mutable_delay() = TimeUtil::MillisecondsToDuration(-200);
       },
       absl::StatusCode::kInvalidArgument, "delay must not be negative, got -0.200s"},
      {"delayed without delay", [](auto& r) { r.set_type(v1::FAILURE_TYPE_DELAYED); },
       absl::StatusCode::kInvalidArgument, "FAILURE_TYPE_DELAYED needs a delay in (0, 10 s]"},
      {"delay too long",
       [](auto& r) {
         r.set_type(v1::FAILURE_TYPE_DELAYED);
         *r.mutable_delay() = TimeUtil::SecondsToDuration(11);
       },
       absl::StatusCode::kInvalidArgument, "got 11s"},
      {"degraded gps",
       [](auto& r) {
         r.set_type(v1::FAILURE_TYPE_DEGRADED);
         r.set_intensity(0.5);
       },
       absl::StatusCode::kInvalidArgument,
       "FAILURE_COMPONENT_GPS accepts FAILURE_TYPE_OFF, _STUCK, _NOISY, _GARBAGE, _INTERMITTENT, "
       "_DELAYED or _OK, not FAILURE_TYPE_DEGRADED"},
      {"stuck wind", [](auto& r) { r.set_component(v1::FAILURE_COMPONENT_WIND); },
       absl::StatusCode::kInvalidArgument,
       "FAILURE_COMPONENT_WIND accepts FAILURE_TYPE_SET (wind_velocity_m_s, gust_stddev_m_s) or "
       "FAILURE_TYPE_OK (calm), not FAILURE_TYPE_STUCK"},
      {"stuck motor", [](auto& r) { r.set_component(v1::FAILURE_COMPONENT_MOTOR); },
       absl::StatusCode::kInvalidArgument,
       "FAILURE_COMPONENT_MOTOR accepts FAILURE_TYPE_OFF (stops), FAILURE_TYPE_DEGRADED"},
      {"motor out of range",
       [](auto& r) {
         r.set_component(v1::FAILURE_COMPONENT_MOTOR);
         r.set_type(v1::FAILURE_TYPE_OFF);
         r.set_motor_index(4);
       },
       absl::StatusCode::kInvalidArgument,
       "motor_index must be within 0..3 (drone1 has 4 motors), got 4"},
      {"too much wind",
       [](auto& r) {
         r.set_component(v1::FAILURE_COMPONENT_WIND);
         r.set_type(v1::FAILURE_TYPE_SET);
         r.mutable_wind_velocity_m_s()->set_x(40);
       },
       absl::StatusCode::kInvalidArgument, "wind_velocity_m_s must be finite and at most 30 m/s"},
      {"negative gusts",
       [](auto& r) {
         r.set_component(v1::FAILURE_COMPONENT_WIND);
         r.set_type(v1::FAILURE_TYPE_SET);
         r.set_gust_stddev_m_s(-1);
       },
       absl::StatusCode::kInvalidArgument, "gust_stddev_m_s must be within [0, 10], got -1"},
      {"battery set",
       [](auto& r) {
         r.set_component(v1::FAILURE_COMPONENT_BATTERY);
         r.set_type(v1::FAILURE_TYPE_SET);
       },
       absl::StatusCode::kInvalidArgument, "(and _DEGRADED: loss of charge)"},
  };
  for (const Refused& c : cases) {
    SCOPED_TRACE(c.what);
    v1::InjectFailureRequest r = request(v1::FAILURE_COMPONENT_GPS, v1::FAILURE_TYPE_STUCK);
    c.change(r);
    const absl::Status s = faults_->inject(r);
    EXPECT_EQ(s.code(), c.code) << s;
    EXPECT_THAT(std::string(s.message()), HasSubstr(c.message));
  }
  // Nothing was applied.
  for (const auto& active : faults_->active()) EXPECT_EQ(active.count, 0) << active.component;
  EXPECT_EQ(sensors_->fault("drone1", SensorKind::kGps).type, SensorFaultType::kOk);
}

TEST_F(FaultInjectorTest, SensorFaultsNeedSensors) {
  FaultInjector without(simulation_, nullptr);
  const absl::Status s = without.inject(request(v1::FAILURE_COMPONENT_IMU, v1::FAILURE_TYPE_OFF));
  EXPECT_EQ(s.code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(std::string(s.message()), HasSubstr("--channel"));
  // Physical faults do not.
  v1::InjectFailureRequest motor = request(v1::FAILURE_COMPONENT_MOTOR, v1::FAILURE_TYPE_OFF);
  EXPECT_TRUE(without.inject(motor).ok());
}

TEST_F(FaultInjectorTest, ASensorFaultActsFromTheCurrentSimulatedTime) {
  simulation_.advance(seconds(1));
  ASSERT_TRUE(faults_->inject(request(v1::FAILURE_COMPONENT_GPS, v1::FAILURE_TYPE_OFF)).ok());
  v1::InjectFailureRequest speed =
      request(v1::FAILURE_COMPONENT_LINEAR_SPEED, v1::FAILURE_TYPE_INTERMITTENT);
  speed.set_intensity(1.0);
  ASSERT_TRUE(faults_->inject(speed).ok());
  simulation_.advance(seconds(1));
  const auto gps = samples(SensorKind::kGps);
  ASSERT_EQ(gps.size(), 10u);
  EXPECT_EQ(gps.back().stamp, seconds(1));
  EXPECT_EQ(samples(SensorKind::kLinearSpeed).size(), 30u);
  EXPECT_EQ(samples(SensorKind::kImu).size(), 400u) << "other sensors are untouched";
  std::map<std::string, int> active;
  for (const auto& a : faults_->active()) active[a.component] = a.count;
  EXPECT_EQ(active["gps"], 1);
  EXPECT_EQ(active["linear_speed"], 1);

  ASSERT_TRUE(faults_->inject(request(v1::FAILURE_COMPONENT_GPS, v1::FAILURE_TYPE_OK)).ok());
  simulation_.advance(seconds(1));
  EXPECT_EQ(samples(SensorKind::kGps).size(), 20u);
  for (const auto& a : faults_->active()) {
    if (a.component == "gps") {
      EXPECT_EQ(a.count, 0);
    }
  }
}

TEST_F(FaultInjectorTest, AMotorOffWhileHoveringBringsTheVehicleDown) {
  hover("drone1", 3.0);
  hover("drone2", 3.0);
  ASSERT_NEAR(state("drone1").first.position_m.z(), 3.0, 0.2);
  v1::InjectFailureRequest off = request(v1::FAILURE_COMPONENT_MOTOR, v1::FAILURE_TYPE_OFF);
  off.set_motor_index(0);
  ASSERT_TRUE(faults_->inject(off).ok());
  simulation_.advance(milliseconds(1000));
  EXPECT_LT(state("drone1").first.position_m.z(), 2.0) << "lost altitude within 1 s";
  simulation_.advance(seconds(4));
  EXPECT_TRUE(state("drone1").first.crashed) << "as a real quadrotor with three motors";
  EXPECT_FALSE(state("drone2").first.crashed);
  EXPECT_NEAR(state("drone2").first.position_m.z(), 3.0, 0.2) << "other vehicles fly on";
  std::map<std::string, int> active;
  for (const auto& a : faults_->active()) active[a.robot_id + "/" + a.component] = a.count;
  EXPECT_EQ(active["drone1/motor"], 1);
}

TEST_F(FaultInjectorTest, ADegradedMotorIsCompensatedAndOkRestoresIt) {
  hover("drone1", 2.0);
  v1::InjectFailureRequest weak = request(v1::FAILURE_COMPONENT_MOTOR, v1::FAILURE_TYPE_DEGRADED);
  weak.set_motor_index(2);
  weak.set_intensity(0.2);
  ASSERT_TRUE(faults_->inject(weak).ok());
  simulation_.advance(seconds(5));
  EXPECT_FALSE(state().first.crashed);
  EXPECT_NEAR(state().first.position_m.z(), 2.0, 0.3) << "the autopilot compensates 20 %";
  weak.set_type(v1::FAILURE_TYPE_OK);
  ASSERT_TRUE(faults_->inject(weak).ok());
  for (const auto& a : faults_->active()) EXPECT_EQ(a.count, 0) << a.component;
}

TEST_F(FaultInjectorTest, ABatteryFaultDropsTheChargeAtOnce) {
  hover("drone1", 2.0);
  const double before = state().first.battery_ratio;
  v1::InjectFailureRequest drop = request(v1::FAILURE_COMPONENT_BATTERY, v1::FAILURE_TYPE_DEGRADED);
  drop.set_intensity(0.4);
  ASSERT_TRUE(faults_->inject(drop).ok());
  simulation_.advance(milliseconds(1000));
  const double after = state().first.battery_ratio;
  EXPECT_NEAR(before - after, 0.4, 0.01) << "hovering drains ~0.1 % a second besides";
  // The battery monitor reports it.
  const auto battery = samples(SensorKind::kBattery);
  ASSERT_FALSE(battery.empty());
  EXPECT_NEAR(std::get<BatteryData>(battery.back().data).charge_ratio, after, 0.005);
  // Not below empty.
  drop.set_intensity(1.0);
  ASSERT_TRUE(faults_->inject(drop).ok());
  EXPECT_EQ(state().first.battery_ratio, 0.0);
}

TEST_F(FaultInjectorTest, WindTiltsAPositionHoldAndGustsAreReproducible) {
  hover("drone1", 2.0);
  const VehicleSnapshot calm = state().first;
  const Eigen::Vector3d calm_body_z = calm.orientation * Eigen::Vector3d::UnitZ();
  EXPECT_NEAR(calm_body_z.x(), 0.0, 0.01);

  v1::InjectFailureRequest wind = request(v1::FAILURE_COMPONENT_WIND, v1::FAILURE_TYPE_SET, "");
  wind.mutable_wind_velocity_m_s()->set_x(5.0);  // towards the east
  ASSERT_TRUE(faults_->inject(wind).ok());
  EXPECT_EQ(simulation_.wind().velocity_m_s.x(), 5.0);
  simulation_.advance(milliseconds(500));
  EXPECT_GT(state().first.position_m.x() - calm.position_m.x(), 0.05) << "pushed east at first";
  const double pushed = state().first.position_m.x() - calm.position_m.x();
  simulation_.advance(seconds(30));
  const VehicleSnapshot held = state().first;
  // The position hold wins (the velocity loop's integrator learns the drag
  // its feed-forward cannot see): back near its place, leaning into the wind
  // (drag 2.25 N at 5 m/s against 14.7 N of weight: ~8.7 degrees, thrust
  // westward).
  EXPECT_LT(std::abs(held.position_m.x() - calm.position_m.x()), 0.5 * pushed);
  EXPECT_NEAR(held.position_m.x(), calm.position_m.x(), 0.1);
  EXPECT_NEAR(held.position_m.z(), 2.0, 0.15);
  const Eigen::Vector3d body_z = held.orientation * Eigen::Vector3d::UnitZ();
  EXPECT_NEAR(std::asin(-body_z.x()), std::atan(2.25 / (1.5 * 9.81)), 0.03);

  // Gusts: the same seed and requests give the same flight, bit for bit.
  auto gusty = [&](uint64_t seed) {
    reset(seed);
    hover("drone1", 2.0);
    v1::InjectFailureRequest gusts = request(v1::FAILURE_COMPONENT_WIND, v1::FAILURE_TYPE_SET, "");
    gusts.set_gust_stddev_m_s(2.0);
    EXPECT_TRUE(faults_->inject(gusts).ok());
    std::vector<double> xs;
    for (int i = 0; i < 50; ++i) {
      simulation_.advance(milliseconds(100));
      xs.push_back(state().first.position_m.x());
    }
    return xs;
  };
  const auto a = gusty(3);
  const auto b = gusty(3);
  const auto c = gusty(4);
  EXPECT_EQ(a, b);
  EXPECT_NE(a, c);
  double spread = 0.0;
  for (double x : a) spread = std::max(spread, std::abs(x - a.front()));
  EXPECT_GT(spread, 0.02) << "the gusts move the vehicle";

  // Reset calms the wind and forgets the faults.
  reset(3);
  EXPECT_EQ(simulation_.wind().gust_stddev_m_s, 0.0);
  for (const auto& active : faults_->active()) EXPECT_EQ(active.count, 0) << active.component;
}

}  // namespace
}  // namespace behaviorlib::sim
