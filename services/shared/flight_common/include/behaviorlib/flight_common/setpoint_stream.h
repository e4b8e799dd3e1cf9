#pragma once

// SetpointStream: setpoints to the platform on one FlightController
// StreamSetpoints call, as a controller sends them at up to 100 Hz (a unary
// SendSetpoint per setpoint costs a round trip each). The stream is opened on
// the first send() and reopened after the platform ended it; the platform ends
// it at the first refused setpoint, and that refusal is what the next send()
// returns.
//
//   SetpointStream stream(flight_controller_client, lease_id);
//   v1::SetpointRequest setpoint;
//   setpoint.mutable_attitude_thrust()->set_thrust_ratio(0.31);
//   if (absl::Status s = stream.send(setpoint); !s.ok()) { /* refused or unreachable */ }
//
// With a SetpointLedger (following the simulator's time grants), each stream
// names its ledger key in its metadata and counts its writes there, so that
// the simulator applies them before it steps on (setpoint_ledger.h).
//
// Not thread-safe: one sender (a behavior's worker thread).

#include <grpcpp/grpcpp.h>

#include <memory>
#include <string>

#include "absl/status/status.h"
#include "behaviorlib/platform/flight_controller_client.h"
#include "behaviorlib/server/setpoint_ledger.h"
#include "behaviorlib/v1/platform.grpc.pb.h"

namespace behaviorlib::flight {

class SetpointStream {
 public:
  /// `client` (and `ledger`, which may be null) must outlive the stream.
  SetpointStream(const platform::FlightControllerClient& client, std::string lease_id,
                 server::SetpointLedger* ledger = nullptr);
  /// Ends the stream (cancelled: no wait for the platform's answer).
  ~SetpointStream();
  SetpointStream(const SetpointStream&) = delete;
  SetpointStream& operator=(const SetpointStream&) = delete;

  /// Writes `setpoint` (robot id and lease id filled in). OK once it is on
  /// its way; the status the platform ended the stream with otherwise.
  absl::Status send(v1::SetpointRequest setpoint);
  /// Setpoints written so far (over every stream).
  uint64_t sent() const { return sent_; }

 private:
  absl::Status finish();

  const platform::FlightControllerClient& client_;
  const std::string lease_id_;
  server::SetpointLedger* const ledger_;
  std::string ledger_key_;  // the open stream's
  std::unique_ptr<grpc::ClientContext> context_;
  v1::StreamSetpointsResponse response_;
  std::unique_ptr<grpc::ClientWriter<v1::SetpointRequest>> writer_;
  uint64_t sent_ = 0;
};

}  // namespace behaviorlib::flight
