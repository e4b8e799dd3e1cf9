#include "behaviorlib/server_kit/audit_log.h"

#include <cerrno>
#include <chrono>
#include <cstring>
#include <ctime>

#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"

namespace behaviorlib::server {
namespace {

std::string jsonString(const std::string& text) {
  std::string out = "\"";
  for (const char c : text) {
    switch (c) {
      case '"':
        out += "\\\"";
        break;
      case '\\':
        out += "\\\\";
        break;
      case '\n':
        out += "\\n";
        break;
      default:
        if (static_cast<unsigned char>(c) < 0x20) {
          out += absl::StrFormat("\\u%04x", static_cast<int>(c));
        } else {
          out += c;
        }
    }
  }
  return out + "\"";
}

// Wall time: an audit log is read against other logs and clocks.
std::string nowUtc() {
  const auto now = std::chrono::system_clock::now();
  const std::time_t seconds = std::chrono::system_clock::to_time_t(now);
  const auto millis =
      std::chrono::duration_cast<std::chrono::milliseconds>(now.time_since_epoch()).count() % 1000;
  std::tm utc{};
  gmtime_r(&seconds, &utc);
  char text[32];
  std::strftime(text, sizeof text, "%Y-%m-%dT%H:%M:%S", &utc);
  return absl::StrFormat("%s.%03dZ", text, static_cast<int>(millis));
}

std::string codeName(grpc::StatusCode code) {
  static constexpr const char* kNames[] = {"OK",
                                           "CANCELLED",
                                           "UNKNOWN",
                                           "INVALID_ARGUMENT",
                                           "DEADLINE_EXCEEDED",
                                           "NOT_FOUND",
                                           "ALREADY_EXISTS",
                                           "PERMISSION_DENIED",
                                           "RESOURCE_EXHAUSTED",
                                           "FAILED_PRECONDITION",
                                           "ABORTED",
                                           "OUT_OF_RANGE",
                                           "UNIMPLEMENTED",
                                           "INTERNAL",
                                           "UNAVAILABLE",
                                           "DATA_LOSS",
                                           "UNAUTHENTICATED"};
  const int i = static_cast<int>(code);
  return i >= 0 && i < 17 ? kNames[i] : absl::StrCat("CODE_", i);
}

class AuditInterceptor final : public grpc::experimental::Interceptor {
 public:
  AuditInterceptor(grpc::experimental::ServerRpcInfo* info, AuditLog* log)
      : info_(info), log_(log) {}

  void Intercept(grpc::experimental::InterceptorBatchMethods* methods) override {
    if (methods->QueryInterceptionHookPoint(
            grpc::experimental::InterceptionHookPoints::PRE_SEND_STATUS)) {
      const grpc::Status status = methods->GetSendStatus();
      const std::optional<Caller> caller = callerOf(*info_->server_context());
      log_->record({caller ? caller->identity : "anonymous", info_->method(),
                    codeName(status.error_code()), status.error_message()});
    }
    methods->Proceed();
  }

 private:
  grpc::experimental::ServerRpcInfo* const info_;
  AuditLog* const log_;
};

class AuditInterceptorFactory final : public grpc::experimental::ServerInterceptorFactoryInterface {
 public:
  explicit AuditInterceptorFactory(AuditLog* log) : log_(log) {}
  grpc::experimental::Interceptor* CreateServerInterceptor(
      grpc::experimental::ServerRpcInfo* info) override {
    // Control calls only: reads and streams of state are not audited.
    if (requiredRole(info->method()) == Role::kViewer) return nullptr;
    return new AuditInterceptor(info, log_);
  }

 private:
  AuditLog* const log_;
};

}  // namespace

absl::StatusOr<std::unique_ptr<AuditLog>> AuditLog::open(const std::string& path,
                                                         prometheus::Registry& registry) {
  std::FILE* file = nullptr;
  if (!path.empty()) {
    file = std::fopen(path.c_str(), "a");
    if (file == nullptr) {
      return absl::InvalidArgumentError(
          absl::StrCat("cannot open the audit log ", path, ": ", std::strerror(errno)));
    }
  }
  auto& calls = prometheus::BuildCounter()
                    .Name("behaviorlib_audited_calls_total")
                    .Help(
                        "Control calls and refused calls, by method, outcome (gRPC code) and "
                        "caller identity")
                    .Register(registry);
  return std::unique_ptr<AuditLog>(new AuditLog(path, file, calls));
}

AuditLog::AuditLog(std::string path, std::FILE* file,
                   prometheus::Family<prometheus::Counter>& calls)
    : path_(std::move(path)), file_(file), calls_(calls) {}

AuditLog::~AuditLog() {
  absl::MutexLock lock(&mutex_);
  if (file_ != nullptr) std::fclose(file_);
}

void AuditLog::record(const AuditRecord& r) {
  // A refused call may name any path: only our methods are label values.
  const bool known = r.method.size() < 128 && (absl::StartsWith(r.method, "/behaviorlib.") ||
                                               absl::StartsWith(r.method, "/grpc."));
  calls_
      .Add({{"method", known ? r.method : "other"},
            {"outcome", r.outcome},
            {"identity", r.identity.substr(0, 128)}})
      .Increment();
  const std::string line =
      absl::StrCat("{\"time\":", jsonString(nowUtc()), ",\"identity\":", jsonString(r.identity),
                   ",\"method\":", jsonString(r.method), ",\"outcome\":", jsonString(r.outcome),
                   ",\"message\":", jsonString(r.message), "}\n");
  absl::MutexLock lock(&mutex_);
  if (file_ == nullptr) return;
  std::fputs(line.c_str(), file_);
  std::fflush(file_);
}

std::unique_ptr<grpc::experimental::ServerInterceptorFactoryInterface> makeAuditInterceptor(
    AuditLog* log) {
  return std::make_unique<AuditInterceptorFactory>(log);
}

}  // namespace behaviorlib::server
