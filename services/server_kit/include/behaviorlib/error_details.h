#pragma once

// Machine-readable error details (errors.proto): a google.rpc.ErrorInfo with a
// stable reason and metadata, and google.rpc.BadRequest field violations.
//
// The core and the servers build absl::Status values; the details ride on
// them as payloads keyed by their type URL ("type.googleapis.com/google.rpc.
// ErrorInfo"), the convention absl::Status documents for payloads. toGrpc()
// packs them into the google.rpc.Status of the grpc-status-details-bin
// trailer, with an ErrorInfo always present; fromGrpc() unpacks a peer's, so
// a relayed error (coordinator <- behavior system) keeps its reason.

#include <grpcpp/support/status.h>

#include <optional>
#include <string>
#include <utility>
#include <vector>

#include "absl/status/status.h"
#include "absl/strings/string_view.h"
#include "behaviorlib/v1/errors.pb.h"
#include "google/rpc/error_details.pb.h"

namespace behaviorlib::errors {

/// ErrorInfo.domain of every behaviorlib error.
inline constexpr char kDomain[] = "behaviorlib.v1";

/// ErrorInfo metadata: what the error is about (errors.proto lists the keys).
using Metadata = std::vector<std::pair<std::string, std::string>>;

/// `status` (not OK) with its ErrorInfo reason set to `reason`, replacing an
/// earlier one, and `metadata` added (an existing key keeps its value).
absl::Status withReason(absl::Status status, v1::ErrorReason reason, const Metadata& metadata = {});

/// Like withReason, but keeps an earlier reason: for a layer that knows a
/// general reason while a lower layer may have said something finer.
absl::Status withDefaultReason(absl::Status status, v1::ErrorReason reason,
                               const Metadata& metadata = {});

/// `status` with `metadata` added to its ErrorInfo (made without a reason if
/// there is none); an existing key keeps its value.
absl::Status withMetadata(absl::Status status, const Metadata& metadata);

/// `status` with one more BadRequest.FieldViolation.
absl::Status withFieldViolation(absl::Status status, absl::string_view field,
                                absl::string_view description);

/// `status` with every field violation's path prefixed by `prefix` (e.g.
/// "parameters." or "steps[2]."), and its description by `description_prefix`
/// (e.g. "mission.yaml:12: ").
absl::Status prefixFieldViolations(absl::Status status, absl::string_view prefix,
                                   absl::string_view description_prefix = {});

/// A new status with `code` and `message` that keeps the details of `from`:
/// for a layer that rewords an error.
absl::Status rewrap(const absl::Status& from, absl::StatusCode code, std::string message);
absl::Status rewrap(const absl::Status& from, std::string message);

/// The details, when present.
std::optional<google::rpc::ErrorInfo> errorInfo(const absl::Status& status);
std::optional<google::rpc::BadRequest> badRequest(const absl::Status& status);
/// ErrorInfo.reason, or "" when there is none.
std::string reasonOf(const absl::Status& status);

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
