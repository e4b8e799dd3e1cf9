#pragma once

// Fault injection into the simulator for integration tests (the simulator
// must run with --enable-fault-injection):
//
//   ASSERT_TRUE(sim_faults::inject(simulator.address(), "drone1",
//                                  v1::FAILURE_COMPONENT_LIDAR, v1::FAILURE_TYPE_OFF).ok());

#include <grpcpp/grpcpp.h>

#include <chrono>
#include <string>

#include "behaviorlib/v1/simulator.grpc.pb.h"

namespace sim_faults {

/// One InjectFailure call (5 s deadline); FAILURE_TYPE_OK clears the fault.
inline grpc::Status inject(const std::string& simulator_address, const std::string& robot_id,
                           behaviorlib::v1::FailureComponent component,
                           behaviorlib::v1::FailureType type) {
  auto simulator = behaviorlib::v1::Simulator::NewStub(
      grpc::CreateChannel(simulator_address, grpc::InsecureChannelCredentials()));
  behaviorlib::v1::InjectFailureRequest request;
  request.set_robot_id(robot_id);
  request.set_component(component);
  request.set_type(type);
  behaviorlib::v1::InjectFailureResponse response;
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(5));
  return simulator->InjectFailure(&context, request, &response);
}

}  // namespace sim_faults
