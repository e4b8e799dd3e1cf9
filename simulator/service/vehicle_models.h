#pragma once

// The physics behind each simulated vehicle: the quadrotor dynamics with its
// autopilot (simulator/dynamics), adapted to the Simulation's VehicleModel;
// and the vehicles of a world file.

#include <Eigen/Core>
#include <cstdint>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "formats/world/world.h"
#include "simulator/core/simulation.h"

namespace behaviorlib::sim {

/// A quadrotor with default parameters, landed at `start_position_m` facing
/// `yaw_rad`; it crashes on `world`'s surfaces when given one (which must
/// outlive it). Its faults: four motors, a battery that can lose charge, the
/// wind with gusts drawn from `gust_seed` (see gustSeed()).
std::unique_ptr<VehicleModel> makeQuadrotorModel(const Eigen::Vector3d& start_position_m,
                                                 double yaw_rad = 0.0,
                                                 const world::CollisionWorld* world = nullptr,
                                                 uint64_t gust_seed = 1);

/// One quadrotor per start pose of `world`; or, when the world has none, one
/// per id of `fallback_ids`, landed at x = 2 i m. `seed` is the run's seed
/// (each vehicle's gusts are seeded from it and the robot id).
std::map<std::string, std::unique_ptr<VehicleModel>> makeVehicles(
    const world::World& world, const std::vector<std::string>& fallback_ids, uint64_t seed = 1);

/// Where a world's name comes from: the simulator's own configuration (its
/// --world flag: any path the operator chose) or a request (Reset), which
/// may name only files inside worlds_dir.
enum class WorldSource { kConfiguration, kRequest };

/// Loads a world by path, or by the name of a shipped world ("rooms" ->
/// `<worlds_dir>/rooms.yaml`). The error names the file, the line and the
/// problem; for a request, a path outside worlds_dir is PERMISSION_DENIED
/// naming worlds_dir.
absl::StatusOr<world::World> loadWorldByName(const std::string& world,
                                             const std::string& worlds_dir,
                                             WorldSource source = WorldSource::kConfiguration);

}  // namespace behaviorlib::sim
