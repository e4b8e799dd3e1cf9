// system_bench: end-to-end figures of a behavior system, measured the way the
// reference figures of the original (ROS 1) behaviorlib were measured: probe
// behaviors stamp CLOCK_MONOTONIC (shared across processes) in shared memory,
// the client stamps its own calls, and random jitter between calls keeps the
// client from phase-locking to the behaviors' ticks.
//
//   system_bench                 # full run (about 2 minutes), markdown to stdout
//   system_bench --smoke         # tiny run for CI: fails on errors, not timings
//   system_bench --window-s 30 --iterations 1000 --anchor-iterations 300
//
// Phases:
//   idle      RSS/PSS and CPU of the 7-behavior system, nothing active.
//   anchor    activate PROBE_1 -> hold 30 ms + U(0,20) -> deactivate -> gap
//             15 ms + U(0,20); first iteration dropped.
//   fast      the same with hold and gap U(0.1,1) ms.
//   goal      WatchEvents subscriber in this process; PROBE_2 activated with a
//             short duration; checkGoal stamp -> finished event received.
//   active    all seven probes active at 100 Hz: CPU and RSS.
//   channel   channel_broker, one publisher at 1 kHz, 10 subscribers (each its
//             own client and reader thread): latency and broker CPU.
//
// Exit code 1 when something is broken (a call fails, an event or stamp does
// not arrive, a server does not exit cleanly); timings never fail the run.

#include <grpcpp/grpcpp.h>
#include <sys/resource.h>
#include <time.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <condition_variable>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <random>
#include <sstream>
#include <stdexcept>
#include <string>
#include <thread>
#include <vector>

#include "behaviorlib/channel/channel_client.h"
#include "behaviorlib/v1/behavior.grpc.pb.h"
#include "behaviorlib/v1/types.pb.h"
#include "bench/bench_shm.h"
#include "support/server_process.h"

namespace behaviorlib::bench {
namespace {

using std::chrono::milliseconds;
using std::chrono::seconds;

/// Something is broken (not slow): the run fails.
class BenchError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

// Long enough never to finish during a run; the parameter's range ends at one
// day.
constexpr double kNeverS = 86400;
constexpr milliseconds kCallDeadline{5000};
constexpr milliseconds kStampTimeout{5000};

// ---------------------------------------------------------------------------
// Options
// ---------------------------------------------------------------------------

struct Options {
  bool smoke = false;
  int anchor_iterations = 300;
  int iterations = 1000;  // fast activations
  int goal_samples = 300;
  int fast_goal_samples = 1000;
  double window_s = 10;
  int subscribers = 10;
  double channel_rate_hz = 1000;
  unsigned seed = 20240611;
};

void usage() {
  std::fprintf(stderr,
               "usage: system_bench [--smoke] [--iterations N] [--anchor-iterations N]\n"
               "                    [--goal-samples N] [--fast-goal-samples N] [--window-s S]\n"
               "                    [--subscribers N] [--seed N]\n"
               "  --smoke               tiny run for CI (fails on errors, never on timings)\n"
               "  --iterations          fast activations (hold/gap U(0.1,1) ms), default 1000\n"
               "  --anchor-iterations   reference-method activations (hold 30+U(0,20) ms,\n"
               "                        gap 15+U(0,20) ms), default 300\n"
               "  --goal-samples        checkGoal -> event samples, 20-30 ms goals, default 300\n"
               "  --fast-goal-samples   checkGoal -> event samples, 1-5 ms goals, default 1000\n"
               "  --window-s            CPU/RSS and channel windows in seconds, default 10\n"
               "  --subscribers         channel subscribers, default 10\n");
}

bool parseOptions(int argc, char** argv, Options* o) {
  for (int i = 1; i < argc; ++i) {
    std::string arg = argv[i];
    std::string value;
    if (auto eq = arg.find('='); eq != std::string::npos) {
      value = arg.substr(eq + 1);
      arg = arg.substr(0, eq);
    } else if (arg != "--smoke" && arg != "--help" && i + 1 < argc) {
      value = argv[++i];
    }
    try {
      if (arg == "--smoke") {
        o->smoke = true;
        o->anchor_iterations = 10;
        o->iterations = 20;
        o->goal_samples = 10;
        o->fast_goal_samples = 10;
        o->window_s = 1;
      } else if (arg == "--iterations") {
        o->iterations = std::stoi(value);
      } else if (arg == "--anchor-iterations") {
        o->anchor_iterations = std::stoi(value);
      } else if (arg == "--goal-samples") {
        o->goal_samples = std::stoi(value);
      } else if (arg == "--fast-goal-samples") {
        o->fast_goal_samples = std::stoi(value);
      } else if (arg == "--window-s") {
        o->window_s = std::stod(value);
      } else if (arg == "--subscribers") {
        o->subscribers = std::stoi(value);
      } else if (arg == "--seed") {
        o->seed = static_cast<unsigned>(std::stoul(value));
      } else {
        usage();
        return false;
      }
    } catch (const std::exception&) {
      std::fprintf(stderr, "system_bench: bad value '%s' for %s\n", value.c_str(), arg.c_str());
      return false;
    }
  }
  if (o->anchor_iterations < 2 || o->iterations < 2 || o->goal_samples < 1 ||
      o->fast_goal_samples < 1 || o->window_s <= 0 || o->subscribers < 1) {
    std::fprintf(stderr, "system_bench: counts must be >= 2 (goal samples >= 1), windows > 0\n");
    return false;
  }
  return true;
}

// ---------------------------------------------------------------------------
// Statistics
// ---------------------------------------------------------------------------

struct Stats {
  size_t n = 0;
  double p50 = 0, p90 = 0, p99 = 0, max = 0;  // milliseconds
};

// Nearest-rank percentiles of samples in nanoseconds, reported in ms.
Stats summarize(std::vector<int64_t> ns) {
  Stats s;
  s.n = ns.size();
  if (ns.empty()) return s;
  std::sort(ns.begin(), ns.end());
  auto at = [&](double p) {
    size_t rank = static_cast<size_t>(std::ceil(p * static_cast<double>(ns.size())));
    rank = std::clamp<size_t>(rank, 1, ns.size());
    return static_cast<double>(ns[rank - 1]) / 1e6;
  };
  s.p50 = at(0.50);
  s.p90 = at(0.90);
  s.p99 = at(0.99);
  s.max = static_cast<double>(ns.back()) / 1e6;
  return s;
}

std::string fmt(const char* format, double v) {
  char buf[64];
  std::snprintf(buf, sizeof(buf), format, v);
  return buf;
}

// ---------------------------------------------------------------------------
// Process resources (/proc)
// ---------------------------------------------------------------------------

struct Memory {
  double rss_mib = 0;   // VmRSS
  double pss_mib = 0;   // Pss from smaps_rollup
  double anon_mib = 0;  // RssAnon
  int threads = 0;
};

// The number after "key:" on its own line of a /proc status-like file; 0 when
// absent.
double procValue(const std::string& text, const std::string& key) {
  size_t pos = text.rfind(key + ":", 0) == 0 ? 0 : text.find("\n" + key + ":");
  if (pos == std::string::npos) return 0;
  pos = text.find(':', pos) + 1;
  return std::strtod(text.c_str() + pos, nullptr);
}

std::string readFile(const std::string& path) {
  std::ifstream in(path);
  std::stringstream ss;
  ss << in.rdbuf();
  return ss.str();
}

Memory readMemory(pid_t pid) {
  Memory m;
  const std::string status = readFile("/proc/" + std::to_string(pid) + "/status");
  if (status.empty()) throw BenchError("cannot read /proc/" + std::to_string(pid) + "/status");
  m.rss_mib = procValue(status, "VmRSS") / 1024;
  m.anon_mib = procValue(status, "RssAnon") / 1024;
  m.threads = static_cast<int>(procValue(status, "Threads"));
  m.pss_mib = procValue(readFile("/proc/" + std::to_string(pid) + "/smaps_rollup"), "Pss") / 1024;
  return m;
}

// utime + stime in clock ticks (the reference method).
int64_t cpuTicks(pid_t pid) {
  const std::string stat = readFile("/proc/" + std::to_string(pid) + "/stat");
  auto close = stat.rfind(')');
  if (close == std::string::npos) throw BenchError("cannot read /proc/<pid>/stat");
  std::istringstream in(stat.substr(close + 2));
  std::vector<std::string> fields;
  for (std::string f; in >> f;) fields.push_back(f);
  // Fields after the command: [0] is field 3 (state); utime is field 14.
  if (fields.size() < 13) throw BenchError("short /proc/<pid>/stat");
  return std::stoll(fields[11]) + std::stoll(fields[12]);
}

// Process CPU time in ns (all threads), finer than the tick counters.
int64_t cpuNs(pid_t pid) {
  clockid_t clock;
  if (clock_getcpuclockid(pid, &clock) != 0) return -1;
  timespec ts;
  if (clock_gettime(clock, &ts) != 0) return -1;
  return static_cast<int64_t>(ts.tv_sec) * 1000000000LL + ts.tv_nsec;
}

struct CpuSample {
  int64_t wall_ns, ticks, ns;
};
CpuSample sampleCpu(pid_t pid) { return {monotonicNs(), cpuTicks(pid), cpuNs(pid)}; }

struct CpuUsage {
  double ticks_percent = 0;  // utime+stime, 10 ms resolution
  double ns_percent = 0;     // process CPU clock
};
CpuUsage cpuBetween(const CpuSample& a, const CpuSample& b) {
  const double wall = static_cast<double>(b.wall_ns - a.wall_ns);
  const double tick_ns = 1e9 / static_cast<double>(sysconf(_SC_CLK_TCK));
  CpuUsage u;
  u.ticks_percent = 100.0 * static_cast<double>(b.ticks - a.ticks) * tick_ns / wall;
  u.ns_percent = a.ns < 0 || b.ns < 0 ? -1 : 100.0 * static_cast<double>(b.ns - a.ns) / wall;
  return u;
}

struct Resources {
  Memory memory;
  CpuUsage cpu;
};
Resources measureWindow(pid_t pid, double window_s) {
  const CpuSample a = sampleCpu(pid);
  std::this_thread::sleep_for(std::chrono::duration<double>(window_s));
  const CpuSample b = sampleCpu(pid);
  return {readMemory(pid), cpuBetween(a, b)};
}

// ---------------------------------------------------------------------------
// The behavior system and its client
// ---------------------------------------------------------------------------

class StampFile {
 public:
  StampFile() {
    char tmpl[] = "/tmp/behaviorlib-bench-shm-XXXXXX";
    const int fd = mkstemp(tmpl);
    if (fd < 0) throw BenchError("mkstemp failed");
    close(fd);
    path_ = tmpl;
    stamps_ = mapSharedStamps(path_, /*create=*/true);
    if (stamps_ == nullptr) throw BenchError("cannot map " + path_);
  }
  ~StampFile() {
    munmap(stamps_, sizeof(SharedStamps));
    unlink(path_.c_str());
  }
  StampFile(const StampFile&) = delete;
  StampFile& operator=(const StampFile&) = delete;
  const std::string& path() const { return path_; }
  ProbeSlot& probe(int i) { return stamps_->probes[i]; }

 private:
  std::string path_;
  SharedStamps* stamps_ = nullptr;
};

// Waits (polling; the stamps are taken by the server, so polling does not
// change them) until `seq` passes `before`; returns `stamp`.
int64_t waitStamp(const std::atomic<uint64_t>& seq, uint64_t before,
                  const std::atomic<int64_t>& stamp, const char* what) {
  const int64_t deadline = monotonicNs() + kStampTimeout.count() * 1000000LL;
  int spins = 0;
  while (seq.load(std::memory_order_acquire) <= before) {
    if (monotonicNs() > deadline) throw BenchError(std::string("no ") + what + " stamp in time");
    if (++spins > 100) std::this_thread::sleep_for(std::chrono::microseconds(20));
  }
  return stamp.load(std::memory_order_relaxed);
}

void setDeadline(grpc::ClientContext* ctx) {
  ctx->set_deadline(std::chrono::system_clock::now() + kCallDeadline);
}

std::string describe(const grpc::Status& s) {
  return "code " + std::to_string(s.error_code()) + ": " + s.error_message();
}

class SystemClient {
 public:
  explicit SystemClient(const std::string& address)
      : channel_(grpc::CreateChannel(address, grpc::InsecureChannelCredentials())),
        stub_(v1::BehaviorSystem::NewStub(channel_)) {}

  v1::BehaviorSystem::Stub& stub() { return *stub_; }

  // Waits for the server and checks that it hosts the probes.
  void checkProbes() {
    grpc::ClientContext ctx;
    setDeadline(&ctx);
    ctx.set_wait_for_ready(true);
    v1::ListBehaviorsResponse response;
    grpc::Status s = stub_->ListBehaviors(&ctx, v1::ListBehaviorsRequest(), &response);
    if (!s.ok()) throw BenchError("ListBehaviors failed: " + describe(s));
    if (response.behaviors_size() != kProbeCount) {
      throw BenchError("expected " + std::to_string(kProbeCount) + " probes, got " +
                       std::to_string(response.behaviors_size()));
    }
  }

  static v1::ActivateBehaviorRequest activateRequest(const std::string& behavior,
                                                     double duration_s) {
    v1::ActivateBehaviorRequest request;
    request.set_behavior(behavior);
    (*request.mutable_parameters()->mutable_fields())["duration_s"].set_number_value(duration_s);
    return request;
  }

  // Activates; `t0`/`t1` bracket the call.
  std::string activate(const v1::ActivateBehaviorRequest& request, int64_t* t0, int64_t* t1) {
    grpc::ClientContext ctx;
    setDeadline(&ctx);
    v1::ActivateResponse response;
    *t0 = monotonicNs();
    grpc::Status s = stub_->ActivateBehavior(&ctx, request, &response);
    *t1 = monotonicNs();
    if (!s.ok())
      throw BenchError("ActivateBehavior(" + request.behavior() + ") failed: " + describe(s));
    if (response.activation_id().empty()) throw BenchError("Activate returned no activation_id");
    return response.activation_id();
  }

  // CheckBehaviorActivation: a unary call that runs no user code and does not
  // wait for the behavior's worker (the transport's floor); returns its
  // round trip.
  int64_t checkActivation(const std::string& behavior) {
    v1::CheckBehaviorActivationRequest request;
    request.set_behavior(behavior);
    grpc::ClientContext ctx;
    setDeadline(&ctx);
    v1::CheckActivationResponse response;
    const int64_t t0 = monotonicNs();
    grpc::Status s = stub_->CheckBehaviorActivation(&ctx, request, &response);
    const int64_t t1 = monotonicNs();
    if (!s.ok()) throw BenchError("CheckBehaviorActivation failed: " + describe(s));
    return t1 - t0;
  }

  // Deactivates (expects it still active); `t0`/`t1` bracket the call.
  void deactivate(const std::string& behavior, const std::string& activation_id, int64_t* t0,
                  int64_t* t1) {
    v1::DeactivateBehaviorRequest request;
    request.set_behavior(behavior);
    request.set_activation_id(activation_id);
    grpc::ClientContext ctx;
    setDeadline(&ctx);
    v1::DeactivateResponse response;
    *t0 = monotonicNs();
    grpc::Status s = stub_->DeactivateBehavior(&ctx, request, &response);
    *t1 = monotonicNs();
    if (!s.ok()) throw BenchError("DeactivateBehavior(" + behavior + ") failed: " + describe(s));
    if (response.already_finished() || response.cause() != v1::TERMINATION_CAUSE_INTERRUPTED) {
      throw BenchError("DeactivateBehavior(" + behavior + "): activation had already finished");
    }
  }

 private:
  std::shared_ptr<grpc::Channel> channel_;
  std::unique_ptr<v1::BehaviorSystem::Stub> stub_;
};

// A WatchEvents subscriber with its own reader thread, which stamps
// CLOCK_MONOTONIC as soon as each message is read.
class EventWatcher {
 public:
  struct Finished {
    int64_t received_ns;
    v1::TerminationCause cause;
  };

  EventWatcher(v1::BehaviorSystem::Stub& stub, const std::string& behavior) {
    request_.add_behaviors(behavior);
    thread_ = std::thread([this, &stub] { readLoop(stub); });
  }
  ~EventWatcher() {
    context_.TryCancel();
    thread_.join();
  }
  EventWatcher(const EventWatcher&) = delete;
  EventWatcher& operator=(const EventWatcher&) = delete;

  void waitStarted() {
    std::unique_lock lock(mutex_);
    if (!cv_.wait_for(lock, kCallDeadline, [this] { return started_ || ended_; }) || !started_) {
      throw BenchError("WatchEvents did not start: " + describe(status_));
    }
  }

  Finished waitFinished(const std::string& activation_id) {
    std::unique_lock lock(mutex_);
    const bool got = cv_.wait_for(lock, kCallDeadline,
                                  [&] { return ended_ || finished_.count(activation_id) > 0; });
    auto it = finished_.find(activation_id);
    if (!got || it == finished_.end()) {
      throw BenchError("no finished event for activation " + activation_id +
                       (ended_ ? " (stream ended: " + describe(status_) + ")" : ""));
    }
    Finished f = it->second;
    finished_.erase(it);
    return f;
  }

 private:
  void readLoop(v1::BehaviorSystem::Stub& stub) {
    auto reader = stub.WatchEvents(&context_, request_);
    v1::WatchEventsResponse message;
    while (reader->Read(&message)) {
      const int64_t now = monotonicNs();
      std::lock_guard lock(mutex_);
      if (message.has_start()) {
        started_ = true;
      } else if (message.event().has_finished()) {
        finished_[message.event().activation_id()] = {now, message.event().finished().cause()};
      } else {
        continue;
      }
      cv_.notify_all();
    }
    grpc::Status status = reader->Finish();
    std::lock_guard lock(mutex_);
    status_ = status;
    ended_ = true;
    cv_.notify_all();
  }

  v1::WatchEventsRequest request_;
  grpc::ClientContext context_;
  std::thread thread_;
  std::mutex mutex_;
  std::condition_variable cv_;
  bool started_ = false;
  bool ended_ = false;
  grpc::Status status_;
  std::map<std::string, Finished> finished_;
};

void sleepMs(double ms) {
  std::this_thread::sleep_for(std::chrono::duration<double, std::milli>(ms));
}

// ---------------------------------------------------------------------------
// Phases
// ---------------------------------------------------------------------------

struct ActivationResult {
  Stats first_execute, activate_rtt, deactivate_rtt;
};

// activate -> hold -> deactivate -> gap, `iterations` times; the first is
// dropped.
ActivationResult runActivations(SystemClient& client, ProbeSlot& slot, int iterations,
                                double hold_min_ms, double hold_max_ms, double gap_min_ms,
                                double gap_max_ms, std::mt19937& rng) {
  std::uniform_real_distribution<double> hold(hold_min_ms, hold_max_ms);
  std::uniform_real_distribution<double> gap(gap_min_ms, gap_max_ms);
  std::vector<int64_t> first, activate_rtt, deactivate_rtt;
  const auto request = SystemClient::activateRequest("PROBE_1", kNeverS);
  for (int i = 0; i < iterations; ++i) {
    const uint64_t seq = slot.first_execute_seq.load(std::memory_order_acquire);
    int64_t t0, t1, t2, t3;
    const std::string id = client.activate(request, &t0, &t1);
    const int64_t executed =
        waitStamp(slot.first_execute_seq, seq, slot.first_execute_ns, "first onExecute");
    sleepMs(hold(rng));
    client.deactivate("PROBE_1", id, &t2, &t3);
    sleepMs(gap(rng));
    if (i == 0) continue;
    first.push_back(executed - t0);
    activate_rtt.push_back(t1 - t0);
    deactivate_rtt.push_back(t3 - t2);
  }
  return {summarize(first), summarize(activate_rtt), summarize(deactivate_rtt)};
}

// The gRPC floor under the same idle pattern: CheckBehaviorActivation round
// trips with random gaps; the first is dropped.
Stats runFloor(SystemClient& client, int calls, double gap_min_ms, double gap_max_ms,
               std::mt19937& rng) {
  std::uniform_real_distribution<double> gap(gap_min_ms, gap_max_ms);
  std::vector<int64_t> rtt;
  for (int i = 0; i < calls; ++i) {
    const int64_t ns = client.checkActivation("PROBE_3");
    if (i > 0) rtt.push_back(ns);
    sleepMs(gap(rng));
  }
  return summarize(rtt);
}

// One Prometheus histogram of one behavior, scraped from /metrics.
struct Histogram {
  std::vector<std::pair<double, double>> buckets;  // (le, cumulative count)
  double sum = 0;
  double count = 0;
};

Histogram scrapeHistogram(int metrics_port, const std::string& name, const std::string& behavior) {
  const std::string body = support::httpGet(metrics_port, "/metrics");
  if (body.empty()) throw BenchError("cannot scrape /metrics");
  Histogram h;
  const std::string label = "behavior=\"" + behavior + "\"";
  std::istringstream in(body);
  for (std::string line; std::getline(in, line);) {
    if (line.rfind(name + "_", 0) != 0 || line.find(label) == std::string::npos) continue;
    const auto close = line.rfind('}');
    if (close == std::string::npos) continue;
    const double value = std::strtod(line.c_str() + close + 1, nullptr);
    const std::string kind = line.substr(name.size() + 1, line.find('{') - name.size() - 1);
    if (kind == "sum") {
      h.sum = value;
    } else if (kind == "count") {
      h.count = value;
    } else if (kind == "bucket") {
      const auto le = line.find("le=\"");
      if (le == std::string::npos) continue;
      const std::string bound = line.substr(le + 4, line.find('"', le + 4) - le - 4);
      h.buckets.push_back(
          {bound == "+Inf" ? INFINITY : std::strtod(bound.c_str(), nullptr), value});
    }
  }
  std::sort(h.buckets.begin(), h.buckets.end());
  return h;
}

Histogram operator-(const Histogram& a, const Histogram& b) {
  Histogram d = a;
  d.sum -= b.sum;
  d.count -= b.count;
  for (auto& [le, n] : d.buckets) {
    for (const auto& [ble, bn] : b.buckets) {
      if (ble == le) n -= bn;
    }
  }
  return d;
}

// Upper bound (the bucket's le) of quantile q, in ms; "> last" as INFINITY.
double bucketQuantileMs(const Histogram& h, double q) {
  for (const auto& [le, n] : h.buckets) {
    if (n >= q * h.count) return le * 1e3;
  }
  return INFINITY;
}

std::string histogramText(const Histogram& h) {
  if (h.count <= 0) return "no samples";
  auto bound = [](double ms) {
    return std::isinf(ms) ? std::string("> 1000") : "≤ " + fmt("%.3f", ms);
  };
  return "mean " + fmt("%.3f", h.sum / h.count * 1e3) + ", p50 " + bound(bucketQuantileMs(h, 0.5)) +
         ", p99 " + bound(bucketQuantileMs(h, 0.99)) + " (n " + fmt("%.0f", h.count) + ")";
}

// PROBE_2 with a goal `duration` away; checkGoal stamp -> finished event read
// by this process.
Stats runGoalToEvent(SystemClient& client, ProbeSlot& slot, int samples, double duration_min_s,
                     double duration_max_s, double gap_min_ms, double gap_max_ms,
                     std::mt19937& rng) {
  std::uniform_real_distribution<double> duration(duration_min_s, duration_max_s);
  std::uniform_real_distribution<double> gap(gap_min_ms, gap_max_ms);
  EventWatcher watcher(client.stub(), "PROBE_2");
  watcher.waitStarted();
  std::vector<int64_t> latency;
  for (int i = 0; i < samples + 1; ++i) {
    const uint64_t seq = slot.goal_seq.load(std::memory_order_acquire);
    int64_t t0, t1;
    const std::string id =
        client.activate(SystemClient::activateRequest("PROBE_2", duration(rng)), &t0, &t1);
    const EventWatcher::Finished finished = watcher.waitFinished(id);
    if (finished.cause != v1::TERMINATION_CAUSE_GOAL_ACHIEVED) {
      throw BenchError("PROBE_2 finished with cause " + std::to_string(finished.cause) +
                       ", expected GOAL_ACHIEVED");
    }
    const int64_t goal = waitStamp(slot.goal_seq, seq, slot.goal_ns, "checkGoal");
    if (i > 0) latency.push_back(finished.received_ns - goal);
    sleepMs(gap(rng));
  }
  return summarize(latency);
}

struct ChannelResult {
  Stats latency;
  uint64_t published = 0;
  uint64_t expected = 0;
  uint64_t received = 0;
  Resources broker;
  CpuUsage client_cpu;
};

ChannelResult runChannel(const Options& o) {
  support::ServerProcess broker(BEHAVIORLIB_CHANNEL_BROKER_PATH, {});
  if (!broker.start()) throw BenchError("channel_broker: " + broker.error());
  const std::string topic = "robots/bench/pose";

  // Samples with header.seq below kWarmup only warm the path up.
  constexpr uint64_t kWarmup = 200;
  struct Subscriber {
    std::unique_ptr<channel::ChannelClient> client;
    std::unique_ptr<channel::Subscription> subscription;
    std::vector<int64_t> latency;
  };
  std::vector<Subscriber> subscribers(static_cast<size_t>(o.subscribers));
  const size_t expected_each = static_cast<size_t>(o.window_s * o.channel_rate_hz) + 16;
  for (auto& s : subscribers) {
    s.latency.reserve(expected_each);
    s.client = std::make_unique<channel::ChannelClient>(broker.address());
    channel::SubscribeOptions options;
    options.mode = v1::DELIVERY_MODE_QUEUE;
    options.queue_size = 1000;
    std::vector<int64_t>* out = &s.latency;
    s.subscription = s.client->subscribeTyped<v1::PoseStamped>(
        topic, options, [out](const v1::PoseStamped& pose) {
          const int64_t now = monotonicNs();
          if (pose.header().seq() < kWarmup) return;
          const auto& stamp = pose.header().stamp();
          out->push_back(now - (stamp.seconds() * 1000000000LL + stamp.nanos()));
        });
  }
  for (auto& s : subscribers) {
    if (!s.subscription->waitConnected(kCallDeadline)) {
      throw BenchError("channel subscription did not connect: " +
                       std::string(s.subscription->status().message()));
    }
  }

  channel::ChannelClient publisher(broker.address());
  v1::PoseStamped pose;
  pose.mutable_header()->set_frame_id("world");
  pose.mutable_header()->set_robot_id("bench");
  pose.mutable_pose()->mutable_orientation()->set_w(1);
  const int64_t period_ns = static_cast<int64_t>(1e9 / o.channel_rate_hz);
  const uint64_t total = kWarmup + static_cast<uint64_t>(o.window_s * o.channel_rate_hz);
  ChannelResult result;
  CpuSample broker_start{}, client_start{};
  timespec next;
  clock_gettime(CLOCK_MONOTONIC, &next);
  for (uint64_t seq = 0; seq < total; ++seq) {
    if (seq == kWarmup) {
      broker_start = sampleCpu(broker.pid());
      client_start = sampleCpu(getpid());
    }
    next.tv_nsec += period_ns;
    while (next.tv_nsec >= 1000000000L) {
      next.tv_nsec -= 1000000000L;
      ++next.tv_sec;
    }
    clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &next, nullptr);
    const int64_t now = monotonicNs();
    pose.mutable_header()->set_seq(seq);
    pose.mutable_header()->mutable_stamp()->set_seconds(now / 1000000000LL);
    pose.mutable_header()->mutable_stamp()->set_nanos(static_cast<int32_t>(now % 1000000000LL));
    if (absl::Status s = publisher.publish(topic, pose); !s.ok()) {
      throw BenchError("publish failed: " + std::string(s.message()));
    }
  }
  const CpuSample broker_end = sampleCpu(broker.pid());
  const CpuSample client_end = sampleCpu(getpid());
  result.broker.cpu = cpuBetween(broker_start, broker_end);
  result.broker.memory = readMemory(broker.pid());
  result.client_cpu = cpuBetween(client_start, client_end);
  result.published = total - kWarmup;
  result.expected = result.published * subscribers.size();

  sleepMs(300);  // let the last samples arrive
  std::vector<int64_t> all;
  for (auto& s : subscribers) {
    s.subscription.reset();  // joins the reader: its vector is ours now
    if (s.latency.empty()) throw BenchError("a channel subscriber received nothing");
    all.insert(all.end(), s.latency.begin(), s.latency.end());
  }
  result.received = all.size();
  result.latency = summarize(std::move(all));
  if (absl::StatusOr<uint64_t> flushed = publisher.flush(); !flushed.ok()) {
    throw BenchError("publisher flush failed: " + std::string(flushed.status().message()));
  }
  subscribers.clear();
  if (int code = broker.terminate(); code != 0) {
    throw BenchError("channel_broker exited with " + std::to_string(code));
  }
  return result;
}

// ---------------------------------------------------------------------------
// Report
// ---------------------------------------------------------------------------

struct LatencyRow {
  std::string figure;
  Stats stats;
  std::string target;  // "p50 / p99" in ms, or "—"
  double target_p50 = 0, target_p99 = 0;
  std::string reference;
};

void printLatencyTable(const std::vector<LatencyRow>& rows) {
  std::printf(
      "| figure (ms) | n | p50 | p90 | p99 | max | target p50 / p99 | ROS 1 reference p50 / "
      "p99 (100 Hz) | verdict |\n"
      "|---|---:|---:|---:|---:|---:|---|---|---|\n");
  for (const auto& r : rows) {
    std::string verdict = "—";
    if (r.target_p50 > 0) {
      const bool p50 = r.stats.p50 <= r.target_p50;
      const bool p99 = r.stats.p99 <= r.target_p99;
      verdict = p50 && p99     ? "meets"
                : !p50 && !p99 ? "misses p50 and p99"
                : !p50         ? "misses p50"
                               : "misses p99";
    }
    std::printf("| %s | %zu | %.3f | %.3f | %.3f | %.3f | %s | %s | %s |\n", r.figure.c_str(),
                r.stats.n, r.stats.p50, r.stats.p90, r.stats.p99, r.stats.max, r.target.c_str(),
                r.reference.c_str(), verdict.c_str());
  }
}

std::string cpuText(const CpuUsage& u) {
  return fmt("%.2f %%", u.ns_percent) + " (ticks: " + fmt("%.2f %%", u.ticks_percent) + ")";
}

int run(const Options& o) {
  std::mt19937 rng(o.seed);
  StampFile stamps;
  setenv(kShmEnv, stamps.path().c_str(), 1);
  support::ServerProcess system(BEHAVIORLIB_BENCH_SYSTEM_PATH,
                                {"--clock", "steady", "--robot-id", "bench"});
  if (!system.start()) throw BenchError("bench_behavior_system: " + system.error());
  SystemClient client(system.address());
  client.checkProbes();

  std::fprintf(stderr, "system_bench: idle window %.0f s\n", o.window_s);
  sleepMs(o.smoke ? 200 : 2000);  // settle after start-up
  const Resources idle = measureWindow(system.pid(), o.window_s);

  const int metrics = system.metricsPort();
  const std::string t3 = "behaviorlib_activation_seconds";
  std::fprintf(stderr, "system_bench: %d activations, reference method\n", o.anchor_iterations);
  const Histogram t3_start = scrapeHistogram(metrics, t3, "PROBE_1");
  const ActivationResult anchor =
      runActivations(client, stamps.probe(0), o.anchor_iterations, 30, 50, 15, 35, rng);
  const Histogram t3_anchor = scrapeHistogram(metrics, t3, "PROBE_1");
  std::fprintf(stderr, "system_bench: %d activations, fast\n", o.iterations);
  const ActivationResult fast =
      runActivations(client, stamps.probe(0), o.iterations, 0.1, 1, 0.1, 1, rng);
  const Histogram t3_fast = scrapeHistogram(metrics, t3, "PROBE_1");
  std::fprintf(stderr, "system_bench: gRPC floor, %d + %d calls\n", o.anchor_iterations,
               o.iterations);
  const Stats floor_slow = runFloor(client, o.anchor_iterations, 15, 50, rng);
  const Stats floor_fast = runFloor(client, o.iterations, 0.1, 1, rng);

  std::fprintf(stderr, "system_bench: %d + %d goal -> event samples\n", o.goal_samples,
               o.fast_goal_samples);
  const Stats goal =
      runGoalToEvent(client, stamps.probe(1), o.goal_samples, 0.02, 0.03, 5, 15, rng);
  const Stats fast_goal =
      runGoalToEvent(client, stamps.probe(1), o.fast_goal_samples, 0.001, 0.005, 0.1, 1, rng);

  std::fprintf(stderr, "system_bench: all %d probes active, window %.0f s\n", kProbeCount,
               o.window_s);
  std::vector<std::string> ids;
  for (int i = 0; i < kProbeCount; ++i) {
    int64_t t0, t1;
    ids.push_back(client.activate(
        SystemClient::activateRequest("PROBE_" + std::to_string(i + 1), kNeverS), &t0, &t1));
  }
  sleepMs(o.smoke ? 200 : 1000);
  const std::string t1 = "behaviorlib_monitoring_seconds";
  std::vector<Histogram> monitoring_start;
  for (int i = 0; i < kProbeCount; ++i) {
    monitoring_start.push_back(scrapeHistogram(metrics, t1, "PROBE_" + std::to_string(i + 1)));
  }
  const Resources active = measureWindow(system.pid(), o.window_s);
  Histogram monitoring;
  for (int i = 0; i < kProbeCount; ++i) {
    const Histogram d = scrapeHistogram(metrics, t1, "PROBE_" + std::to_string(i + 1)) -
                        monitoring_start[static_cast<size_t>(i)];
    monitoring.sum += d.sum;
    monitoring.count += d.count;
  }
  for (int i = 0; i < kProbeCount; ++i) {
    int64_t t0, t1;
    client.deactivate("PROBE_" + std::to_string(i + 1), ids[static_cast<size_t>(i)], &t0, &t1);
  }
  sleepMs(o.smoke ? 200 : 1000);
  const Resources after = measureWindow(system.pid(), o.smoke ? 0.5 : o.window_s);

  std::fprintf(stderr, "system_bench: channel, %d subscribers at %.0f Hz, window %.0f s\n",
               o.subscribers, o.channel_rate_hz, o.window_s);
  const ChannelResult channel = runChannel(o);

  if (int code = system.terminate(); code != 0) {
    throw BenchError("bench_behavior_system exited with " + std::to_string(code));
  }

  // ---- Report ----------------------------------------------------------------
  std::printf("## Activation and events\n\n");
  const std::string a_hold = " (hold 30+U(0,20) ms, gap 15+U(0,20) ms)";
  const std::string f_hold = " (hold, gap U(0.1,1) ms)";
  printLatencyTable({
      {"activate call → first onExecute" + a_hold, anchor.first_execute, "≤ 0.25 / ≤ 1", 0.25, 1.0,
       "6.56 / 13.7"},
      {"activate round trip" + a_hold, anchor.activate_rtt, "≤ 0.25 / ≤ 1", 0.25, 1.0,
       "6.64 / 13.8"},
      {"deactivate round trip" + a_hold, anchor.deactivate_rtt, "—", 0, 0, "6.58 / 12.0"},
      {"activate call → first onExecute" + f_hold, fast.first_execute, "≤ 0.25 / ≤ 1", 0.25, 1.0,
       "6.56 / 13.7"},
      {"activate round trip" + f_hold, fast.activate_rtt, "≤ 0.25 / ≤ 1", 0.25, 1.0, "6.64 / 13.8"},
      {"deactivate round trip" + f_hold, fast.deactivate_rtt, "—", 0, 0, "6.58 / 12.0"},
      {"checkGoal true → finished event received (goals 20-30 ms)", goal, "≤ 0.2 / ≤ 1", 0.2, 1.0,
       "0.28 / 1.74"},
      {"checkGoal true → finished event received (goals 1-5 ms)", fast_goal, "≤ 0.2 / ≤ 1", 0.2,
       1.0, "0.28 / 1.74"},
      {"floor: CheckBehaviorActivation round trip (gaps U(15,50) ms)", floor_slow, "—", 0, 0,
       "gRPC floor on this VM class: 0.155-0.215 / 0.32-0.45"},
      {"floor: CheckBehaviorActivation round trip (gaps U(0.1,1) ms)", floor_fast, "—", 0, 0,
       "gRPC floor on this VM class: 0.155-0.215 / 0.32-0.45"},
  });

  std::printf("\n## Inside the system process (its own Prometheus histograms)\n\n");
  std::printf(
      "| figure (ms) | value (p50/p99: upper bucket bounds) |\n|---|---|\n"
      "| Activate request received → first onExecute, reference method | %s |\n"
      "| Activate request received → first onExecute, fast | %s |\n"
      "| the four monitoring functions of one tick, 7 probes active at 100 Hz (µs) | mean "
      "%.3f (n %.0f) |\n",
      histogramText(t3_anchor - t3_start).c_str(), histogramText(t3_fast - t3_anchor).c_str(),
      monitoring.count > 0 ? monitoring.sum / monitoring.count * 1e6 : 0.0, monitoring.count);

  std::printf("\n## Resources of the 7-behavior system (window %.0f s)\n\n", o.window_s);
  std::printf(
      "| state | VmRSS (MiB) | PSS (MiB) | anonymous (MiB) | threads | CPU of one core | target | "
      "ROS 1 reference (7 nodes + roslaunch) | verdict |\n"
      "|---|---:|---:|---:|---:|---|---|---|---|\n");
  auto resourceRow = [](const char* state, const Resources& r, const std::string& target,
                        const std::string& reference, const std::string& verdict) {
    std::printf("| %s | %.1f | %.1f | %.1f | %d | %s | %s | %s | %s |\n", state, r.memory.rss_mib,
                r.memory.pss_mib, r.memory.anon_mib, r.memory.threads, cpuText(r.cpu).c_str(),
                target.c_str(), reference.c_str(), verdict.c_str());
  };
  const bool idle_ok = idle.memory.rss_mib <= 20 && idle.cpu.ns_percent <= 0.5;
  resourceRow("idle (after start-up)", idle, "RSS ≤ 20 MiB, CPU ≤ 0.5 %", "126.8 MiB, 3.15 %",
              idle_ok ? "meets" : "misses");
  resourceRow("all 7 active at 100 Hz", active, "CPU ≤ 3 %", "—",
              active.cpu.ns_percent <= 3 ? "meets" : "misses");
  resourceRow("idle again (after the runs)", after, "RSS ≤ 20 MiB, CPU ≤ 0.5 %", "—",
              after.memory.rss_mib <= 20 && after.cpu.ns_percent <= 0.5 ? "meets" : "misses");

  std::printf("\n## Data channel: 1 publisher at %.0f Hz → %d subscribers (window %.0f s)\n\n",
              o.channel_rate_hz, o.subscribers, o.window_s);
  std::printf(
      "| figure | value |\n|---|---|\n"
      "| publish stamp → subscriber callback, p50 / p90 / p99 / max (ms) | %.3f / %.3f / %.3f / "
      "%.3f |\n"
      "| samples published / delivered (of expected) | %llu / %llu (of %llu) |\n"
      "| broker CPU of one core | %s |\n"
      "| broker VmRSS / PSS (MiB) | %.1f / %.1f |\n"
      "| bench process CPU (publisher + %d subscribers) | %s |\n",
      channel.latency.p50, channel.latency.p90, channel.latency.p99, channel.latency.max,
      static_cast<unsigned long long>(channel.published),
      static_cast<unsigned long long>(channel.received),
      static_cast<unsigned long long>(channel.expected), cpuText(channel.broker.cpu).c_str(),
      channel.broker.memory.rss_mib, channel.broker.memory.pss_mib, o.subscribers,
      cpuText(channel.client_cpu).c_str());
  std::printf(
      "\nCPU: process CPU clock over the window (in brackets utime+stime from /proc/<pid>/stat, "
      "%ld Hz ticks).%s\n",
      sysconf(_SC_CLK_TCK), o.smoke ? " Smoke run: figures are not meaningful." : "");
  return 0;
}

}  // namespace
}  // namespace behaviorlib::bench

int main(int argc, char** argv) {
  behaviorlib::bench::Options options;
  for (int i = 1; i < argc; ++i) {
    if (std::strcmp(argv[i], "--help") == 0) {
      behaviorlib::bench::usage();
      return 0;
    }
  }
  if (!behaviorlib::bench::parseOptions(argc, argv, &options)) return 2;
  try {
    return behaviorlib::bench::run(options);
  } catch (const behaviorlib::bench::BenchError& e) {
    std::fprintf(stderr, "system_bench: FAILED: %s\n", e.what());
    return 1;
  } catch (const std::exception& e) {
    std::fprintf(stderr, "system_bench: FAILED: %s\n", e.what());
    return 1;
  }
}
