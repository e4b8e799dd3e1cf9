#include "simulator/service/vehicle_models.h"

#include <cmath>

#include "behaviorlib/server_kit/confined_files.h"
#include "simulator/dynamics/autopilot.h"
#include "simulator/dynamics/gust.h"
#include "simulator/dynamics/quadrotor.h"

namespace behaviorlib::sim {
namespace {

// Translates the platform's command into the autopilot's setpoint.
Setpoint toSetpoint(const PlatformCommand& c) {
  switch (c.kind) {
    case PlatformCommand::Kind::kThrustRates:
      return ThrustRates{c.thrust_ratio, c.vector};
    case PlatformCommand::Kind::kAttitudeThrust:
      return AttitudeThrust{c.orientation, c.thrust_ratio};
    case PlatformCommand::Kind::kVelocityYawRate:
      return VelocityYawRate{c.vector, c.yaw_rate_rad_s};
    case PlatformCommand::Kind::kPositionYaw:
      return PositionYaw{c.vector, c.yaw_rad};
    case PlatformCommand::Kind::kIdle:
      break;
  }
  return Idle{};
}

// The rigid-body quadrotor flown by the simulator's autopilot.
class QuadrotorModel final : public VehicleModel {
 public:
  QuadrotorModel(const Eigen::Vector3d& start, double yaw_rad, const world::CollisionWorld* world,
                 uint64_t gust_seed)
      : quadrotor_(QuadrotorParams{}, initialState(start, yaw_rad)),
        autopilot_(QuadrotorParams{}),
        gusts_(gust_seed) {
    if (world) quadrotor_.setCollisionWorld(world);
  }

  void command(const PlatformCommand& command) override { setpoint_ = toSetpoint(command); }
  void step(double dt_s) override {
    if (wind_.gust_stddev_m_s > 0.0) {
      quadrotor_.setWindVelocity(
          wind_.velocity_m_s + gusts_.step(dt_s, wind_.gust_stddev_m_s, kDefaultGustTimeConstantS));
    }
    quadrotor_.step(dt_s, autopilot_.update(quadrotor_.state(), setpoint_, dt_s));
  }

  int motorCount() const override { return kMotorCount; }
  void setMotorEfficiency(int motor, double efficiency) override {
    quadrotor_.setMotorEfficiency(motor, efficiency);
  }
  void dropBatteryCharge(double ratio) override {
    quadrotor_.setBatteryStateOfCharge(quadrotor_.state().battery_soc - ratio);
  }
  void setWind(const Wind& wind) override {
    wind_ = wind;
    // Steady wind (or calm): the gusts restart from zero when turned on again.
    if (wind_.gust_stddev_m_s <= 0.0) {
      gusts_.step(0.0, 0.0, kDefaultGustTimeConstantS);
      quadrotor_.setWindVelocity(wind_.velocity_m_s);
    }
  }
  VehicleSnapshot snapshot() const override {
    const QuadrotorState& s = quadrotor_.state();
    VehicleSnapshot out;
    out.position_m = s.position_m;
    out.velocity_m_s = s.velocity_m_s;
    out.orientation = s.orientation;
    out.angular_velocity_rad_s = s.angular_velocity_rad_s;
    const Eigen::Vector3d forward = s.orientation * Eigen::Vector3d::UnitX();
    out.yaw_rad = std::atan2(forward.y(), forward.x());
    out.on_ground = s.landed;
    out.crashed = s.crashed;
    out.battery_ratio = s.battery_soc;
    out.acceleration_m_s2 = s.acceleration_m_s2;
    out.battery_voltage_v = s.battery_voltage_v;
    // The battery model draws I = P / V_open_circuit (Quadrotor::updateBattery).
    const double open_circuit_v = quadrotor_.openCircuitVoltage(s.battery_soc);
    out.battery_current_a = open_circuit_v > 0.0 ? s.battery_power_w / open_circuit_v : 0.0;
    return out;
  }

 private:
  static QuadrotorState initialState(const Eigen::Vector3d& start, double yaw_rad) {
    QuadrotorState state;
    state.position_m = start;
    state.orientation = Eigen::Quaterniond(Eigen::AngleAxisd(yaw_rad, Eigen::Vector3d::UnitZ()));
    state.landed = true;
    return state;
  }

  Quadrotor quadrotor_;
  Autopilot autopilot_;
  Setpoint setpoint_ = Idle{};
  Wind wind_;
  GustModel gusts_;
};

}  // namespace

std::unique_ptr<VehicleModel> makeQuadrotorModel(const Eigen::Vector3d& start_position_m,
                                                 double yaw_rad, const world::CollisionWorld* world,
                                                 uint64_t gust_seed) {
  return std::make_unique<QuadrotorModel>(start_position_m, yaw_rad, world, gust_seed);
}

std::map<std::string, std::unique_ptr<VehicleModel>> makeVehicles(
    const world::World& world, const std::vector<std::string>& fallback_ids, uint64_t seed) {
  std::map<std::string, std::unique_ptr<VehicleModel>> vehicles;
  for (const auto& start : world.startPoses()) {
    vehicles[start.robot_id] =
        makeQuadrotorModel(start.position_m, start.yaw_rad, &world, gustSeed(seed, start.robot_id));
  }
  if (vehicles.empty()) {
    for (size_t i = 0; i < fallback_ids.size(); ++i) {
      vehicles[fallback_ids[i]] =
          makeQuadrotorModel(Eigen::Vector3d(2.0 * static_cast<double>(i), 0, 0), 0.0, &world,
                             gustSeed(seed, fallback_ids[i]));
    }
  }
  return vehicles;
}

absl::StatusOr<world::World> loadWorldByName(const std::string& world,
                                             const std::string& worlds_dir, WorldSource source) {
  const bool is_name = world.find('/') == std::string::npos &&
                       (world.size() < 5 || world.substr(world.size() - 5) != ".yaml");
  if (source == WorldSource::kConfiguration) {
    return world::loadWorld(is_name ? worlds_dir + "/" + world + ".yaml" : world);
  }
  absl::StatusOr<server_kit::ConfinedDirectory> dir =
      server_kit::ConfinedDirectory::open("worlds", worlds_dir, world::kMaxWorldFileBytes);
  if (!dir.ok()) return dir.status();
  absl::StatusOr<std::string> text = dir->read(is_name ? world + ".yaml" : world);
  if (!text.ok()) return text.status();
  return world::parseWorld(*text, world);
}

}  // namespace behaviorlib::sim
