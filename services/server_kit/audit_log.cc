#include "behaviorlib/server_kit/audit_log.h"

#include <google/protobuf/struct.pb.h>
#include <google/protobuf/util/json_util.h>
#include <sys/stat.h>

#include <algorithm>
#include <cerrno>
#include <chrono>
#include <cstring>
#include <ctime>

#include "absl/strings/escaping.h"
#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "behaviorlib/server_kit/server_metrics.h"

namespace behaviorlib::server_kit {
namespace {

// A JSON string literal, escaped by protobuf's JSON printer. Text with bytes
// past ASCII (a refused call's method is whatever the caller sent, maybe not
// UTF-8) is C-escaped first, losslessly: the printer refuses what is not
// UTF-8, and logs it on every call.
std::string jsonString(const std::string& text) {
  const bool ascii = std::all_of(text.begin(), text.end(),
                                 [](char c) { return static_cast<unsigned char>(c) < 0x80; });
  google::protobuf::Value value;
  value.set_string_value(ascii ? text : absl::CHexEscape(text));
  std::string out;
  return google::protobuf::util::MessageToJsonString(value, &out).ok() ? out : "\"\"";
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
                    grpcCodeName(status.error_code()), status.error_message()});
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
                                                         prometheus::Registry& registry,
                                                         AuditRotation rotation) {
  if (rotation.max_bytes == 0 || rotation.keep < 0) {
    return absl::InvalidArgumentError(
        "the audit log's rotation needs a size above 0 bytes and a count of 0 or more files");
  }
  std::FILE* file = nullptr;
  uint64_t bytes = 0;
  if (!path.empty()) {
    file = std::fopen(path.c_str(), "a");
    if (file == nullptr) {
      return absl::InvalidArgumentError(
          absl::StrCat("cannot open the audit log ", path, ": ", std::strerror(errno)));
    }
    struct stat info {};
    if (fstat(fileno(file), &info) == 0) bytes = static_cast<uint64_t>(info.st_size);
  }
  auto& calls = prometheus::BuildCounter()
                    .Name("behaviorlib_audited_calls_total")
                    .Help(
                        "Control calls and refused calls, by method, outcome (gRPC code) and "
                        "caller identity")
                    .Register(registry);
  return std::unique_ptr<AuditLog>(new AuditLog(path, file, bytes, rotation, calls));
}

AuditLog::AuditLog(std::string path, std::FILE* file, uint64_t bytes, AuditRotation rotation,
                   prometheus::Family<prometheus::Counter>& calls)
    : path_(std::move(path)), rotation_(rotation), file_(file), bytes_(bytes), calls_(calls) {}

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
  bytes_ += line.size();
  if (bytes_ >= rotation_.max_bytes) rotateLocked();
}

void AuditLog::rotateLocked() {
  std::fclose(file_);
  file_ = nullptr;
  if (rotation_.keep == 0) {
    std::remove(path_.c_str());
  } else {
    // FILE.keep is replaced by FILE.(keep-1), ..., FILE.1 by FILE.
    for (int i = rotation_.keep - 1; i >= 1; --i) {
      std::rename(absl::StrCat(path_, ".", i).c_str(), absl::StrCat(path_, ".", i + 1).c_str());
    }
    if (std::rename(path_.c_str(), absl::StrCat(path_, ".1").c_str()) != 0) {
      std::fprintf(stderr, "audit log: cannot rotate %s: %s; it goes on growing\n", path_.c_str(),
                   std::strerror(errno));
    }
  }
  file_ = std::fopen(path_.c_str(), "a");
  if (file_ == nullptr) {
    std::fprintf(stderr, "audit log: cannot reopen %s: %s; control calls are only counted\n",
                 path_.c_str(), std::strerror(errno));
    return;
  }
  struct stat info {};
  bytes_ = fstat(fileno(file_), &info) == 0 ? static_cast<uint64_t>(info.st_size) : 0;
}

std::unique_ptr<grpc::experimental::ServerInterceptorFactoryInterface> makeAuditInterceptor(
    AuditLog* log) {
  return std::make_unique<AuditInterceptorFactory>(log);
}

}  // namespace behaviorlib::server_kit
