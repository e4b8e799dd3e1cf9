#include "behaviorlib/flight_common/setpoint_stream.h"

namespace behaviorlib::flight {

SetpointStream::SetpointStream(const platform::FlightControllerClient& client, std::string lease_id,
                               server::SetpointLedger* ledger)
    : client_(client), lease_id_(std::move(lease_id)), ledger_(ledger) {}

SetpointStream::~SetpointStream() {
  if (!writer_) return;
  // Nothing more to say: cancelling does not wait for a platform that may
  // have stopped answering (the setpoints written so far were sent).
  context_->TryCancel();
  (void)finish();
}

absl::Status SetpointStream::finish() {
  // After a failed Write the platform has already ended the stream, so
  // Finish() returns its status at once.
  const grpc::Status status = writer_->Finish();
  writer_.reset();
  context_.reset();
  if (ledger_ != nullptr) ledger_->closed(ledger_key_);
  return client_.describe(status, "StreamSetpoints");
}

absl::Status SetpointStream::send(v1::SetpointRequest setpoint) {
  setpoint.set_robot_id(client_.robotId());
  setpoint.set_lease_id(lease_id_);
  if (!writer_) {
    context_ = std::make_unique<grpc::ClientContext>();
    if (ledger_ != nullptr) {
      ledger_key_ = ledger_->open();
      context_->AddMetadata(server_kit::kSetpointStreamMetadataKey, ledger_key_);
    }
    response_.Clear();
    writer_ = client_.stub().StreamSetpoints(context_.get(), &response_);
  }
  if (writer_->Write(setpoint)) {
    ++sent_;
    if (ledger_ != nullptr) ledger_->wrote(ledger_key_);
    return absl::OkStatus();
  }
  // The stream has ended: the platform refused a setpoint or went away.
  absl::Status status = finish();
  if (status.ok()) {
    status = absl::UnavailableError("the flight controller at " + client_.address() +
                                    " closed the setpoint stream");
  }
  return status;
}

}  // namespace behaviorlib::flight
