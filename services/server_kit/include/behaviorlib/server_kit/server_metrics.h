#pragma once

// The metrics every server process exposes besides its own (decision 33):
//
//   grpc_server_started_total{grpc_type,grpc_service,grpc_method}
//   grpc_server_handled_total{grpc_type,grpc_service,grpc_method,grpc_code}
//   grpc_server_handling_seconds{grpc_type,grpc_service,grpc_method}   histogram
//       every call, named as go-grpc-prometheus names them; grpc_type is
//       unary, client_stream, server_stream or bidi_stream; grpc_code the
//       status code's name (OK, NOT_FOUND, ...). A stream's handling time is
//       its whole life.
//   process_cpu_seconds_total, process_resident_memory_bytes,
//   process_virtual_memory_bytes, process_open_fds, process_max_fds,
//   process_start_time_seconds
//       the Prometheus client libraries' process metrics, read from /proc at
//       each scrape.
//   behaviorlib_process_heap_in_use_bytes, behaviorlib_process_heap_free_bytes
//       the C library allocator's own count (mallinfo2): what is handed out,
//       and what it holds freed without having returned it to the system. A
//       resident size that grows while the first stays flat is the
//       allocator's fragmentation, not a leak.
//   behaviorlib_build_info{version,grpc_version,protobuf_version,compiler,build_type} 1

#include <grpcpp/support/server_interceptor.h>
#include <grpcpp/support/status.h>
#include <prometheus/collectable.h>
#include <prometheus/registry.h>

#include <chrono>
#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <string>

namespace behaviorlib::server_kit {

/// The name of a gRPC status code as the gRPC specification spells it
/// ("OK", "NOT_FOUND", ...), or "CODE_<n>" for one outside it.
std::string grpcCodeName(grpc::StatusCode code);

/// A steady clock for the handling time; a test gives its own.
using MetricsClock = std::function<std::chrono::steady_clock::time_point()>;

/// Interceptors that count and time every call into `registry`'s grpc_server_*
/// families (created here). The registry must outlive the server.
std::unique_ptr<grpc::experimental::ServerInterceptorFactoryInterface> makeServerMetricsInterceptor(
    prometheus::Registry& registry, MetricsClock clock = {});

/// What /proc/self/stat says about a process.
struct ProcStat {
  double cpu_seconds = 0;  // user + system
  double start_seconds_after_boot = 0;
  uint64_t virtual_memory_bytes = 0;
  uint64_t resident_memory_bytes = 0;
};
/// Parses the text of /proc/<pid>/stat; nullopt if it is not such a text.
/// `ticks_per_second` is sysconf(_SC_CLK_TCK), `page_bytes` the page size.
std::optional<ProcStat> parseProcStat(const std::string& text, long ticks_per_second,
                                      long page_bytes);

/// What the C library's allocator says of the calling process's heap.
struct HeapStat {
  uint64_t in_use_bytes = 0;  // allocated and not freed, mmap'd blocks included
  uint64_t free_bytes = 0;    // freed into the arenas, not returned to the system
};
HeapStat heapStat();

/// The process_* metrics of the calling process, collected at each scrape
/// (register it with the Exposer beside the registry).
std::shared_ptr<prometheus::Collectable> makeProcessCollector();

/// Adds behaviorlib_build_info to `registry`.
void addBuildInfo(prometheus::Registry& registry);

}  // namespace behaviorlib::server_kit
