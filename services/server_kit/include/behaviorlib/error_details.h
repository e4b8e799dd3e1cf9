#pragma once

// Error details across gRPC: the details of behaviorlib/errors/status_details.h
// (a google.rpc.ErrorInfo with a stable reason and metadata, and
// google.rpc.BadRequest field violations, as absl::Status payloads) packed
// into the google.rpc.Status of the grpc-status-details-bin trailer by
// toGrpc(), and unpacked from a peer's by fromGrpc(), so a relayed error
// (coordinator <- behavior system) keeps its reason.

#include <grpcpp/support/status.h>

#include <optional>
#include <string>

#include "absl/status/status.h"
#include "behaviorlib/errors/status_details.h"

namespace behaviorlib::errors {

/// absl::Status -> grpc::Status: the same code and message, and a
/// google.rpc.Status with every detail as error_details. An error without an
/// ErrorInfo gets one: reason INVALID_REQUEST for INVALID_ARGUMENT,
/// ERROR_REASON_UNSPECIFIED for other codes.
grpc::Status toGrpc(const absl::Status& status);
/// grpc::Status -> absl::Status, keeping the details a peer sent. The access
/// policy's PERMISSION_DENIED, which gRPC delivers without details, gets its
/// ErrorInfo (ROLE_REQUIRED, role, identity) back from its message.
absl::Status fromGrpc(const grpc::Status& status);

/// A grpc::Status error with its ErrorInfo, for servers that answer with
/// grpc::Status directly.
grpc::Status grpcError(grpc::StatusCode code, v1::ErrorReason reason, std::string message,
                       const Metadata& metadata = {});

/// The ErrorInfo and BadRequest of a grpc::Status's details (tests and
/// clients).
std::optional<google::rpc::ErrorInfo> errorInfo(const grpc::Status& status);
std::optional<google::rpc::BadRequest> badRequest(const grpc::Status& status);

}  // namespace behaviorlib::errors
