// coordinator_bench: throughput and latency of the coordinator (issue 4 §12)
// with the real `coordinator` binary and 20 real behavior systems
// (coordinator_bench_system, each its own process, own port and own system
// name, registered through the library's --coordinator support), all on
// loopback with free ports.
//
//   coordinator_bench                  # full run (about 1 minute), markdown to stdout
//   coordinator_bench --smoke          # tiny run for CI: fails on errors, not timings
//   coordinator_bench --behaviors 100,1000 --window-s 15 --activations 500 --robots 1
//
// For each fleet size (--behaviors, spread evenly over --systems systems,
// behaviors BENCH_0001.., all systems serving robot "bench" unless --robots
// spreads them):
//   idle        CPU of the coordinator and the systems with nothing to do.
//   events      --subscribers clients each open Coordinator.WatchEvents (own
//               connection, no filter, live events only). One driver thread
//               per system calls BehaviorSystem.ActivateBehavior on its
//               system directly, round robin over its behaviors, with
//               duration_s 0: each activation yields an activated and a
//               finished event (GOAL_ACHIEVED on the first tick). First as
//               fast as the machine allows, then at a fixed rate
//               (--paced-events-per-s) for the lag below saturation. The
//               drivers hold back while a subscriber is more than --max-lag
//               events behind, so that no subscriber reaches the
//               coordinator's per-subscriber queue limit (4096). Measured over
//               a window after a warm-up: events/s into the coordinator (its
//               own counter), events/s delivered to each subscriber, the lag
//               of each event (the system's wall_time of the event ->
//               received by the subscriber, and the coordinator's wall_time
//               -> received), the lag in events, and the CPU of each party.
//               Afterwards every subscriber must have received every
//               activated and finished event exactly once, with consecutive
//               coordinator seqs.
//   activation  --activations iterations, each on the next behavior (round
//               robin over the systems), in random order: through the
//               coordinator (Coordinator.ActivateBehavior with duration_s
//               86400, then Coordinator.DeactivateBehavior) and directly
//               (BehaviorSystem.ActivateBehavior, DeactivateBehavior) on the
//               same behavior, plus one direct CheckBehaviorActivation (the
//               gRPC floor); U(0.1,1) ms between calls; first iteration
//               dropped.
//
// The coordinator runs without --catalog and the requests leave skip_plan
// unset. Children are killed when this process dies (PR_SET_PDEATHSIG) and
// their output goes to log files, kept (and named) only when the run fails.
// Exit code 1 when something is broken (a call fails, an event is lost or
// doubled, a process does not exit cleanly); timings never fail the run.

#include <fcntl.h>
#include <grpcpp/grpcpp.h>
#include <sched.h>
#include <signal.h>
#include <sys/prctl.h>
#include <sys/wait.h>
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
#include <filesystem>
#include <fstream>
#include <map>
#include <memory>
#include <mutex>
#include <random>
#include <sstream>
#include <stdexcept>
#include <string>
#include <thread>
#include <vector>

#include "behaviorlib/v1/behavior.grpc.pb.h"
#include "behaviorlib/v1/coordinator.grpc.pb.h"
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

int64_t monotonicNs() {
  timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return static_cast<int64_t>(ts.tv_sec) * 1000000000LL + ts.tv_nsec;
}

int64_t wallNs() {
  timespec ts;
  clock_gettime(CLOCK_REALTIME, &ts);
  return static_cast<int64_t>(ts.tv_sec) * 1000000000LL + ts.tv_nsec;
}

int64_t toNs(const google::protobuf::Timestamp& t) {
  return t.seconds() * 1000000000LL + t.nanos();
}

void sleepS(double s) { std::this_thread::sleep_for(std::chrono::duration<double>(s)); }

std::string describe(const grpc::Status& s) {
  return "code " + std::to_string(s.error_code()) + ": " + s.error_message();
}

// Every call goes to a server that is up. Each client opens a connection of
// its own (ownChannel), several at the same moment, and a fail-fast call
// fails at the first failed attempt of its new connection (UNAVAILABLE
// "failed to connect to all addresses"), which made the smoke run fail once
// beside another test; waiting for ready lets gRPC retry the connection,
// with backoff, within the call's deadline.
void setDeadline(grpc::ClientContext* ctx, milliseconds limit = kCallDeadline) {
  ctx->set_deadline(std::chrono::system_clock::now() + limit);
  ctx->set_wait_for_ready(true);
}

// Each client its own TCP connection (gRPC otherwise shares one between
// channels to the same address).
std::shared_ptr<grpc::Channel> ownChannel(const std::string& address) {
  grpc::ChannelArguments args;
  args.SetInt(GRPC_ARG_USE_LOCAL_SUBCHANNEL_POOL, 1);
  return grpc::CreateCustomChannel(address, grpc::InsecureChannelCredentials(), args);
}

// ---------------------------------------------------------------------------
// Options
// ---------------------------------------------------------------------------

struct Options {
  bool smoke = false;
  int systems = 20;
  int subscribers = 10;
  std::vector<int> behaviors = {100, 1000};
  double warmup_s = 2;
  double window_s = 15;
  int activations = 500;
  int max_lag = 1000;
  double paced_events_per_s = 1000;
  double paced_window_s = 5;
  int robots = 1;
  int batch = 64;  // WatchEvents max_events_per_message of the subscribers
  unsigned seed = 20240611;
};

void usage() {
  std::fprintf(
      stderr,
      "usage: coordinator_bench [--smoke] [--systems N] [--subscribers N] [--behaviors N,M,...]\n"
      "                         [--warmup-s S] [--window-s S] [--activations N] [--max-lag N]\n"
      "                         [--paced-events-per-s R] [--paced-window-s S] [--robots N]\n"
      "                         [--seed N] [--batch N]\n"
      "  --smoke         tiny run for CI (fails on errors, never on timings)\n"
      "  --systems       behavior-system processes, default 20\n"
      "  --subscribers   Coordinator.WatchEvents clients, default 10\n"
      "  --behaviors     registered behaviors in all (one fleet each), default 100,1000\n"
      "  --warmup-s      events phase: seconds before the window, default 2\n"
      "  --window-s      events phase: measured seconds, default 15\n"
      "  --activations   activation phase: iterations, default 500\n"
      "  --max-lag       drivers hold back while a subscriber is this many events\n"
      "                  behind, default 1000 (the coordinator cuts a subscriber off\n"
      "                  at 4096)\n"
      "  --paced-events-per-s  then the same at this fixed event rate (for the lag\n"
      "                  below saturation), default 1000; 0 skips it\n"
      "  --paced-window-s      measured seconds of the paced run, default 5\n"
      "  --robots        robots the systems are spread over (round robin), default 1:\n"
      "                  every system serves robot \"bench\"\n"
      "  --batch         events per message the subscribers ask for\n"
      "                  (WatchEvents max_events_per_message), default 64; 1: one\n"
      "                  event per message\n");
}

std::vector<int> parseList(const std::string& text) {
  std::vector<int> out;
  std::stringstream ss(text);
  for (std::string item; std::getline(ss, item, ',');) out.push_back(std::stoi(item));
  return out;
}

bool parseOptions(int argc, char** argv, Options* o) {
  for (int i = 1; i < argc; ++i) {
    std::string arg = argv[i];
    std::string value;
    if (auto eq = arg.find('='); eq != std::string::npos) {
      value = arg.substr(eq + 1);
      arg = arg.substr(0, eq);
    } else if (arg != "--smoke" && i + 1 < argc) {
      value = argv[++i];
    }
    try {
      if (arg == "--smoke") {
        o->smoke = true;
        o->systems = 4;
        o->subscribers = 3;
        o->behaviors = {8, 40};
        o->warmup_s = 0.3;
        o->window_s = 1;
        o->activations = 20;
        o->paced_events_per_s = 200;
        o->paced_window_s = 0.5;
      } else if (arg == "--systems") {
        o->systems = std::stoi(value);
      } else if (arg == "--subscribers") {
        o->subscribers = std::stoi(value);
      } else if (arg == "--behaviors") {
        o->behaviors = parseList(value);
      } else if (arg == "--warmup-s") {
        o->warmup_s = std::stod(value);
      } else if (arg == "--window-s") {
        o->window_s = std::stod(value);
      } else if (arg == "--activations") {
        o->activations = std::stoi(value);
      } else if (arg == "--max-lag") {
        o->max_lag = std::stoi(value);
      } else if (arg == "--paced-events-per-s") {
        o->paced_events_per_s = std::stod(value);
      } else if (arg == "--paced-window-s") {
        o->paced_window_s = std::stod(value);
      } else if (arg == "--robots") {
        o->robots = std::stoi(value);
      } else if (arg == "--batch") {
        o->batch = std::stoi(value);
      } else if (arg == "--seed") {
        o->seed = static_cast<unsigned>(std::stoul(value));
      } else {
        usage();
        return false;
      }
    } catch (const std::exception&) {
      std::fprintf(stderr, "coordinator_bench: bad value '%s' for %s\n", value.c_str(),
                   arg.c_str());
      return false;
    }
  }
  if (o->systems < 1 || o->systems > 100 || o->subscribers < 1 || o->behaviors.empty() ||
      o->warmup_s < 0 || o->window_s <= 0 || o->activations < 2 || o->max_lag < 10 ||
      o->max_lag > 4000 || o->paced_events_per_s < 0 || o->paced_window_s <= 0 || o->robots < 1 ||
      o->robots > o->systems || o->batch < 1 || o->batch > 1024) {
    std::fprintf(stderr,
                 "coordinator_bench: need 1-100 systems, >= 1 subscriber, a behavior count, "
                 "windows > 0, >= 2 activations, max lag in [10, 4000], a paced rate >= 0, "
                 "1 to --systems robots\n");
    return false;
  }
  for (int b : o->behaviors) {
    if (b < o->systems || b > 9999) {
      std::fprintf(stderr,
                   "coordinator_bench: --behaviors %d: each count must be in [--systems (%d), "
                   "9999]\n",
                   b, o->systems);
      return false;
    }
  }
  return true;
}

// ---------------------------------------------------------------------------
// Statistics
// ---------------------------------------------------------------------------

struct Stats {
  size_t n = 0;
  double p50 = 0, p90 = 0, p99 = 0, max = 0;
};

// Nearest-rank percentiles of `ns` divided by `unit` (default: ns -> ms).
Stats summarize(std::vector<int64_t> ns, double unit = 1e6) {
  Stats s;
  s.n = ns.size();
  if (ns.empty()) return s;
  std::sort(ns.begin(), ns.end());
  auto at = [&](double p) {
    size_t rank = static_cast<size_t>(std::ceil(p * static_cast<double>(ns.size())));
    rank = std::clamp<size_t>(rank, 1, ns.size());
    return static_cast<double>(ns[rank - 1]) / unit;
  };
  s.p50 = at(0.50);
  s.p90 = at(0.90);
  s.p99 = at(0.99);
  s.max = static_cast<double>(ns.back()) / unit;
  return s;
}

double median(std::vector<double> v) {
  if (v.empty()) return 0;
  std::sort(v.begin(), v.end());
  const size_t n = v.size();
  return n % 2 == 1 ? v[n / 2] : (v[n / 2 - 1] + v[n / 2]) / 2;
}

// ---------------------------------------------------------------------------
// Child processes
// ---------------------------------------------------------------------------

std::string readFile(const std::string& path) {
  std::ifstream in(path);
  std::stringstream ss;
  ss << in.rdbuf();
  return ss.str();
}

// Process CPU time in ns (all threads); -1 when the process is gone.
int64_t cpuNs(pid_t pid) {
  clockid_t clock;
  if (clock_getcpuclockid(pid, &clock) != 0) return -1;
  timespec ts;
  if (clock_gettime(clock, &ts) != 0) return -1;
  return static_cast<int64_t>(ts.tv_sec) * 1000000000LL + ts.tv_nsec;
}

// VmRSS in MiB.
double rssMiB(pid_t pid) {
  const std::string status = readFile("/proc/" + std::to_string(pid) + "/status");
  const auto pos = status.find("\nVmRSS:");
  if (pos == std::string::npos) return 0;
  return std::strtod(status.c_str() + pos + 7, nullptr) / 1024;
}

/// A server binary started with `--listen 127.0.0.1:0 --metrics-listen
/// 127.0.0.1:0 --port-file <file>` plus `args`; its output goes to `log`. It
/// gets SIGKILL when this process dies, and from the destructor if still
/// running.
class Child {
 public:
  Child(std::string name, std::string binary, std::vector<std::string> args, std::string log)
      : name_(std::move(name)),
        binary_(std::move(binary)),
        args_(std::move(args)),
        log_(std::move(log)),
        port_file_(log_ + ".ports") {}
  ~Child() {
    kill();
    unlink(port_file_.c_str());
  }
  Child(const Child&) = delete;
  Child& operator=(const Child&) = delete;

  /// Forks and execs; does not wait.
  void launch() {
    std::vector<std::string> argv_s = {
        binary_,       "--listen",    "127.0.0.1:0", "--metrics-listen",
        "127.0.0.1:0", "--port-file", port_file_};
    argv_s.insert(argv_s.end(), args_.begin(), args_.end());
    std::vector<char*> argv;
    for (auto& a : argv_s) argv.push_back(a.data());
    argv.push_back(nullptr);
    const pid_t parent = getpid();
    pid_ = fork();
    if (pid_ < 0) throw BenchError("fork failed for " + name_);
    if (pid_ == 0) {
      prctl(PR_SET_PDEATHSIG, SIGKILL);
      if (getppid() != parent) _exit(1);  // the parent died before prctl
      // Only async-signal-safe calls between fork and exec.
      const int fd = open(log_.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
      if (fd >= 0) {
        dup2(fd, STDOUT_FILENO);
        dup2(fd, STDERR_FILENO);
        close(fd);
      }
      execv(argv[0], argv.data());
      static const char kMessage[] = "execv failed\n";
      [[maybe_unused]] const ssize_t n = write(STDERR_FILENO, kMessage, sizeof(kMessage) - 1);
      _exit(127);
    }
  }

  /// Waits until the port file names the gRPC port.
  void awaitPorts(int64_t deadline_ns) {
    while (monotonicNs() < deadline_ns) {
      grpc_port_ = support::readPortFromFile(port_file_, "grpc_port");
      if (grpc_port_ > 0) {
        metrics_port_ = support::readPortFromFile(port_file_, "metrics_port");
        return;
      }
      int status = 0;
      if (waitpid(pid_, &status, WNOHANG) == pid_) {
        pid_ = -1;
        throw BenchError(name_ + " exited before binding its port (log " + log_ + ")");
      }
      std::this_thread::sleep_for(milliseconds(5));
    }
    throw BenchError(name_ + " did not write its port file in time (log " + log_ + ")");
  }

  std::string address() const { return "127.0.0.1:" + std::to_string(grpc_port_); }
  int metricsPort() const { return metrics_port_; }
  pid_t pid() const { return pid_; }
  const std::string& name() const { return name_; }

  void sendTerm() const {
    if (pid_ > 0) ::kill(pid_, SIGTERM);
  }

  /// Waits for the exit; the exit code, 128+signal, or -1 when it had to be
  /// killed after `timeout`.
  int reap(milliseconds timeout) {
    if (pid_ <= 0) return -1;
    const int64_t deadline = monotonicNs() + timeout.count() * 1000000LL;
    while (true) {
      int status = 0;
      const pid_t r = waitpid(pid_, &status, WNOHANG);
      if (r == pid_) {
        pid_ = -1;
        if (WIFEXITED(status)) return WEXITSTATUS(status);
        if (WIFSIGNALED(status)) return 128 + WTERMSIG(status);
        return -1;
      }
      if (r < 0 || monotonicNs() > deadline) {
        kill();
        return -1;
      }
      std::this_thread::sleep_for(milliseconds(5));
    }
  }

  void kill() {
    if (pid_ <= 0) return;
    ::kill(pid_, SIGKILL);
    waitpid(pid_, nullptr, 0);
    pid_ = -1;
  }

 private:
  std::string name_;
  std::string binary_;
  std::vector<std::string> args_;
  std::string log_;
  std::string port_file_;
  pid_t pid_ = -1;
  int grpc_port_ = 0;
  int metrics_port_ = 0;
};

/// A directory for the children's logs; removed unless keep() was called.
class LogDir {
 public:
  LogDir() {
    char tmpl[] = "/tmp/behaviorlib-coordinator-bench-XXXXXX";
    if (mkdtemp(tmpl) == nullptr) throw BenchError("mkdtemp failed");
    path_ = tmpl;
  }
  ~LogDir() {
    if (keep_) return;
    std::error_code ec;
    std::filesystem::remove_all(path_, ec);
  }
  LogDir(const LogDir&) = delete;
  LogDir& operator=(const LogDir&) = delete;
  const std::string& path() const { return path_; }
  void keep() { keep_ = true; }

 private:
  std::string path_;
  bool keep_ = false;
};

// The value of an unlabelled counter or gauge in a Prometheus text body; -1
// when absent.
double scrapeValue(int metrics_port, const std::string& name) {
  const std::string body = support::httpGet(metrics_port, "/metrics");
  std::istringstream in(body);
  for (std::string line; std::getline(in, line);) {
    if (line.rfind(name, 0) != 0) continue;
    const auto rest = line.substr(name.size());
    if (rest.empty() || (rest[0] != ' ' && rest[0] != '{')) continue;
    const auto space = rest.rfind(' ');
    if (space == std::string::npos) continue;
    return std::strtod(rest.c_str() + space + 1, nullptr);
  }
  return -1;
}

// ---------------------------------------------------------------------------
// The fleet: a coordinator and its behavior systems
// ---------------------------------------------------------------------------

struct SystemEntry {
  std::unique_ptr<Child> process;
  std::string robot_id;                // the robot it serves
  std::string system;                  // its system name
  std::vector<std::string> behaviors;  // names it hosts
};

class Fleet {
 public:
  Fleet(const Options& o, int behaviors, LogDir& logs) {
    coordinator_ = std::make_unique<Child>(
        "coordinator", BEHAVIORLIB_COORDINATOR_PATH, std::vector<std::string>{},
        logs.path() + "/coordinator-" + std::to_string(behaviors) + ".log");
    coordinator_->launch();
    coordinator_->awaitPorts(monotonicNs() + 10 * 1000000000LL);
    channel_ = ownChannel(coordinator_->address());
    stub_ = v1::Coordinator::NewStub(channel_);

    int next = 1;
    for (int i = 0; i < o.systems; ++i) {
      const int count = behaviors / o.systems + (i < behaviors % o.systems ? 1 : 0);
      char system[32];
      std::snprintf(system, sizeof(system), "bench_system_%02d", i + 1);
      SystemEntry entry;
      entry.system = system;
      if (o.robots == 1) {
        entry.robot_id = "bench";
      } else {
        char robot[32];
        std::snprintf(robot, sizeof(robot), "bench_%02d", i % o.robots + 1);
        entry.robot_id = robot;
      }
      for (int b = 0; b < count; ++b) {
        char name[32];
        std::snprintf(name, sizeof(name), "BENCH_%04d", next + b);
        entry.behaviors.push_back(name);
      }
      entry.process = std::make_unique<Child>(
          entry.system, BEHAVIORLIB_COORDINATOR_BENCH_SYSTEM_PATH,
          std::vector<std::string>{"--bench-system", entry.system, "--bench-behaviors",
                                   std::to_string(count), "--bench-first", std::to_string(next),
                                   "--robot-id", entry.robot_id, "--clock", "steady",
                                   "--coordinator", coordinator_->address()},
          logs.path() + "/" + entry.system + "-" + std::to_string(behaviors) + ".log");
      next += count;
      systems_.push_back(std::move(entry));
    }
    // Start them all at once: they start up in parallel.
    for (auto& s : systems_) s.process->launch();
    const int64_t deadline = monotonicNs() + 20 * 1000000000LL;
    for (auto& s : systems_) s.process->awaitPorts(deadline);
    awaitAllUp(deadline);
    checkBehaviors(behaviors);
  }

  v1::Coordinator::Stub& coordinator() { return *stub_; }
  const Child& coordinatorProcess() const { return *coordinator_; }
  const std::vector<SystemEntry>& systems() const { return systems_; }

  /// The start message of a new Coordinator.WatchEvents stream: the
  /// coordinator's incarnation and its newest seq.
  v1::WatchEventsStart streamStart() {
    grpc::ClientContext ctx;
    setDeadline(&ctx);
    v1::WatchFleetEventsRequest request;
    request.add_robot_ids("no robot: only the start message");
    auto reader = stub_->WatchEvents(&ctx, request);
    v1::WatchFleetEventsResponse message;
    const bool read = reader->Read(&message);
    ctx.TryCancel();
    const grpc::Status s = reader->Finish();
    if (!read || !message.has_start()) {
      throw BenchError("Coordinator.WatchEvents sent no start message: " + describe(s));
    }
    return message.start();
  }

  /// SIGTERM to every system (they unregister), then to the coordinator;
  /// every one must exit 0.
  void shutdown() {
    for (auto& s : systems_) s.process->sendTerm();
    std::string failed;
    for (auto& s : systems_) {
      if (int code = s.process->reap(seconds(10)); code != 0) {
        failed += " " + s.system + " (exit " + std::to_string(code) + ")";
      }
    }
    coordinator_->sendTerm();
    if (int code = coordinator_->reap(seconds(10)); code != 0) {
      failed += " coordinator (exit " + std::to_string(code) + ")";
    }
    if (!failed.empty()) throw BenchError("did not exit cleanly after SIGTERM:" + failed);
  }

 private:
  // Follows the coordinator's stream (replay from the start) until every
  // system is UP.
  void awaitAllUp(int64_t deadline_ns) {
    grpc::ClientContext ctx;
    ctx.set_deadline(std::chrono::system_clock::now() +
                     std::chrono::nanoseconds(deadline_ns - monotonicNs()));
    v1::WatchFleetEventsRequest request;
    auto reader = stub_->WatchEvents(&ctx, request);
    std::map<std::string, v1::SystemState> state;
    size_t up = 0;
    v1::WatchFleetEventsResponse message;
    while (up < systems_.size() && reader->Read(&message)) {
      if (!message.has_event() || !message.event().has_system_state_changed()) continue;
      const auto& info = message.event().system_state_changed().system();
      state[info.system()] = info.state();
      up = static_cast<size_t>(std::count_if(state.begin(), state.end(), [](const auto& e) {
        return e.second == v1::SYSTEM_STATE_UP;
      }));
    }
    if (up < systems_.size()) {
      ctx.TryCancel();
      const grpc::Status s = reader->Finish();
      throw BenchError("only " + std::to_string(up) + " of " + std::to_string(systems_.size()) +
                       " systems came UP at the coordinator in time (" + describe(s) + ")");
    }
    ctx.TryCancel();
    reader->Finish();
  }

  void checkBehaviors(int expected) {
    grpc::ClientContext ctx;
    setDeadline(&ctx);
    v1::ListFleetBehaviorsRequest request;  // every robot
    v1::ListFleetBehaviorsResponse response;
    const grpc::Status s = stub_->ListBehaviors(&ctx, request, &response);
    if (!s.ok()) throw BenchError("Coordinator.ListBehaviors failed: " + describe(s));
    if (response.behaviors_size() != expected) {
      throw BenchError("the coordinator lists " + std::to_string(response.behaviors_size()) +
                       " behaviors, expected " + std::to_string(expected));
    }
  }

  std::unique_ptr<Child> coordinator_;
  std::shared_ptr<grpc::Channel> channel_;
  std::unique_ptr<v1::Coordinator::Stub> stub_;
  std::vector<SystemEntry> systems_;
};

// ---------------------------------------------------------------------------
// Events phase
// ---------------------------------------------------------------------------

struct EventsResult {
  double window_s = 0;
  double activations_per_s = 0;
  uint64_t busy = 0;                   // activations refused: still active
  double events_in_per_s = 0;          // the coordinator's events_received_total
  std::vector<double> per_subscriber;  // events/s delivered to each
  Stats lag_system;                    // system wall_time -> received (ms)
  Stats lag_coordinator;               // coordinator wall_time -> received (ms)
  Stats lag_events;                    // events behind, sampled every 10 ms (count)
  double held_back_fraction = 0;       // of driver time spent held back by --max-lag
  double coordinator_cpu = 0;          // % of one core
  double systems_cpu = 0;              // all systems together
  double bench_cpu = 0;                // this process (drivers + subscribers)
  double coordinator_rss_mib = 0;
  double systems_rss_mib = 0;
  uint64_t checked_activations = 0;  // delivered exactly once to every subscriber
};

class Subscriber;

// What the drivers and the subscribers share: the drivers hold back while
// the slowest subscriber is more than `max_lag` events behind what they
// produced, and go on once it is back under half of it (woken by the
// subscriber that gets there). Also wakes the main thread while it waits for
// the last events.
struct Progress {
  explicit Progress(int64_t max_lag) : max_lag(max_lag) {}
  const int64_t max_lag;
  std::vector<Subscriber*> subscribers;
  std::atomic<uint64_t> produced{0};  // two events per successful activation
  std::atomic<bool> holding{false};
  std::atomic<bool> draining{false};
  std::atomic<bool> stop{false};
  std::mutex mutex;
  std::condition_variable cv;

  uint64_t minReceived() const;
  int64_t lag() const {
    return static_cast<int64_t>(produced.load(std::memory_order_relaxed)) -
           static_cast<int64_t>(minReceived());
  }
  void wakeAll() {
    { std::lock_guard lock(mutex); }
    cv.notify_all();
  }
  // Subscriber side, after each event.
  void onReceived() {
    if (holding.load(std::memory_order_relaxed) && lag() <= max_lag / 2) {
      {
        std::lock_guard lock(mutex);
        holding.store(false);
      }
      cv.notify_all();
    } else if (draining.load(std::memory_order_relaxed)) {
      wakeAll();
    }
  }
  // Driver side, before each activation; returns how long it was held (ns).
  int64_t holdIfBehind() {
    if (lag() <= max_lag) return 0;
    const int64_t t0 = monotonicNs();
    std::unique_lock lock(mutex);
    holding.store(true);
    // The timeout only guards against a wake-up lost to a subscriber that
    // read `holding` just before it was set.
    while (!stop.load() && lag() > max_lag / 2) {
      holding.store(true);
      cv.wait_for(lock, milliseconds(20));
    }
    return monotonicNs() - t0;
  }
};

// One Coordinator.WatchEvents client (its own connection) on a thread of its
// own.
class Subscriber {
 public:
  Subscriber(const std::string& address, v1::WatchFleetEventsRequest request, Progress& progress)
      : channel_(ownChannel(address)),
        stub_(v1::Coordinator::NewStub(channel_)),
        request_(std::move(request)),
        progress_(progress) {}
  ~Subscriber() { stop(); }
  Subscriber(const Subscriber&) = delete;
  Subscriber& operator=(const Subscriber&) = delete;

  void start() {
    thread_ = std::thread([this] { run(); });
  }
  void stop() {
    ctx_.TryCancel();
    if (thread_.joinable()) thread_.join();
  }

  bool ready() const { return ready_.load(); }
  bool done() const { return done_.load(); }
  uint64_t received() const { return received_.load(std::memory_order_relaxed); }
  uint64_t activated() const { return activated_.load(); }
  uint64_t finished() const { return finished_.load(); }
  void record(bool on) { recording_.store(on); }
  // Valid after stop().
  const std::string& error() const { return error_; }
  const std::vector<int64_t>& lagSystem() const { return lag_system_; }
  const std::vector<int64_t>& lagCoordinator() const { return lag_coordinator_; }

 private:
  void run() {
    // Up to the wait for every subscriber's start (runEvents), then stop()
    // cancels it: a new connection that fails once is tried again.
    ctx_.set_wait_for_ready(true);
    auto reader = stub_->WatchEvents(&ctx_, request_);
    v1::WatchFleetEventsResponse message;
    uint64_t last_seq = 0;
    while (reader->Read(&message)) {
      if (message.has_start()) {
        set(ready_);
        continue;
      }
      if (message.has_event()) {
        onEvent(message.event(), last_seq);
      } else {
        for (const v1::FleetEvent& event : message.events().events()) onEvent(event, last_seq);
      }
    }
    const grpc::Status s = reader->Finish();
    if (s.error_code() != grpc::StatusCode::CANCELLED && error_.empty()) {
      error_ = "WatchEvents ended: " + describe(s);
    }
    set(done_);
  }

  void onEvent(const v1::FleetEvent& event, uint64_t& last_seq) {
    if (last_seq != 0 && event.seq() != last_seq + 1 && error_.empty()) {
      error_ = "coordinator seq jumped from " + std::to_string(last_seq) + " to " +
               std::to_string(event.seq());
    }
    last_seq = event.seq();
    if (!event.has_behavior_event()) return;
    const int64_t now = wallNs();
    const v1::BehaviorEvent& e = event.behavior_event();
    if (e.has_activated()) {
      activated_.fetch_add(1);
    } else if (e.has_finished()) {
      if (e.finished().cause() != v1::TERMINATION_CAUSE_GOAL_ACHIEVED && error_.empty()) {
        error_ = e.behavior() + " finished with cause " +
                 v1::TerminationCause_Name(e.finished().cause()) + ", expected GOAL_ACHIEVED";
      }
      finished_.fetch_add(1);
    }
    if (recording_.load(std::memory_order_relaxed)) {
      lag_system_.push_back(now - toNs(e.wall_time()));
      lag_coordinator_.push_back(now - toNs(event.wall_time()));
    }
    received_.fetch_add(1, std::memory_order_relaxed);
    progress_.onReceived();
  }

  void set(std::atomic<bool>& flag) {
    flag.store(true);
    progress_.wakeAll();
  }

  std::shared_ptr<grpc::Channel> channel_;
  std::unique_ptr<v1::Coordinator::Stub> stub_;
  const v1::WatchFleetEventsRequest request_;
  Progress& progress_;
  grpc::ClientContext ctx_;
  std::thread thread_;
  std::atomic<bool> ready_{false}, done_{false}, recording_{false};
  std::atomic<uint64_t> received_{0}, activated_{0}, finished_{0};
  std::string error_;
  std::vector<int64_t> lag_system_, lag_coordinator_;
};

uint64_t Progress::minReceived() const {
  uint64_t m = UINT64_MAX;
  for (const Subscriber* s : subscribers) m = std::min(m, s->received());
  return m;
}

struct CpuSnapshot {
  int64_t wall = 0, coordinator = 0, systems = 0, bench = 0;
};

CpuSnapshot sampleCpu(Fleet& fleet) {
  CpuSnapshot s;
  s.wall = monotonicNs();
  s.coordinator = cpuNs(fleet.coordinatorProcess().pid());
  for (const auto& sys : fleet.systems()) s.systems += cpuNs(sys.process->pid());
  s.bench = cpuNs(getpid());
  return s;
}

// One thread per system, activating its behaviors round robin, straight at
// the system.
class Drivers {
 public:
  /// `events_per_s` > 0: all drivers together activate at half that rate
  /// (two events an activation), each on a fixed schedule, staggered; 0: as
  /// fast as they can.
  Drivers(Fleet& fleet, Progress& progress, double events_per_s) : progress_(progress) {
    const size_t n = fleet.systems().size();
    const int64_t period =
        events_per_s > 0 ? static_cast<int64_t>(2e9 * static_cast<double>(n) / events_per_s) : 0;
    const int64_t start = monotonicNs();
    for (size_t i = 0; i < n; ++i) {
      const auto& sys = fleet.systems()[i];
      const int64_t first = start + period * static_cast<int64_t>(i) / static_cast<int64_t>(n);
      threads_.emplace_back([this, address = sys.process->address(), names = sys.behaviors, period,
                             first] { run(address, names, period, first); });
    }
  }
  ~Drivers() { stop(); }
  Drivers(const Drivers&) = delete;
  Drivers& operator=(const Drivers&) = delete;

  void stop() {
    progress_.stop.store(true);
    progress_.wakeAll();
    for (auto& t : threads_) t.join();
    threads_.clear();
  }

  uint64_t activations() const { return activations_.load(); }
  uint64_t busy() const { return busy_.load(); }
  uint64_t heldNs() const { return held_ns_.load(); }
  bool failed() const { return failed_.load(); }
  // Valid after stop().
  const std::string& error() const { return error_; }

 private:
  void run(const std::string& address, const std::vector<std::string>& names, int64_t period,
           int64_t next) {
    auto stub = v1::BehaviorSystem::NewStub(ownChannel(address));
    v1::ActivateBehaviorRequest request;
    (*request.mutable_parameters()->mutable_fields())["duration_s"].set_number_value(0);
    for (size_t i = 0; !progress_.stop.load(std::memory_order_relaxed);
         i = (i + 1) % names.size()) {
      if (period > 0) {
        // A late driver skips what it missed rather than bursting.
        const int64_t now = monotonicNs();
        if (next < now) next = now;
        const timespec at{static_cast<time_t>(next / 1000000000LL),
                          static_cast<long>(next % 1000000000LL)};
        clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &at, nullptr);
        next += period;
      }
      if (const int64_t held = progress_.holdIfBehind(); held > 0) {
        held_ns_.fetch_add(static_cast<uint64_t>(held), std::memory_order_relaxed);
        continue;  // re-check stop
      }
      request.set_behavior(names[i]);
      grpc::ClientContext ctx;
      setDeadline(&ctx);
      v1::ActivateResponse response;
      const grpc::Status s = stub->ActivateBehavior(&ctx, request, &response);
      if (s.ok()) {
        // Counted before the events can be counted as received.
        activations_.fetch_add(1, std::memory_order_relaxed);
        progress_.produced.fetch_add(2, std::memory_order_relaxed);
      } else if (s.error_code() == grpc::StatusCode::FAILED_PRECONDITION) {
        busy_.fetch_add(1, std::memory_order_relaxed);  // its last activation still runs
      } else {
        std::lock_guard lock(mutex_);
        if (error_.empty()) {
          error_ = "BehaviorSystem.ActivateBehavior(" + names[i] + ") failed: " + describe(s);
        }
        failed_.store(true);
        progress_.stop.store(true);
      }
    }
  }

  Progress& progress_;
  std::vector<std::thread> threads_;
  std::atomic<uint64_t> activations_{0}, busy_{0}, held_ns_{0};
  std::atomic<bool> failed_{false};
  std::mutex mutex_;
  std::string error_;
};

// `events_per_s` 0: as fast as the drivers can.
EventsResult runEvents(const Options& o, Fleet& fleet, double events_per_s, double warmup_s,
                       double window_s) {
  Progress progress(o.max_lag);
  // Only what happens from now on (no replay of an earlier phase's events).
  const v1::WatchEventsStart now = fleet.streamStart();
  v1::WatchFleetEventsRequest request;
  request.set_since_seq(now.latest_seq());
  request.set_incarnation(now.incarnation());
  request.set_max_events_per_message(static_cast<uint32_t>(o.batch));
  std::vector<std::unique_ptr<Subscriber>> subscribers;
  for (int i = 0; i < o.subscribers; ++i) {
    subscribers.push_back(
        std::make_unique<Subscriber>(fleet.coordinatorProcess().address(), request, progress));
    progress.subscribers.push_back(subscribers.back().get());
  }
  for (auto& s : subscribers) s->start();
  {
    std::unique_lock lock(progress.mutex);
    progress.cv.wait_for(lock, kCallDeadline, [&] {
      return std::all_of(subscribers.begin(), subscribers.end(),
                         [](const auto& s) { return s->ready() || s->done(); });
    });
  }
  for (size_t i = 0; i < subscribers.size(); ++i) {
    if (!subscribers[i]->ready() || subscribers[i]->received() != 0) {
      for (auto& s : subscribers) s->stop();
      throw BenchError("WatchEvents subscriber " + std::to_string(i + 1) +
                       (subscribers[i]->ready() ? " received behavior events before the drivers "
                                                  "started"
                                                : " did not start: " + subscribers[i]->error()));
    }
  }

  EventsResult result;
  std::vector<int64_t> lag_events;
  Drivers drivers(fleet, progress, events_per_s);
  sleepS(warmup_s);
  for (auto& s : subscribers) s->record(true);
  const CpuSnapshot cpu_a = sampleCpu(fleet);
  const uint64_t act_a = drivers.activations();
  const uint64_t held_a = drivers.heldNs();
  const double in_a = scrapeValue(fleet.coordinatorProcess().metricsPort(),
                                  "behaviorlib_coordinator_events_received_total");
  std::vector<uint64_t> recv_a;
  for (const auto& s : subscribers) recv_a.push_back(s->received());
  // The lag in events, sampled every 10 ms: this thread's only work during
  // the window.
  const int64_t end = cpu_a.wall + static_cast<int64_t>(window_s * 1e9);
  while (monotonicNs() < end && !drivers.failed()) {
    std::this_thread::sleep_for(milliseconds(10));
    const int64_t produced = static_cast<int64_t>(progress.produced.load());
    for (const auto& s : subscribers) {
      lag_events.push_back(std::max<int64_t>(0, produced - static_cast<int64_t>(s->received())));
    }
  }
  const CpuSnapshot cpu_b = sampleCpu(fleet);
  for (auto& s : subscribers) s->record(false);
  const uint64_t act_b = drivers.activations();
  const uint64_t held_b = drivers.heldNs();
  const double in_b = scrapeValue(fleet.coordinatorProcess().metricsPort(),
                                  "behaviorlib_coordinator_events_received_total");
  std::vector<uint64_t> recv_b;
  for (const auto& s : subscribers) recv_b.push_back(s->received());
  result.coordinator_rss_mib = rssMiB(fleet.coordinatorProcess().pid());
  for (const auto& sys : fleet.systems()) result.systems_rss_mib += rssMiB(sys.process->pid());
  drivers.stop();
  if (!drivers.error().empty()) throw BenchError(drivers.error());
  result.busy = drivers.busy();

  const double wall = static_cast<double>(cpu_b.wall - cpu_a.wall);
  result.window_s = wall / 1e9;
  for (size_t i = 0; i < subscribers.size(); ++i) {
    result.per_subscriber.push_back(static_cast<double>(recv_b[i] - recv_a[i]) / result.window_s);
  }
  result.activations_per_s = static_cast<double>(act_b - act_a) / result.window_s;
  result.events_in_per_s = in_a < 0 || in_b < 0 ? -1 : (in_b - in_a) / result.window_s;
  result.held_back_fraction =
      static_cast<double>(held_b - held_a) / (wall * static_cast<double>(o.systems));
  result.coordinator_cpu =
      100.0 * static_cast<double>(cpu_b.coordinator - cpu_a.coordinator) / wall;
  result.systems_cpu = 100.0 * static_cast<double>(cpu_b.systems - cpu_a.systems) / wall;
  result.bench_cpu = 100.0 * static_cast<double>(cpu_b.bench - cpu_a.bench) / wall;

  // Every activation's two events reach every subscriber, exactly once.
  const uint64_t expected = drivers.activations();
  progress.draining.store(true);
  {
    std::unique_lock lock(progress.mutex);
    progress.cv.wait_for(lock, seconds(10), [&] {
      return std::all_of(subscribers.begin(), subscribers.end(),
                         [&](const auto& s) { return s->done() || s->received() >= 2 * expected; });
    });
  }
  for (auto& s : subscribers) s->stop();
  for (size_t i = 0; i < subscribers.size(); ++i) {
    const auto& s = *subscribers[i];
    const std::string who = "subscriber " + std::to_string(i + 1);
    if (!s.error().empty()) throw BenchError(who + ": " + s.error());
    if (s.activated() != expected || s.finished() != expected) {
      throw BenchError(who + " received " + std::to_string(s.activated()) + " activated and " +
                       std::to_string(s.finished()) + " finished events for " +
                       std::to_string(expected) + " activations (each should arrive once)");
    }
  }
  result.checked_activations = expected;
  std::vector<int64_t> system_lag, coordinator_lag;
  for (const auto& s : subscribers) {
    system_lag.insert(system_lag.end(), s->lagSystem().begin(), s->lagSystem().end());
    coordinator_lag.insert(coordinator_lag.end(), s->lagCoordinator().begin(),
                           s->lagCoordinator().end());
  }
  result.lag_system = summarize(std::move(system_lag));
  result.lag_coordinator = summarize(std::move(coordinator_lag));
  result.lag_events = summarize(std::move(lag_events), 1);
  return result;
}

// ---------------------------------------------------------------------------
// Activation phase
// ---------------------------------------------------------------------------

struct ActivationResult {
  Stats coordinator_activate, direct_activate;
  Stats coordinator_deactivate, direct_deactivate;
  Stats floor;  // direct CheckBehaviorActivation
};

class LatencyClient {
 public:
  explicit LatencyClient(Fleet& fleet) : fleet_(fleet) {
    for (const auto& sys : fleet.systems()) {
      direct_.push_back(v1::BehaviorSystem::NewStub(ownChannel(sys.process->address())));
    }
  }

  // Through the coordinator; returns the activation id.
  std::string coordinatorActivate(size_t system, const std::string& behavior, int64_t* ns) {
    v1::ActivateFleetBehaviorRequest request;
    request.set_robot_id(fleet_.systems()[system].robot_id);
    request.set_behavior(behavior);
    (*request.mutable_parameters()->mutable_fields())["duration_s"].set_number_value(kNeverS);
    v1::ActivateFleetBehaviorResponse response;
    grpc::ClientContext ctx;
    setDeadline(&ctx);
    const int64_t t0 = monotonicNs();
    const grpc::Status s = fleet_.coordinator().ActivateBehavior(&ctx, request, &response);
    *ns = monotonicNs() - t0;
    if (!s.ok()) {
      throw BenchError("Coordinator.ActivateBehavior(" + behavior + ") failed: " + describe(s));
    }
    if (response.system() != fleet_.systems()[system].system ||
        response.activation().activation_id().empty()) {
      throw BenchError("Coordinator.ActivateBehavior(" + behavior + ") answered system '" +
                       response.system() + "' and activation '" +
                       response.activation().activation_id() + "'");
    }
    return response.activation().activation_id();
  }

  void coordinatorDeactivate(size_t system, const std::string& behavior, const std::string& id,
                             int64_t* ns) {
    v1::DeactivateFleetBehaviorRequest request;
    request.set_robot_id(fleet_.systems()[system].robot_id);
    request.set_behavior(behavior);
    request.set_activation_id(id);
    v1::DeactivateFleetBehaviorResponse response;
    grpc::ClientContext ctx;
    setDeadline(&ctx);
    const int64_t t0 = monotonicNs();
    const grpc::Status s = fleet_.coordinator().DeactivateBehavior(&ctx, request, &response);
    *ns = monotonicNs() - t0;
    if (!s.ok()) {
      throw BenchError("Coordinator.DeactivateBehavior(" + behavior + ") failed: " + describe(s));
    }
    checkInterrupted(behavior, response.result());
  }

  std::string directActivate(size_t system, const std::string& behavior, int64_t* ns) {
    v1::ActivateBehaviorRequest request;
    request.set_behavior(behavior);
    (*request.mutable_parameters()->mutable_fields())["duration_s"].set_number_value(kNeverS);
    v1::ActivateResponse response;
    grpc::ClientContext ctx;
    setDeadline(&ctx);
    const int64_t t0 = monotonicNs();
    const grpc::Status s = direct_[system]->ActivateBehavior(&ctx, request, &response);
    *ns = monotonicNs() - t0;
    if (!s.ok()) {
      throw BenchError("BehaviorSystem.ActivateBehavior(" + behavior + ") failed: " + describe(s));
    }
    if (response.activation_id().empty()) throw BenchError("Activate returned no activation_id");
    return response.activation_id();
  }

  void directDeactivate(size_t system, const std::string& behavior, const std::string& id,
                        int64_t* ns) {
    v1::DeactivateBehaviorRequest request;
    request.set_behavior(behavior);
    request.set_activation_id(id);
    v1::DeactivateResponse response;
    grpc::ClientContext ctx;
    setDeadline(&ctx);
    const int64_t t0 = monotonicNs();
    const grpc::Status s = direct_[system]->DeactivateBehavior(&ctx, request, &response);
    *ns = monotonicNs() - t0;
    if (!s.ok()) {
      throw BenchError("BehaviorSystem.DeactivateBehavior(" + behavior +
                       ") failed: " + describe(s));
    }
    checkInterrupted(behavior, response);
  }

  int64_t floor(size_t system, const std::string& behavior) {
    v1::CheckBehaviorActivationRequest request;
    request.set_behavior(behavior);
    v1::CheckActivationResponse response;
    grpc::ClientContext ctx;
    setDeadline(&ctx);
    const int64_t t0 = monotonicNs();
    const grpc::Status s = direct_[system]->CheckBehaviorActivation(&ctx, request, &response);
    const int64_t ns = monotonicNs() - t0;
    if (!s.ok()) throw BenchError("CheckBehaviorActivation failed: " + describe(s));
    return ns;
  }

 private:
  static void checkInterrupted(const std::string& behavior, const v1::DeactivateResponse& r) {
    if (r.already_finished() || r.cause() != v1::TERMINATION_CAUSE_INTERRUPTED) {
      throw BenchError("deactivating " + behavior + ": the activation had already finished");
    }
  }

  Fleet& fleet_;
  std::vector<std::unique_ptr<v1::BehaviorSystem::Stub>> direct_;
};

ActivationResult runActivations(const Options& o, Fleet& fleet, std::mt19937& rng) {
  LatencyClient client(fleet);
  std::uniform_real_distribution<double> gap_ms(0.1, 1.0);
  std::bernoulli_distribution coordinator_first(0.5);
  auto gap = [&] { sleepS(gap_ms(rng) / 1000); };
  std::vector<int64_t> ca, cd, da, dd, fl;
  const size_t systems = fleet.systems().size();
  for (int i = 0; i < o.activations; ++i) {
    const size_t sys = static_cast<size_t>(i) % systems;
    const auto& names = fleet.systems()[sys].behaviors;
    const std::string& behavior = names[(static_cast<size_t>(i) / systems) % names.size()];
    int64_t a = 0, d = 0;
    auto viaCoordinator = [&] {
      const std::string id = client.coordinatorActivate(sys, behavior, &a);
      gap();
      client.coordinatorDeactivate(sys, behavior, id, &d);
      if (i > 0) {
        ca.push_back(a);
        cd.push_back(d);
      }
      gap();
    };
    auto direct = [&] {
      const std::string id = client.directActivate(sys, behavior, &a);
      gap();
      client.directDeactivate(sys, behavior, id, &d);
      if (i > 0) {
        da.push_back(a);
        dd.push_back(d);
      }
      gap();
    };
    if (coordinator_first(rng)) {
      viaCoordinator();
      direct();
    } else {
      direct();
      viaCoordinator();
    }
    const int64_t f = client.floor(sys, behavior);
    if (i > 0) fl.push_back(f);
    gap();
  }
  ActivationResult r;
  r.coordinator_activate = summarize(std::move(ca));
  r.coordinator_deactivate = summarize(std::move(cd));
  r.direct_activate = summarize(std::move(da));
  r.direct_deactivate = summarize(std::move(dd));
  r.floor = summarize(std::move(fl));
  return r;
}

// ---------------------------------------------------------------------------
// Report
// ---------------------------------------------------------------------------

std::string cpuModel() {
  std::istringstream in(readFile("/proc/cpuinfo"));
  for (std::string line; std::getline(in, line);) {
    if (line.rfind("model name", 0) == 0) {
      const auto colon = line.find(':');
      if (colon != std::string::npos) return line.substr(colon + 2);
    }
  }
  return "unknown";
}

// What `nproc` prints: the CPUs this process may run on.
int cpuCount() {
  cpu_set_t set;
  CPU_ZERO(&set);
  if (sched_getaffinity(0, sizeof(set), &set) != 0) return -1;
  return CPU_COUNT(&set);
}

std::string loadAverage() {
  std::istringstream in(readFile("/proc/loadavg"));
  std::string a, b, c;
  in >> a >> b >> c;
  return a + " " + b + " " + c;
}

std::string fmt(const char* format, double v) {
  char buf[64];
  std::snprintf(buf, sizeof(buf), format, v);
  return buf;
}

struct FleetResult {
  int behaviors = 0;
  double idle_window_s = 0;
  double idle_coordinator_cpu = 0;  // % of one core, everything registered, no traffic
  double idle_systems_cpu = 0;
  EventsResult events;  // as fast as possible
  bool has_paced = false;
  EventsResult paced;  // at --paced-events-per-s
  ActivationResult activation;
};

void printReport(const Options& o, const std::vector<FleetResult>& results,
                 const std::string& load_start) {
  std::printf("## Coordinator: %d systems (%d robot%s), %d subscribers\n\n", o.systems, o.robots,
              o.robots == 1 ? "" : "s", o.subscribers);
  std::printf("Machine: %d CPUs (nproc), %s; load average %s at the start, %s at the end.%s\n\n",
              cpuCount(), cpuModel().c_str(), load_start.c_str(), loadAverage().c_str(),
              o.smoke ? " Smoke run: figures are not meaningful." : "");

  struct Column {
    std::string label;
    const EventsResult* events;
  };
  std::vector<Column> columns;
  for (const auto& r : results) {
    columns.push_back({std::to_string(r.behaviors) + " behaviors, max rate", &r.events});
    if (r.has_paced) {
      columns.push_back({std::to_string(r.behaviors) + " behaviors, paced " +
                             fmt("%.0f", o.paced_events_per_s) + " events/s",
                         &r.paced});
    }
  }
  std::printf("### Events through the coordinator (max rate: %g s window after %g s warm-up",
              o.window_s, o.warmup_s);
  if (o.paced_events_per_s > 0) {
    std::printf("; paced: %g s window after %g s", o.paced_window_s, std::min(1.0, o.warmup_s));
  }
  std::printf(")\n\n");
  std::printf("| figure |");
  for (const auto& c : columns) std::printf(" %s |", c.label.c_str());
  std::printf("\n|---|");
  for (size_t i = 0; i < columns.size(); ++i) std::printf("---:|");
  std::printf("\n");
  auto row = [&](const char* name, auto value) {
    std::printf("| %s |", name);
    for (const auto& c : columns) std::printf(" %s |", value(*c.events).c_str());
    std::printf("\n");
  };
  row("activations/s driven (direct to the systems)",
      [](const EventsResult& e) { return fmt("%.0f", e.activations_per_s); });
  row("events/s into the coordinator (its events_received counter)",
      [](const EventsResult& e) { return fmt("%.0f", e.events_in_per_s); });
  row("events/s delivered to each subscriber: median / min", [](const EventsResult& e) {
    const auto& v = e.per_subscriber;
    return fmt("%.0f", median(v)) + " / " + fmt("%.0f", *std::min_element(v.begin(), v.end()));
  });
  row("events/s delivered to all subscribers together", [](const EventsResult& e) {
    double sum = 0;
    for (double v : e.per_subscriber) sum += v;
    return fmt("%.0f", sum);
  });
  row("lag, system emits → subscriber receives (ms): p50 / p99 / max", [](const EventsResult& e) {
    const Stats& s = e.lag_system;
    return fmt("%.3f", s.p50) + " / " + fmt("%.3f", s.p99) + " / " + fmt("%.1f", s.max);
  });
  row("lag, coordinator accepts → subscriber receives (ms): p50 / p99", [](const EventsResult& e) {
    const Stats& s = e.lag_coordinator;
    return fmt("%.3f", s.p50) + " / " + fmt("%.3f", s.p99);
  });
  row("lag in events (sampled every 10 ms, each subscriber): p50 / p99 / max",
      [](const EventsResult& e) {
        const Stats& s = e.lag_events;
        return fmt("%.0f", s.p50) + " / " + fmt("%.0f", s.p99) + " / " + fmt("%.0f", s.max);
      });
  row("drivers held back by --max-lag (share of their time)",
      [](const EventsResult& e) { return fmt("%.0f %%", 100 * e.held_back_fraction); });
  row("activations refused as still active",
      [](const EventsResult& e) { return std::to_string(e.busy); });
  row("CPU, % of one core: coordinator / all systems / bench clients", [](const EventsResult& e) {
    return fmt("%.0f", e.coordinator_cpu) + " / " + fmt("%.0f", e.systems_cpu) + " / " +
           fmt("%.0f", e.bench_cpu);
  });
  row("coordinator CPU per event in, with its deliveries, idle cost included (µs)",
      [](const EventsResult& e) {
        return e.events_in_per_s > 0 ? fmt("%.1f", e.coordinator_cpu * 1e4 / e.events_in_per_s)
                                     : std::string("—");
      });
  row("VmRSS (MiB): coordinator / all systems", [](const EventsResult& e) {
    return fmt("%.1f", e.coordinator_rss_mib) + " / " + fmt("%.1f", e.systems_rss_mib);
  });
  row("activations checked: both events exactly once at every subscriber",
      [](const EventsResult& e) { return std::to_string(e.checked_activations); });
  std::printf("\nIdle, everything registered and no traffic:");
  for (const auto& r : results) {
    std::printf(" %d behaviors: coordinator %.2f %%, all systems %.2f %% of one core (%g s);",
                r.behaviors, r.idle_coordinator_cpu, r.idle_systems_cpu, r.idle_window_s);
  }
  std::printf("\n");

  std::printf("\n### Activation latency, request → reply (ms; %d iterations, first dropped)\n\n",
              o.activations);
  std::printf(
      "| call | behaviors | n | p50 | p90 | p99 | max |\n|---|---:|---:|---:|---:|---:|---:|\n");
  for (const auto& r : results) {
    auto line = [&](const char* name, const Stats& s) {
      std::printf("| %s | %d | %zu | %.3f | %.3f | %.3f | %.3f |\n", name, r.behaviors, s.n, s.p50,
                  s.p90, s.p99, s.max);
    };
    const ActivationResult& a = r.activation;
    line("Coordinator.ActivateBehavior", a.coordinator_activate);
    line("BehaviorSystem.ActivateBehavior (direct)", a.direct_activate);
    line("Coordinator.DeactivateBehavior", a.coordinator_deactivate);
    line("BehaviorSystem.DeactivateBehavior (direct)", a.direct_deactivate);
    line("floor: BehaviorSystem.CheckBehaviorActivation (direct)", a.floor);
  }
  std::printf(
      "\n| coordinator's overhead on ActivateBehavior (ms) | p50 | p99 |\n|---|---:|---:|\n");
  for (const auto& r : results) {
    const ActivationResult& a = r.activation;
    std::printf("| %d behaviors | %+.3f | %+.3f |\n", r.behaviors,
                a.coordinator_activate.p50 - a.direct_activate.p50,
                a.coordinator_activate.p99 - a.direct_activate.p99);
  }
}

int run(const Options& o) {
  LogDir logs;
  const std::string load_start = loadAverage();
  std::mt19937 rng(o.seed);
  std::vector<FleetResult> results;
  try {
    for (int behaviors : o.behaviors) {
      std::fprintf(stderr, "coordinator_bench: %d behaviors on %d systems: starting\n", behaviors,
                   o.systems);
      Fleet fleet(o, behaviors, logs);
      FleetResult r;
      r.behaviors = behaviors;
      r.idle_window_s = o.smoke ? 0.3 : 2;
      const CpuSnapshot idle_a = sampleCpu(fleet);
      sleepS(r.idle_window_s);
      const CpuSnapshot idle_b = sampleCpu(fleet);
      const double idle_wall = static_cast<double>(idle_b.wall - idle_a.wall);
      r.idle_coordinator_cpu =
          100.0 * static_cast<double>(idle_b.coordinator - idle_a.coordinator) / idle_wall;
      r.idle_systems_cpu = 100.0 * static_cast<double>(idle_b.systems - idle_a.systems) / idle_wall;
      std::fprintf(stderr, "coordinator_bench: events at max rate, %d subscribers, %g s window\n",
                   o.subscribers, o.window_s);
      r.events = runEvents(o, fleet, 0, o.warmup_s, o.window_s);
      if (o.paced_events_per_s > 0) {
        std::fprintf(stderr, "coordinator_bench: events at %g/s, %g s window\n",
                     o.paced_events_per_s, o.paced_window_s);
        r.paced =
            runEvents(o, fleet, o.paced_events_per_s, std::min(1.0, o.warmup_s), o.paced_window_s);
        r.has_paced = true;
      }
      std::fprintf(stderr, "coordinator_bench: %d activations each way\n", o.activations);
      r.activation = runActivations(o, fleet, rng);
      fleet.shutdown();
      results.push_back(std::move(r));
    }
  } catch (...) {
    logs.keep();
    std::fprintf(stderr, "coordinator_bench: logs of the processes kept in %s\n",
                 logs.path().c_str());
    throw;
  }
  printReport(o, results, load_start);
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
  } catch (const std::exception& e) {
    std::fprintf(stderr, "coordinator_bench: FAILED: %s\n", e.what());
    return 1;
  }
}
