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

#include <grpcpp/support/server_interceptor.h>
#include <prometheus/counter.h>
#include <prometheus/family.h>
#include <prometheus/registry.h>

#include <cstdio>
#include <memory>
#include <string>

#include "absl/base/thread_annotations.h"
#include "absl/status/status.h"
#include "absl/synchronization/mutex.h"
#include "behaviorlib/server_kit/access_policy.h"

namespace behaviorlib::server {

class AuditLog {
 public:
  /// Appends to `path` (made if missing; empty: metrics only).
  static absl::StatusOr<std::unique_ptr<AuditLog>> open(const std::string& path,
                                                        prometheus::Registry& registry);
  ~AuditLog();
  AuditLog(const AuditLog&) = delete;
  AuditLog& operator=(const AuditLog&) = delete;

  void record(const AuditRecord& record);
  const std::string& path() const { return path_; }

 private:
  AuditLog(std::string path, std::FILE* file, prometheus::Family<prometheus::Counter>& calls);
  const std::string path_;
  absl::Mutex mutex_;
  std::FILE* const file_ ABSL_GUARDED_BY(mutex_);
  prometheus::Family<prometheus::Counter>& calls_;
};

/// Interceptors that hand each control call's outcome to `log`.
std::unique_ptr<grpc::experimental::ServerInterceptorFactoryInterface> makeAuditInterceptor(
    AuditLog* log);

}  // namespace behaviorlib::server
