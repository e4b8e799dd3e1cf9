#pragma once

// What every behaviorlib server process shares: a gRPC server with the
// standard health service and reflection, a Prometheus /metrics endpoint
// (with gRPC, process and build metrics: server_metrics.h),
// the port file that tells scripts and tests which ports were bound
// (`--listen 127.0.0.1:0` is allowed), and orderly SIGTERM handling.
//
//   ServerRuntime::blockShutdownSignals();      // first thing in main()
//   ServerRuntime runtime;
//   if (!runtime.startMetrics(metrics_listen, &error)) ...
//   grpc::ServerBuilder builder;
//   builder.RegisterService(&my_service);
//   if (!runtime.startServer(builder, listen, {"my.pkg.MyService"}, &error)) ...
//   runtime.writePortFile(port_file);
//   ServerRuntime::waitForShutdownSignal();
//   runtime.shutdown(std::chrono::seconds(5));

#include <chrono>
#include <memory>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "behaviorlib/server_kit/audit_log.h"

namespace grpc {
class Server;
class ServerBuilder;
class Service;
}  // namespace grpc

namespace prometheus {
class Collectable;
class Exposer;
class Registry;
}  // namespace prometheus

namespace behaviorlib::server_kit {

/// Limits every server sets explicitly rather than inheriting gRPC's
/// defaults (some of which are unlimited).
struct ServerLimits {
  /// A request larger is RESOURCE_EXHAUSTED before any handler runs.
  static constexpr int kMaxReceiveBytes = 4 << 20;
  /// A reply larger fails instead of being sent (List* RPCs paginate).
  static constexpr int kMaxSendBytes = 16 << 20;
  /// Concurrent streams on one client connection.
  static constexpr int kMaxConcurrentStreams = 256;
  /// Request metadata (headers) per call.
  static constexpr int kMaxMetadataBytes = 16 << 10;
  /// The server pings an idle connection this often and closes it when the
  /// ping is not answered within the timeout: a vanished peer's streams end.
  static constexpr int kKeepaliveTimeMs = 30'000;
  static constexpr int kKeepaliveTimeoutMs = 10'000;
  /// A client may ping at most this often; more is a strike, and two strikes
  /// close its connection (GOAWAY too_many_pings).
  static constexpr int kMinClientPingIntervalMs = 10'000;
  static constexpr int kMaxPingStrikes = 2;
};

class ServerRuntime {
 public:
  ServerRuntime();
  ~ServerRuntime();
  ServerRuntime(const ServerRuntime&) = delete;
  ServerRuntime& operator=(const ServerRuntime&) = delete;

  /// Blocks SIGTERM and SIGINT in the calling thread (and so in every thread
  /// it starts later), and turns off Abseil's lock-order checks; call it
  /// first in main().
  static void blockShutdownSignals();
  /// Waits for SIGTERM or SIGINT; returns the signal number.
  static int waitForShutdownSignal();

  /// The registry served on /metrics.
  prometheus::Registry& registry() { return *registry_; }
  std::shared_ptr<prometheus::Registry> registryPtr() { return registry_; }

  /// Serves /metrics on `address` ("host:port", port 0 allowed; empty means
  /// no metrics endpoint). False with an actionable `error` if it cannot bind.
  bool startMetrics(const std::string& address, std::string* error);

  /// Enables the health service and reflection, listens on `address` (port 0
  /// allowed) with the process's transport security (transport_security.h:
  /// mutual TLS, or plaintext on loopback unless --insecure) and the limits
  /// of ServerLimits, and starts the server. `service_names` are the
  /// fully-qualified services registered on `builder`; each is reported
  /// SERVING by the health service, as is the overall "" service. False with
  /// an actionable `error` when the address cannot be bound or is refused.
  bool startServer(grpc::ServerBuilder& builder, const std::string& address,
                   std::vector<std::string> service_names, std::string* error);

  /// The audit log's file when --audit-log is not given (the coordinator:
  /// beside its journal); call before startServer.
  void setDefaultAuditLog(std::string path) { default_audit_log_ = std::move(path); }
  /// The audit log (after startServer).
  AuditLog* auditLog() { return audit_.get(); }

  grpc::Server* server() { return server_.get(); }
  int grpcPort() const { return grpc_port_; }
  int metricsPort() const { return metrics_port_; }

  /// Sets one service's (or "" for the server's) health status.
  void setServing(const std::string& service_name, bool serving);

  /// Writes "grpc_port=N\nmetrics_port=M\n" atomically (temp file + rename).
  bool writePortFile(const std::string& path, std::string* error) const;

  /// Marks every service NOT_SERVING, then shuts the server down, letting
  /// calls in flight finish until `deadline` from now. For the end of a
  /// process: the metrics endpoint is abandoned to the process's exit
  /// (stopping it takes up to 2 s).
  void shutdown(std::chrono::milliseconds deadline);

 private:
  std::shared_ptr<prometheus::Registry> registry_;
  // process_* metrics, collected at each scrape.
  std::shared_ptr<prometheus::Collectable> process_;
  std::unique_ptr<prometheus::Exposer> exposer_;
  std::vector<std::unique_ptr<grpc::Service>> reflection_services_;
  std::string default_audit_log_;
  // Outlives the server, whose interceptors and authorizer write to it.
  std::unique_ptr<AuditLog> audit_;
  std::unique_ptr<grpc::Server> server_;
  std::vector<std::string> service_names_;
  int grpc_port_ = 0;
  int metrics_port_ = 0;
};

/// Prints "<program>: <message>" to stderr; returns 1 for use as an exit code.
int fatal(const std::string& program, const std::string& message);
/// Prints "<program>: <status message>"; returns the exit code for a start
/// that failed with `status`: 2 for INVALID_ARGUMENT (bad options), else 1.
int fatal(const std::string& program, const absl::Status& status);

}  // namespace behaviorlib::server_kit
