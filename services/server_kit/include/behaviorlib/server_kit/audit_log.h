#pragma once

// The audit log of a server: every control call (any method that needs more
// than the viewer role) with who made it, what it was and how it ended, and
// every call the access policy refused. One JSON object per line, appended
// and flushed per record; also counted in behaviorlib_audited_calls_total
// {method, outcome, identity}.
//
//   {"time":"2026-11-27T02:10:00.123Z","identity":"behaviorlib:operator",
//    "method":"/behaviorlib.v1.Coordinator/Kill","outcome":"OK","message":""}
//
// The coordinator keeps its log beside the journal (<state-dir>/audit.jsonl);
// any server writes one with --audit-log FILE.
//
// The log rotates by size: when the file passes max_bytes it becomes
// FILE.1 (FILE.1 becomes FILE.2, ...; the oldest past `keep` is removed), and
// a new FILE is begun. So the log takes at most (keep + 1) * max_bytes plus
// one record of disk (--audit-log-max-bytes, --audit-log-keep).

#include <grpcpp/support/server_interceptor.h>
#include <prometheus/counter.h>
#include <prometheus/family.h>
#include <prometheus/registry.h>

#include <cstdint>
#include <cstdio>
#include <memory>
#include <string>

#include "absl/base/thread_annotations.h"
#include "absl/status/status.h"
#include "absl/synchronization/mutex.h"
#include "behaviorlib/server_kit/access_policy.h"

namespace behaviorlib::server_kit {

struct AuditRotation {
  uint64_t max_bytes = 64ull << 20;  ///< rotate when the file passes this size
  int keep = 4;                      ///< rotated files kept (FILE.1 .. FILE.keep)
};

class AuditLog {
 public:
  /// Appends to `path` (made if missing; empty: metrics only).
  /// INVALID_ARGUMENT for a zero max_bytes or a negative keep.
  static absl::StatusOr<std::unique_ptr<AuditLog>> open(const std::string& path,
                                                        prometheus::Registry& registry,
                                                        AuditRotation rotation = {});
  ~AuditLog();
  AuditLog(const AuditLog&) = delete;
  AuditLog& operator=(const AuditLog&) = delete;

  void record(const AuditRecord& record);
  const std::string& path() const { return path_; }

 private:
  AuditLog(std::string path, std::FILE* file, uint64_t bytes, AuditRotation rotation,
           prometheus::Family<prometheus::Counter>& calls);
  void rotateLocked() ABSL_EXCLUSIVE_LOCKS_REQUIRED(mutex_);

  const std::string path_;
  const AuditRotation rotation_;
  absl::Mutex mutex_;
  std::FILE* file_ ABSL_GUARDED_BY(mutex_);
  uint64_t bytes_ ABSL_GUARDED_BY(mutex_);  // in the current file
  prometheus::Family<prometheus::Counter>& calls_;
};

/// Interceptors that hand each control call's outcome to `log`.
std::unique_ptr<grpc::experimental::ServerInterceptorFactoryInterface> makeAuditInterceptor(
    AuditLog* log);

}  // namespace behaviorlib::server_kit
