#pragma once

// absl::Status <-> grpc::Status: the codes are the same numbers.

#include <grpcpp/support/status.h>

#include "absl/status/status.h"

namespace behaviorlib::server {

inline grpc::Status toGrpc(const absl::Status& status) {
  if (status.ok()) return grpc::Status::OK;
  return grpc::Status(static_cast<grpc::StatusCode>(status.code()), std::string(status.message()));
}

}  // namespace behaviorlib::server
