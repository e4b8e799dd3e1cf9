#include "behaviorlib/server_kit/server_runtime.h"

#include <grpcpp/grpcpp.h>
#include <grpcpp/health_check_service_interface.h>
#include <prometheus/exposer.h>
#include <prometheus/registry.h>
#include <signal.h>
#include <unistd.h>

#include <cstdio>
#include <fstream>
#include <vector>

#include "absl/flags/flag.h"
#include "absl/synchronization/mutex.h"
#include "behaviorlib/reflection/reflection_service.h"
#include "behaviorlib/server_kit/access_policy.h"
#include "behaviorlib/server_kit/server_metrics.h"
#include "behaviorlib/server_kit/transport_security.h"

ABSL_FLAG(std::string, access_policy, "",
          "YAML file mapping certificate names and bearer tokens to roles (viewer, operator, "
          "safety, system, admin); needs TLS; empty: every peer with a certificate from the CA "
          "may call anything");
ABSL_FLAG(std::string, audit_log, "",
          "file that every control call and every refused call is appended to (JSON lines); "
          "the coordinator's default is <state-dir>/audit.jsonl");
ABSL_FLAG(uint64_t, audit_log_max_bytes, 64ull << 20,
          "the audit log is rotated (FILE -> FILE.1 -> FILE.2 ...) when it passes this size");
ABSL_FLAG(int32_t, audit_log_keep, 4, "rotated audit log files kept (FILE.1 .. FILE.N)");
ABSL_FLAG(bool, grpc_metrics, true,
          "count and time every call by service, method and status code (grpc_server_* on "
          "/metrics); docs/benchmarks.md has its cost");

namespace behaviorlib::server_kit {

ServerRuntime::ServerRuntime()
    : registry_(std::make_shared<prometheus::Registry>()), process_(makeProcessCollector()) {
  addBuildInfo(*registry_);
}

ServerRuntime::~ServerRuntime() {
  if (server_) server_->Shutdown(std::chrono::system_clock::now());
}

void ServerRuntime::blockShutdownSignals() {
  sigset_t set;
  sigemptyset(&set);
  sigaddset(&set, SIGTERM);
  sigaddset(&set, SIGINT);
  pthread_sigmask(SIG_BLOCK, &set, nullptr);
  // A client closing its socket mid-write must not kill the server.
  signal(SIGPIPE, SIG_IGN);
  // Abseil's lock-order graph, a debugging aid that the distribution's build
  // leaves on: it costs a hash lookup on every lock and unlock of gRPC's
  // mutexes (3 % of the coordinator's CPU under load, by perf).
  absl::SetMutexDeadlockDetectionMode(absl::OnDeadlockCycle::kIgnore);
}

int ServerRuntime::waitForShutdownSignal() {
  sigset_t set;
  sigemptyset(&set);
  sigaddset(&set, SIGTERM);
  sigaddset(&set, SIGINT);
  int sig = 0;
  sigwait(&set, &sig);
  return sig;
}

bool ServerRuntime::startMetrics(const std::string& address, std::string* error) {
  if (address.empty()) return true;
  // Plain HTTP, with or without TLS for gRPC: Debian's civetweb (under
  // prometheus-cpp) crashes serving HTTPS with OpenSSL 3 (decision 23).
  // Metrics are read-only; off loopback they belong on a private network.
  if (!isLoopbackAddress(address)) {
    std::fprintf(stderr,
                 "note: --metrics-listen %s serves plain HTTP: keep it on a private network\n",
                 address.c_str());
  }
  try {
    exposer_ = std::make_unique<prometheus::Exposer>(address);
  } catch (const std::exception& e) {
    *error = "cannot serve metrics on " + address + " (" + e.what() +
             "); is the port in use? choose another with --metrics-listen";
    return false;
  }
  exposer_->RegisterCollectable(registry_);
  exposer_->RegisterCollectable(process_);
  auto ports = exposer_->GetListeningPorts();
  metrics_port_ = ports.empty() ? 0 : ports.front();
  return true;
}

bool ServerRuntime::startServer(grpc::ServerBuilder& builder, const std::string& address,
                                std::vector<std::string> service_names, std::string* error) {
  grpc::EnableDefaultHealthCheckService(true);
  service_names.push_back("grpc.health.v1.Health");
  reflection_services_ = makeReflectionServices(service_names);
  for (auto& s : reflection_services_) builder.RegisterService(s.get());
  const TransportSecurity& security = processTransport();
  if (absl::Status s = checkListenAddress(address, security); !s.ok()) {
    *error = std::string(s.message());
    return false;
  }
  absl::StatusOr<std::shared_ptr<grpc::ServerCredentials>> credentials =
      serverCredentials(security);
  if (!credentials.ok()) {
    *error = std::string(credentials.status().message());
    return false;
  }
  // Roles and the audit log.
  std::shared_ptr<const AccessPolicy> policy;
  if (const std::string path = absl::GetFlag(FLAGS_access_policy); !path.empty()) {
    if (!security.tls()) {
      *error =
          "--access-policy needs TLS (--tls-cert, --tls-key, --tls-ca): roles are given to "
          "certificates and to bearer tokens sent over TLS";
      return false;
    }
    absl::StatusOr<AccessPolicy> loaded = AccessPolicy::load(path);
    if (!loaded.ok()) {
      *error = "--access-policy: " + std::string(loaded.status().message());
      return false;
    }
    policy = std::make_shared<const AccessPolicy>(std::move(*loaded));
  }
  setProcessAccessPolicy(policy);
  const std::string audit_path =
      absl::GetFlag(FLAGS_audit_log).empty() ? default_audit_log_ : absl::GetFlag(FLAGS_audit_log);
  AuditRotation rotation;
  rotation.max_bytes = absl::GetFlag(FLAGS_audit_log_max_bytes);
  rotation.keep = absl::GetFlag(FLAGS_audit_log_keep);
  absl::StatusOr<std::unique_ptr<AuditLog>> audit =
      AuditLog::open(audit_path, *registry_, rotation);
  if (!audit.ok()) {
    *error = "--audit-log: " + std::string(audit.status().message());
    return false;
  }
  audit_ = std::move(*audit);
  if (security.tls()) {
    AuditLog* log = audit_.get();
    (*credentials)
        ->SetAuthMetadataProcessor(
            makeAuthorizer(policy, [log](const AuditRecord& record) { log->record(record); }));
  }
  std::vector<std::unique_ptr<grpc::experimental::ServerInterceptorFactoryInterface>> interceptors;
  interceptors.push_back(makeAuditInterceptor(audit_.get()));
  if (absl::GetFlag(FLAGS_grpc_metrics)) {
    interceptors.push_back(makeServerMetricsInterceptor(*registry_));
  }
  builder.experimental().SetInterceptorCreators(std::move(interceptors));
  builder.AddListeningPort(address, *credentials, &grpc_port_);
  builder.SetMaxReceiveMessageSize(ServerLimits::kMaxReceiveBytes);
  builder.SetMaxSendMessageSize(ServerLimits::kMaxSendBytes);
  builder.AddChannelArgument(GRPC_ARG_MAX_CONCURRENT_STREAMS, ServerLimits::kMaxConcurrentStreams);
  builder.AddChannelArgument(GRPC_ARG_MAX_METADATA_SIZE, ServerLimits::kMaxMetadataBytes);
  builder.AddChannelArgument(GRPC_ARG_KEEPALIVE_TIME_MS, ServerLimits::kKeepaliveTimeMs);
  builder.AddChannelArgument(GRPC_ARG_KEEPALIVE_TIMEOUT_MS, ServerLimits::kKeepaliveTimeoutMs);
  builder.AddChannelArgument(GRPC_ARG_HTTP2_MIN_RECV_PING_INTERVAL_WITHOUT_DATA_MS,
                             ServerLimits::kMinClientPingIntervalMs);
  builder.AddChannelArgument(GRPC_ARG_HTTP2_MAX_PING_STRIKES, ServerLimits::kMaxPingStrikes);
  // gRPC sets SO_REUSEPORT by default, which would let a second server bind a
  // port already in use and silently share it; we want a clear failure.
  builder.AddChannelArgument(GRPC_ARG_ALLOW_REUSEPORT, 0);
  server_ = builder.BuildAndStart();
  if (!server_ || grpc_port_ == 0) {
    *error = "cannot listen on " + address +
             " (address in use or invalid); choose another with --listen, e.g. 127.0.0.1:0";
    server_.reset();
    return false;
  }
  service_names_ = std::move(service_names);
  setServing("", true);
  for (const auto& name : service_names_) setServing(name, true);
  return true;
}

void ServerRuntime::setServing(const std::string& service_name, bool serving) {
  if (!server_) return;
  if (auto* health = server_->GetHealthCheckService()) {
    health->SetServingStatus(service_name, serving);
  }
}

bool ServerRuntime::writePortFile(const std::string& path, std::string* error) const {
  if (path.empty()) return true;
  const std::string tmp = path + ".tmp." + std::to_string(getpid());
  {
    std::ofstream out(tmp);
    out << "grpc_port=" << grpc_port_ << "\nmetrics_port=" << metrics_port_ << "\n";
    if (!out) {
      *error = "cannot write port file " + tmp;
      return false;
    }
  }
  if (std::rename(tmp.c_str(), path.c_str()) != 0) {
    *error = "cannot rename port file to " + path;
    return false;
  }
  return true;
}

void ServerRuntime::shutdown(std::chrono::milliseconds deadline) {
  if (!server_) return;
  setServing("", false);
  for (const auto& name : service_names_) setServing(name, false);
  server_->Shutdown(std::chrono::system_clock::now() + deadline);
  server_->Wait();
  server_.reset();
  // The process is about to exit. Stopping the metrics endpoint would block
  // for up to two seconds (civetweb's master thread polls its sockets in
  // 2 s quanta and mg_stop waits for it); the process's exit ends its
  // threads anyway, so the exposer (and the registry it holds) is left to it.
  // It stays reachable from here, so a leak checker does not report it.
  if (exposer_) {
    static absl::Mutex mutex;
    static auto* const left_to_exit = new std::vector<prometheus::Exposer*>();
    absl::MutexLock lock(&mutex);
    left_to_exit->push_back(exposer_.release());
  }
}

int fatal(const std::string& program, const std::string& message) {
  std::fprintf(stderr, "%s: %s\n", program.c_str(), message.c_str());
  return 1;
}

int fatal(const std::string& program, const absl::Status& status) {
  fatal(program, std::string(status.message()));
  return status.code() == absl::StatusCode::kInvalidArgument ? 2 : 1;
}

}  // namespace behaviorlib::server_kit
