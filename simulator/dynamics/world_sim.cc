#include "simulator/dynamics/world_sim.h"

#include <cmath>
#include <utility>

namespace behaviorlib::sim {

SimVehicle::SimVehicle(std::string robot_id, const QuadrotorParams& params,
                       const QuadrotorState& initial, const AutopilotParams& autopilot,
                       std::uint64_t seed)
    : robot_id_(std::move(robot_id)),
      quadrotor_(params, initial),
      autopilot_(params, autopilot),
      gusts_(seed) {}

void SimVehicle::step(double dt_s, const WorldSimOptions& options) {
  quadrotor_.setWindVelocity(options.wind_m_s +
                             gusts_.step(dt_s, options.gust_std_m_s, options.gust_time_constant_s));
  commands_ = autopilot_.update(quadrotor_.state(), setpoint_, dt_s);
  quadrotor_.step(dt_s, commands_);
}

WorldSim::WorldSim(WorldSimOptions options) : options_(std::move(options)) {}

SimVehicle* WorldSim::addVehicle(const std::string& robot_id, const QuadrotorState& initial,
                                 const QuadrotorParams& params, const AutopilotParams& autopilot) {
  if (robot_id.empty() || vehicles_.count(robot_id) > 0) return nullptr;
  const std::uint64_t seed = gustSeed(options_.seed, robot_id);
  auto vehicle = std::make_unique<SimVehicle>(robot_id, params, initial, autopilot, seed);
  vehicle->quadrotor().setCollisionWorld(collision_world_);
  vehicle->quadrotor().setWindVelocity(options_.wind_m_s);
  SimVehicle* raw = vehicle.get();
  vehicles_.emplace(robot_id, std::move(vehicle));
  return raw;
}

bool WorldSim::removeVehicle(const std::string& robot_id) { return vehicles_.erase(robot_id) > 0; }

SimVehicle* WorldSim::vehicle(const std::string& robot_id) {
  const auto it = vehicles_.find(robot_id);
  return it == vehicles_.end() ? nullptr : it->second.get();
}

const SimVehicle* WorldSim::vehicle(const std::string& robot_id) const {
  const auto it = vehicles_.find(robot_id);
  return it == vehicles_.end() ? nullptr : it->second.get();
}

std::vector<std::string> WorldSim::robotIds() const {
  std::vector<std::string> ids;
  ids.reserve(vehicles_.size());
  for (const auto& [id, vehicle] : vehicles_) ids.push_back(id);
  return ids;
}

bool WorldSim::setSetpoint(const std::string& robot_id, const Setpoint& setpoint) {
  SimVehicle* v = vehicle(robot_id);
  if (v == nullptr) return false;
  v->setSetpoint(setpoint);
  return true;
}

void WorldSim::step(double dt_s) {
  if (dt_s <= 0.0) return;
  for (auto& [id, vehicle] : vehicles_) vehicle->step(dt_s, options_);
  time_ns_ += std::llround(dt_s * 1e9);
  ++step_count_;
}

void WorldSim::advance(double duration_s) {
  const long long steps = std::llround(duration_s / options_.physics_step_s);
  for (long long i = 0; i < steps; ++i) step();
}

void WorldSim::setCollisionWorld(const world::CollisionWorld* world) {
  collision_world_ = world;
  for (auto& [id, vehicle] : vehicles_) vehicle->quadrotor().setCollisionWorld(world);
}

}  // namespace behaviorlib::sim
