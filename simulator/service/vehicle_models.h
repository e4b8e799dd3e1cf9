#pragma once

// The physics behind each simulated vehicle: the quadrotor dynamics with its
// autopilot (simulator/dynamics), adapted to the Simulation's VehicleModel.

#include <Eigen/Core>
#include <memory>

#include "simulator/core/simulation.h"

namespace behaviorlib::sim {

/// A quadrotor with default parameters, landed at `start_position_m`.
std::unique_ptr<VehicleModel> makeQuadrotorModel(const Eigen::Vector3d& start_position_m);

}  // namespace behaviorlib::sim
