#pragma once

// absl::Status <-> grpc::Status: the codes are the same numbers, and the
// error details (error_details.h) travel in grpc-status-details-bin.

#include <grpcpp/support/status.h>

#include "absl/status/status.h"
#include "behaviorlib/error_details.h"

namespace behaviorlib::server {

inline grpc::Status toGrpc(const absl::Status& status) { return errors::toGrpc(status); }

}  // namespace behaviorlib::server
