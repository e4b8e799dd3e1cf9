#pragma once

// Machine-readable error details (errors.proto) on absl::Status, with no
// transport: a google.rpc.ErrorInfo with a stable reason and metadata, and
// google.rpc.BadRequest field violations.
//
// The core and the servers build absl::Status values; the details ride on
// them as payloads keyed by their type URL ("type.googleapis.com/google.rpc.
// ErrorInfo"), the convention absl::Status documents for payloads. The gRPC
// side (behaviorlib/error_details.h in the server kit) packs them into the
// google.rpc.Status of the grpc-status-details-bin trailer and back. This
// library links protobuf and Abseil only, so that the core builds without
// gRPC.

#include <optional>
#include <string>
#include <utility>
#include <vector>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/string_view.h"
#include "behaviorlib/v1/errors.pb.h"
#include "google/rpc/error_details.pb.h"

namespace behaviorlib::errors {

/// ErrorInfo.domain of every behaviorlib error.
inline constexpr char kDomain[] = "behaviorlib.v1";

/// The prefix of a detail's type URL, and a message type's URL.
inline constexpr char kTypeUrlPrefix[] = "type.googleapis.com/";
template <typename Message>
std::string typeUrl() {
  return absl::StrCat(kTypeUrlPrefix, Message::descriptor()->full_name());
}

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

}  // namespace behaviorlib::errors
