#include "behaviorlib/platform/flight_controller_client.h"

#include <google/protobuf/util/time_util.h>

#include "behaviorlib/server_kit/transport_security.h"

namespace behaviorlib::platform {
namespace {

// Reconnect quickly after the flight controller comes up (gRPC's default
// backoff grows to two minutes, far too slow for a simulator restart).
grpc::ChannelArguments channelArguments() {
  grpc::ChannelArguments args;
  args.SetInt(GRPC_ARG_INITIAL_RECONNECT_BACKOFF_MS, 100);
  // gRPC gives each connection attempt at least this long (its "minimum
  // connect timeout"); a refused attempt is still retried after the initial
  // backoff. At 100 ms, a server slow to send its HTTP/2 settings on a loaded
  // machine failed the call.
  args.SetInt(GRPC_ARG_MIN_RECONNECT_BACKOFF_MS, 5000);
  args.SetInt(GRPC_ARG_MAX_RECONNECT_BACKOFF_MS, 1000);
  return args;
}

}  // namespace

std::string flightStateName(v1::FlightState state) {
  std::string name = v1::FlightState_Name(state);
  constexpr std::string_view kPrefix = "FLIGHT_STATE_";
  return name.rfind(kPrefix, 0) == 0 ? name.substr(kPrefix.size()) : name;
}

FlightControllerClient::FlightControllerClient(std::string address, std::string robot_id,
                                               FlightControllerClientOptions options)
    : address_(std::move(address)),
      robot_id_(std::move(robot_id)),
      options_(options),
      channel_(behaviorlib::server_kit::makeChannel(address_, channelArguments())),
      stub_(v1::FlightController::NewStub(channel_)) {}

std::unique_ptr<grpc::ClientContext> FlightControllerClient::context() const {
  auto context = std::make_unique<grpc::ClientContext>();
  context->set_deadline(std::chrono::system_clock::now() + options_.call_timeout);
  return context;
}

absl::Status FlightControllerClient::describe(const grpc::Status& status, const char* call) const {
  if (status.ok()) return absl::OkStatus();
  std::string message = status.error_message();
  switch (status.error_code()) {
    case grpc::StatusCode::UNAVAILABLE:
      message = "flight controller at " + address_ + " is unreachable (" + message + ")";
      break;
    case grpc::StatusCode::DEADLINE_EXCEEDED:
      message = "flight controller at " + address_ + " did not answer " + call + " within " +
                std::to_string(options_.call_timeout.count()) + " ms";
      break;
    default:
      message =
          std::string(call) + " refused by the flight controller at " + address_ + ": " + message;
  }
  return absl::Status(static_cast<absl::StatusCode>(status.error_code()), message);
}

absl::StatusOr<v1::AcquireLeaseResponse> FlightControllerClient::acquireLease(
    const std::string& holder, std::chrono::nanoseconds ttl, bool preempt) const {
  v1::AcquireLeaseRequest request;
  request.set_robot_id(robot_id_);
  request.set_holder(holder);
  *request.mutable_ttl() = google::protobuf::util::TimeUtil::NanosecondsToDuration(ttl.count());
  request.set_preempt(preempt);
  v1::AcquireLeaseResponse response;
  const grpc::Status status = stub_->AcquireLease(context().get(), request, &response);
  if (!status.ok()) return describe(status, "AcquireLease");
  return response;
}

absl::StatusOr<v1::RenewLeaseResponse> FlightControllerClient::renewLease(
    const std::string& lease_id) const {
  v1::RenewLeaseRequest request;
  request.set_robot_id(robot_id_);
  request.set_lease_id(lease_id);
  v1::RenewLeaseResponse response;
  const grpc::Status status = stub_->RenewLease(context().get(), request, &response);
  if (!status.ok()) return describe(status, "RenewLease");
  return response;
}

absl::Status FlightControllerClient::releaseLease(const std::string& lease_id) const {
  v1::ReleaseLeaseRequest request;
  request.set_robot_id(robot_id_);
  request.set_lease_id(lease_id);
  v1::ReleaseLeaseResponse response;
  return describe(stub_->ReleaseLease(context().get(), request, &response), "ReleaseLease");
}

absl::StatusOr<v1::FlightState> FlightControllerClient::executeFlightAction(
    const std::string& lease_id, v1::FlightAction action, double takeoff_altitude_m,
    bool confirm) const {
  v1::ExecuteFlightActionRequest request;
  request.set_robot_id(robot_id_);
  request.set_lease_id(lease_id);
  request.set_action(action);
  request.set_takeoff_altitude_m(takeoff_altitude_m);
  request.set_confirm(confirm);
  v1::ExecuteFlightActionResponse response;
  const grpc::Status status = stub_->ExecuteFlightAction(context().get(), request, &response);
  if (!status.ok()) return describe(status, "ExecuteFlightAction");
  return response.state();
}

absl::StatusOr<v1::FlightState> FlightControllerClient::sendSetpoint(
    const std::string& lease_id, v1::SetpointRequest setpoint) const {
  setpoint.set_robot_id(robot_id_);
  setpoint.set_lease_id(lease_id);
  v1::SendSetpointResponse response;
  const grpc::Status status = stub_->SendSetpoint(context().get(), setpoint, &response);
  if (!status.ok()) return describe(status, "SendSetpoint");
  return response.state();
}

absl::StatusOr<v1::FlightState> FlightControllerClient::sendPositionSetpoint(
    const std::string& lease_id, double x_m, double y_m, double z_m, double yaw_rad) const {
  v1::SetpointRequest setpoint;
  auto* position = setpoint.mutable_position_yaw();
  position->mutable_position_m()->set_x(x_m);
  position->mutable_position_m()->set_y(y_m);
  position->mutable_position_m()->set_z(z_m);
  position->set_yaw_rad(yaw_rad);
  return sendSetpoint(lease_id, std::move(setpoint));
}

}  // namespace behaviorlib::platform
