#include "behaviorlib/server_kit/server_metrics.h"

#include <dirent.h>
#include <google/protobuf/descriptor.h>
#include <google/protobuf/stubs/common.h>
#include <grpcpp/grpcpp.h>
#include <malloc.h>
#include <prometheus/counter.h>
#include <prometheus/family.h>
#include <prometheus/gauge.h>
#include <prometheus/histogram.h>
#include <prometheus/metric_family.h>
#include <sys/resource.h>
#include <unistd.h>

#include <array>
#include <atomic>
#include <fstream>
#include <sstream>
#include <vector>

#include "absl/container/flat_hash_map.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "absl/synchronization/mutex.h"

#ifndef BEHAVIORLIB_VERSION
#define BEHAVIORLIB_VERSION "unknown"
#endif
#ifndef BEHAVIORLIB_BUILD_TYPE
#define BEHAVIORLIB_BUILD_TYPE "unknown"
#endif

namespace behaviorlib::server_kit {
namespace {

constexpr int kCodes = 17;  // OK .. UNAUTHENTICATED

const char* typeName(grpc::experimental::ServerRpcInfo::Type type) {
  using Type = grpc::experimental::ServerRpcInfo::Type;
  switch (type) {
    case Type::UNARY:
      return "unary";
    case Type::CLIENT_STREAMING:
      return "client_stream";
    case Type::SERVER_STREAMING:
      return "server_stream";
    case Type::BIDI_STREAMING:
      return "bidi_stream";
  }
  return "unknown";
}

// The series of one method, made at its first call. Handled counters are
// made per code at the code's first use: a method that never fails has one.
struct MethodSeries {
  prometheus::Counter* started = nullptr;
  prometheus::Histogram* seconds = nullptr;
  std::array<std::atomic<prometheus::Counter*>, kCodes> handled{};
  prometheus::Labels labels;  // grpc_type, grpc_service, grpc_method
};

class ServerMetrics {
 public:
  ServerMetrics(prometheus::Registry& registry, MetricsClock clock)
      : clock_(clock ? std::move(clock) : [] { return std::chrono::steady_clock::now(); }),
        started_(prometheus::BuildCounter()
                     .Name("grpc_server_started_total")
                     .Help("Calls started on the server, by type, service and method.")
                     .Register(registry)),
        handled_(prometheus::BuildCounter()
                     .Name("grpc_server_handled_total")
                     .Help("Calls completed on the server, by type, service, method and status "
                           "code (a stream ended by its client counts as CANCELLED).")
                     .Register(registry)),
        seconds_(prometheus::BuildHistogram()
                     .Name("grpc_server_handling_seconds")
                     .Help("Time from a call's arrival to its status, by type, service and "
                           "method (a stream's whole life).")
                     .Register(registry)) {}

  std::chrono::steady_clock::time_point now() const { return clock_(); }

  MethodSeries& series(const char* method, grpc::experimental::ServerRpcInfo::Type type) {
    const std::string full = method == nullptr ? std::string() : std::string(method);
    const std::string key = absl::StrCat(typeName(type), " ", full);
    absl::MutexLock lock(&mutex_);
    if (auto it = methods_.find(key); it != methods_.end()) return *it->second;
    // "/package.Service/Method". A caller may send any name: one the
    // server's protos do not declare, or one past kMaxMethods, is counted
    // under service and method "unknown" and not remembered, so that
    // neither the series nor this map grow with what callers invent.
    const size_t slash = full.rfind('/');
    std::string service = slash == std::string::npos || slash == 0 ? "" : full.substr(1, slash - 1);
    std::string name = slash == std::string::npos ? full : full.substr(slash + 1);
    const bool known = declared(service, name) && methods_.size() < kMaxMethods;
    if (!known) {
      service = name = "unknown";
      auto& unknown = unknown_[static_cast<size_t>(type) % unknown_.size()];
      if (unknown) return *unknown;
      unknown = makeSeries(type, service, name);
      return *unknown;
    }
    auto& slot = methods_[key];
    slot = makeSeries(type, service, name);
    return *slot;
  }

  prometheus::Counter& handled(MethodSeries& series, grpc::StatusCode code) {
    const int i = static_cast<int>(code);
    const int index = i >= 0 && i < kCodes ? i : static_cast<int>(grpc::StatusCode::UNKNOWN);
    prometheus::Counter* counter = series.handled[index].load(std::memory_order_acquire);
    if (counter != nullptr) return *counter;
    prometheus::Labels labels = series.labels;
    labels["grpc_code"] = grpcCodeName(static_cast<grpc::StatusCode>(index));
    // Family::Add is thread-safe and gives the same series for the same labels.
    counter = &handled_.Add(labels);
    series.handled[index].store(counter, std::memory_order_release);
    return *counter;
  }

 private:
  // 100 µs (a loopback call) to 10 s; longer streams fall in +Inf.
  static const prometheus::Histogram::BucketBoundaries& bucketBoundaries() {
    static const prometheus::Histogram::BucketBoundaries kBuckets = {
        0.0001, 0.00025, 0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025,
        0.05,   0.1,     0.25,   0.5,   1,      2.5,   5,    10};
    return kBuckets;
  }

  // Methods with series of their own, at most (a server has tens).
  static constexpr size_t kMaxMethods = 1024;

  // Whether the generated protos declare the method (or it is the health
  // service's, which gRPC implements without them).
  static bool declared(const std::string& service, const std::string& method) {
    if (service.empty() || method.empty()) return false;
    if (service == "grpc.health.v1.Health") return method == "Check" || method == "Watch";
    return google::protobuf::DescriptorPool::generated_pool()->FindMethodByName(
               absl::StrCat(service, ".", method)) != nullptr;
  }

  std::unique_ptr<MethodSeries> makeSeries(grpc::experimental::ServerRpcInfo::Type type,
                                           const std::string& service, const std::string& name) {
    auto series = std::make_unique<MethodSeries>();
    series->labels = {
        {"grpc_type", typeName(type)}, {"grpc_service", service}, {"grpc_method", name}};
    series->started = &started_.Add(series->labels);
    series->seconds = &seconds_.Add(series->labels, bucketBoundaries());
    return series;
  }

  const MetricsClock clock_;
  prometheus::Family<prometheus::Counter>& started_;
  prometheus::Family<prometheus::Counter>& handled_;
  prometheus::Family<prometheus::Histogram>& seconds_;
  absl::Mutex mutex_;
  // By "<type> /package.Service/Method", declared methods only.
  absl::flat_hash_map<std::string, std::unique_ptr<MethodSeries>> methods_ ABSL_GUARDED_BY(mutex_);
  // The calls of undeclared methods, by type.
  std::array<std::unique_ptr<MethodSeries>, 4> unknown_ ABSL_GUARDED_BY(mutex_);
};

class MetricsInterceptor final : public grpc::experimental::Interceptor {
 public:
  MetricsInterceptor(ServerMetrics& metrics, MethodSeries& series)
      : metrics_(metrics), series_(series), start_(metrics.now()) {
    series_.started->Increment();
  }
  // A call whose status was never sent (its client cancelled a stream) ends
  // with the interceptor.
  ~MetricsInterceptor() override { finish(grpc::StatusCode::CANCELLED); }

  // gRPC runs a call's hook points on whichever threads its batches complete
  // on (the handler's for the status, a completion-queue thread for the
  // close), ordered inside libgrpc where ThreadSanitizer cannot see it: the
  // flag is atomic.
  void Intercept(grpc::experimental::InterceptorBatchMethods* methods) override {
    if (methods->QueryInterceptionHookPoint(
            grpc::experimental::InterceptionHookPoints::PRE_SEND_STATUS)) {
      finish(methods->GetSendStatus().error_code());
    }
    methods->Proceed();
  }

 private:
  // Counts the call once: at its status, or at the end of the interceptor.
  void finish(grpc::StatusCode code) {
    if (done_.exchange(true, std::memory_order_acq_rel)) return;
    const std::chrono::duration<double> took = metrics_.now() - start_;
    series_.seconds->Observe(took.count());
    metrics_.handled(series_, code).Increment();
  }

  ServerMetrics& metrics_;
  MethodSeries& series_;
  const std::chrono::steady_clock::time_point start_;
  std::atomic<bool> done_{false};
};

class MetricsInterceptorFactory final
    : public grpc::experimental::ServerInterceptorFactoryInterface {
 public:
  MetricsInterceptorFactory(prometheus::Registry& registry, MetricsClock clock)
      : metrics_(registry, std::move(clock)) {}
  grpc::experimental::Interceptor* CreateServerInterceptor(
      grpc::experimental::ServerRpcInfo* info) override {
    return new MetricsInterceptor(metrics_, metrics_.series(info->method(), info->type()));
  }

 private:
  ServerMetrics metrics_;
};

std::string readFile(const char* path) {
  std::ifstream in(path);
  std::stringstream text;
  text << in.rdbuf();
  return text.str();
}

// Seconds since the epoch at which the machine booted (/proc/stat btime).
std::optional<double> bootTimeSeconds() {
  std::istringstream in(readFile("/proc/stat"));
  std::string line;
  while (std::getline(in, line)) {
    if (line.rfind("btime ", 0) != 0) continue;
    double seconds = 0;
    if (absl::SimpleAtod(line.substr(6), &seconds)) return seconds;
  }
  return std::nullopt;
}

size_t openFileDescriptors() {
  DIR* dir = opendir("/proc/self/fd");
  if (dir == nullptr) return 0;
  size_t n = 0;
  while (const dirent* entry = readdir(dir)) {
    if (entry->d_name[0] != '.') ++n;
  }
  closedir(dir);
  return n > 0 ? n - 1 : 0;  // not the directory's own descriptor
}

prometheus::MetricFamily gaugeFamily(std::string name, std::string help, double value,
                                     prometheus::MetricType type = prometheus::MetricType::Gauge) {
  prometheus::MetricFamily family;
  family.name = std::move(name);
  family.help = std::move(help);
  family.type = type;
  prometheus::ClientMetric metric;
  if (type == prometheus::MetricType::Counter) {
    metric.counter.value = value;
  } else {
    metric.gauge.value = value;
  }
  family.metric.push_back(std::move(metric));
  return family;
}

class ProcessCollector final : public prometheus::Collectable {
 public:
  ProcessCollector()
      : ticks_(sysconf(_SC_CLK_TCK)), page_(sysconf(_SC_PAGESIZE)), boot_(bootTimeSeconds()) {}

  std::vector<prometheus::MetricFamily> Collect() const override {
    std::vector<prometheus::MetricFamily> out;
    if (auto stat = parseProcStat(readFile("/proc/self/stat"), ticks_, page_)) {
      out.push_back(gaugeFamily("process_cpu_seconds_total",
                                "Total user and system CPU time spent in seconds.",
                                stat->cpu_seconds, prometheus::MetricType::Counter));
      out.push_back(gaugeFamily("process_resident_memory_bytes", "Resident memory size in bytes.",
                                static_cast<double>(stat->resident_memory_bytes)));
      out.push_back(gaugeFamily("process_virtual_memory_bytes", "Virtual memory size in bytes.",
                                static_cast<double>(stat->virtual_memory_bytes)));
      if (boot_) {
        out.push_back(gaugeFamily("process_start_time_seconds",
                                  "Start time of the process since unix epoch in seconds.",
                                  *boot_ + stat->start_seconds_after_boot));
      }
    }
    const HeapStat heap = heapStat();
    out.push_back(gaugeFamily("behaviorlib_process_heap_in_use_bytes",
                              "Bytes the allocator has handed out and not had back (malloc "
                              "arenas and mmap'd blocks).",
                              static_cast<double>(heap.in_use_bytes)));
    out.push_back(gaugeFamily("behaviorlib_process_heap_free_bytes",
                              "Bytes the allocator holds from the system but has not handed out "
                              "(freed, not yet returned).",
                              static_cast<double>(heap.free_bytes)));
    out.push_back(gaugeFamily("process_open_fds", "Number of open file descriptors.",
                              static_cast<double>(openFileDescriptors())));
    rlimit limit{};
    if (getrlimit(RLIMIT_NOFILE, &limit) == 0) {
      out.push_back(gaugeFamily("process_max_fds", "Maximum number of open file descriptors.",
                                static_cast<double>(limit.rlim_cur)));
    }
    return out;
  }

 private:
  const long ticks_;
  const long page_;
  const std::optional<double> boot_;
};

}  // namespace

std::string grpcCodeName(grpc::StatusCode code) {
  static constexpr const char* kNames[kCodes] = {"OK",
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
  return i >= 0 && i < kCodes ? kNames[i] : absl::StrCat("CODE_", i);
}

std::unique_ptr<grpc::experimental::ServerInterceptorFactoryInterface> makeServerMetricsInterceptor(
    prometheus::Registry& registry, MetricsClock clock) {
  return std::make_unique<MetricsInterceptorFactory>(registry, std::move(clock));
}

std::optional<ProcStat> parseProcStat(const std::string& text, long ticks_per_second,
                                      long page_bytes) {
  // "pid (comm) state ppid ...": comm may hold spaces and parentheses, so
  // the fields are counted from the last ')'. Field 3 (state) is fields[0].
  const size_t close = text.rfind(')');
  if (close == std::string::npos || ticks_per_second <= 0 || page_bytes <= 0) return std::nullopt;
  const std::vector<std::string> fields =
      absl::StrSplit(text.substr(close + 1), ' ', absl::SkipWhitespace());
  auto field = [&](int n, uint64_t* value) {  // n as proc(5) numbers them
    const size_t i = static_cast<size_t>(n - 3);
    return i < fields.size() && absl::SimpleAtoi(fields[i], value);
  };
  uint64_t utime = 0, stime = 0, start = 0, vsize = 0, rss = 0;
  if (!field(14, &utime) || !field(15, &stime) || !field(22, &start) || !field(23, &vsize) ||
      !field(24, &rss)) {
    return std::nullopt;
  }
  ProcStat stat;
  const double ticks = static_cast<double>(ticks_per_second);
  stat.cpu_seconds = static_cast<double>(utime + stime) / ticks;
  stat.start_seconds_after_boot = static_cast<double>(start) / ticks;
  stat.virtual_memory_bytes = vsize;
  stat.resident_memory_bytes = rss * static_cast<uint64_t>(page_bytes);
  return stat;
}

HeapStat heapStat() {
  const struct mallinfo2 info = mallinfo2();
  HeapStat stat;
  stat.in_use_bytes = static_cast<uint64_t>(info.uordblks + info.hblkhd);
  stat.free_bytes = static_cast<uint64_t>(info.fordblks);
  return stat;
}

std::shared_ptr<prometheus::Collectable> makeProcessCollector() {
  return std::make_shared<ProcessCollector>();
}

void addBuildInfo(prometheus::Registry& registry) {
  prometheus::BuildGauge()
      .Name("behaviorlib_build_info")
      .Help("1, labelled with the version of behaviorlib and of the libraries it was built with.")
      .Register(registry)
      .Add(
          {{"version", BEHAVIORLIB_VERSION},
           {"grpc_version", grpc::Version()},
           {"protobuf_version", google::protobuf::internal::VersionString(GOOGLE_PROTOBUF_VERSION)},
           {"compiler", __VERSION__},
           {"build_type", BEHAVIORLIB_BUILD_TYPE}})
      .Set(1);
}

}  // namespace behaviorlib::server_kit
