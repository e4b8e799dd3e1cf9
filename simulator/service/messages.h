#pragma once

// The simulator's published messages, built in one place: the ground-truth
// VehicleState and the platform's FlightStatus of one vehicle.

#include <string>

#include "behaviorlib/v1/platform.pb.h"
#include "behaviorlib/v1/simulator.pb.h"
#include "simulator/core/simulation.h"

namespace behaviorlib::sim {

/// Ground truth of a vehicle (header: simulated time, frame "world").
v1::VehicleState vehicleStateMessage(const std::string& robot_id, SimTime now,
                                     const VehicleReport& report);

/// The platform's status of a vehicle (header: simulated time, frame "world").
v1::FlightStatus flightStatusMessage(const std::string& robot_id, SimTime now,
                                     const VehiclePlatform& platform, double battery_ratio);

}  // namespace behaviorlib::sim
