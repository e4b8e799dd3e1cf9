#pragma once

// Client of the platform interface (behaviorlib.v1.FlightController, served by
// the simulator or an autopilot bridge): blocking calls with a bounded wall
// deadline, each failure an absl::Status whose message names the flight
// controller's address, so that a behavior can say why it cannot fly.
//
//   behaviorlib::platform::FlightControllerClient fc("127.0.0.1:50070", "drone1");
//   auto lease = behaviorlib::platform::LeaseKeeper::acquire(fc, clock, "drone1/TAKE_OFF");
//   if (!lease.ok()) return lease.status();          // e.g. UNAVAILABLE: simulator not up
//   auto state = fc.executeFlightAction((*lease)->id(), v1::FLIGHT_ACTION_TAKE_OFF, 1.5);
//   behaviorlib::platform::FlightStateWatcher watcher(fc);   // WatchFlightState in the background
//   absl::StatusOr<v1::FlightStatus> status = watcher.latest();
//
// Deadlines are wall time (RPC deadlines never follow simulated time); keep
// them well under a behavior's watchdog timeout, since behaviors call these
// from their user functions.

#include <grpcpp/grpcpp.h>

#include <chrono>
#include <memory>
#include <string>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "behaviorlib/v1/platform.grpc.pb.h"

namespace behaviorlib::platform {

struct FlightControllerClientOptions {
  /// Wall-time deadline of each unary call.
  std::chrono::milliseconds call_timeout{400};
};

/// A connection to one FlightController for one vehicle. Thread-safe.
class FlightControllerClient {
 public:
  /// `address` is "host:port" (the connection is made lazily); `robot_id`
  /// the vehicle every call names.
  FlightControllerClient(std::string address, std::string robot_id,
                         FlightControllerClientOptions options = {});
  FlightControllerClient(const FlightControllerClient&) = delete;
  FlightControllerClient& operator=(const FlightControllerClient&) = delete;

  const std::string& address() const { return address_; }
  const std::string& robotId() const { return robot_id_; }
  v1::FlightController::Stub& stub() const { return *stub_; }

  absl::StatusOr<v1::AcquireLeaseResponse> acquireLease(const std::string& holder,
                                                        std::chrono::nanoseconds ttl,
                                                        bool preempt) const;
  absl::StatusOr<v1::RenewLeaseResponse> renewLease(const std::string& lease_id) const;
  absl::Status releaseLease(const std::string& lease_id) const;
  /// TAKE_OFF, LAND, HOVER (need the lease), EMERGENCY_LAND, KILL (confirm).
  /// Returns the flight state right after the platform accepted it.
  absl::StatusOr<v1::FlightState> executeFlightAction(const std::string& lease_id,
                                                      v1::FlightAction action,
                                                      double takeoff_altitude_m = 0.0,
                                                      bool confirm = false) const;
  /// Sends one setpoint (robot_id and lease_id are filled in).
  absl::StatusOr<v1::FlightState> sendSetpoint(const std::string& lease_id,
                                               v1::SetpointRequest setpoint) const;
  /// A position + yaw setpoint (world frame ENU, yaw CCW from +x).
  absl::StatusOr<v1::FlightState> sendPositionSetpoint(const std::string& lease_id, double x_m,
                                                       double y_m, double z_m,
                                                       double yaw_rad) const;

  /// A grpc::Status as an absl::Status whose message says which call to
  /// which flight controller failed.
  absl::Status describe(const grpc::Status& status, const char* call) const;

 private:
  std::unique_ptr<grpc::ClientContext> context() const;

  std::string address_;
  std::string robot_id_;
  FlightControllerClientOptions options_;
  std::shared_ptr<grpc::Channel> channel_;
  std::unique_ptr<v1::FlightController::Stub> stub_;
};

/// "TAKING_OFF" for FLIGHT_STATE_TAKING_OFF.
std::string flightStateName(v1::FlightState state);

}  // namespace behaviorlib::platform
