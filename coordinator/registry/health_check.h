#pragma once

// A client of the standard gRPC health service (grpc.health.v1.Health/Check)
// for the coordinator's supervision. The two messages are tiny, so they are
// encoded by hand over a generic stub: health.proto is not compiled into our
// generated code (the server side of gRPC C++ does not need it).

#include <grpcpp/grpcpp.h>

#include <chrono>
#include <functional>
#include <memory>
#include <string>

namespace behaviorlib::coordinator {

struct HealthResult {
  /// True when the server answered SERVING.
  bool serving = false;
  /// What went wrong otherwise (the RPC error or the reported status), for
  /// messages to people.
  std::string detail;
};

/// Asks `channel`'s server for the health of `service` ("" for the whole
/// server), waiting at most `timeout`. `context_hook`, if set, is called with
/// the call's context before it starts and with nullptr after it ended, so
/// that another thread can cancel it.
HealthResult checkHealth(const std::shared_ptr<grpc::Channel>& channel, const std::string& service,
                         std::chrono::milliseconds timeout,
                         const std::function<void(grpc::ClientContext*)>& context_hook = nullptr);

}  // namespace behaviorlib::coordinator
