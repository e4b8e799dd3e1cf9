#pragma once

// The FlightController gRPC service over a Simulation: each call runs on the
// vehicle's VehiclePlatform under the simulation's mutex. Flight-state
// watchers are fed by a step listener (latest status per vehicle; a slow
// watcher skips intermediate states but never blocks the physics).

#include <grpcpp/grpcpp.h>

#include <map>
#include <memory>
#include <mutex>
#include <set>
#include <string>

#include "behaviorlib/server_kit/access_policy.h"
#include "behaviorlib/v1/platform.grpc.pb.h"
#include "simulator/core/simulation.h"
#include "simulator/service/latest_writer.h"
#include "simulator/service/setpoint_barrier.h"

namespace behaviorlib::sim {

using FlightStatusWatcher = LatestWriter<v1::WatchFlightStateResponse>;

class FlightControllerService final : public v1::FlightController::CallbackService {
 public:
  explicit FlightControllerService(Simulation& simulation);
  ~FlightControllerService() override;

  /// Ends every WatchFlightState and StreamSetpoints stream (shutdown).
  void shutdown();
  /// The deterministic mode: what StreamSetpoints calls that name a ledger
  /// key read is counted in `barrier` (set before serving).
  void setSetpointBarrier(SetpointBarrier* barrier) { setpoint_barrier_ = barrier; }
  SetpointBarrier* setpointBarrier() const { return setpoint_barrier_; }

  grpc::ServerUnaryReactor* AcquireLease(grpc::CallbackServerContext* context,
                                         const v1::AcquireLeaseRequest* request,
                                         v1::AcquireLeaseResponse* response) override;
  grpc::ServerUnaryReactor* RenewLease(grpc::CallbackServerContext* context,
                                       const v1::RenewLeaseRequest* request,
                                       v1::RenewLeaseResponse* response) override;
  grpc::ServerUnaryReactor* ReleaseLease(grpc::CallbackServerContext* context,
                                         const v1::ReleaseLeaseRequest* request,
                                         v1::ReleaseLeaseResponse* response) override;
  grpc::ServerUnaryReactor* ExecuteFlightAction(grpc::CallbackServerContext* context,
                                                const v1::ExecuteFlightActionRequest* request,
                                                v1::ExecuteFlightActionResponse* response) override;
  grpc::ServerUnaryReactor* SendSetpoint(grpc::CallbackServerContext* context,
                                         const v1::SetpointRequest* request,
                                         v1::SendSetpointResponse* response) override;
  grpc::ServerReadReactor<v1::SetpointRequest>* StreamSetpoints(
      grpc::CallbackServerContext* context, v1::StreamSetpointsResponse* response) override;
  grpc::ServerWriteReactor<v1::WatchFlightStateResponse>* WatchFlightState(
      grpc::CallbackServerContext* context, const v1::WatchFlightStateRequest* request) override;

  /// Applies one setpoint (shared by SendSetpoint and StreamSetpoints).
  // Refused for a caller bound to another robot (`scope`).
  absl::StatusOr<v1::FlightState> applySetpoint(const v1::SetpointRequest& request,
                                                const server_kit::RobotScope& scope);

 private:
  void removeWatcher(FlightStatusWatcher* watcher);

  SetpointBarrier* setpoint_barrier_ = nullptr;

  Simulation& simulation_;
  std::mutex watchers_mutex_;
  std::set<FlightStatusWatcher*> watchers_;
  std::map<std::string, v1::FlightStatus> last_status_;
  bool shutting_down_ = false;
};

}  // namespace behaviorlib::sim
