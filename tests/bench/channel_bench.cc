// channel_bench: what one same-host channel delivery costs in CPU, summed
// over every process (issue 14 goal 2; docs/benchmarks.md).
//
//   channel_bench [--rate-hz 1000] [--subscribers 10] [--window-s 10] [--runs 3]
//                 [--modes pace,floor,stream,ring] [--topics 1] [--smoke]
//
// Each run starts a real channel_broker, one publisher process and N
// subscriber processes (forked before any gRPC object exists), and publishes
// behaviorlib.v1.Imu samples at the given rate. Every process measures its own
// CPU (getrusage) over the window; the broker's comes from /proc/<pid>/stat.
// Modes:
//   stream  every subscriber gets its samples on its own gRPC stream
//   ring    subscribers read the broker's shared-memory ring (decision 20)
//   floor   no broker and no gRPC: the publisher writes the serialized
//           samples into a ShmRing itself, the readers parse them; what the
//           ring costs at best, measured in the same run
//   pace    the publisher's loop alone (it wakes at the rate and publishes
//           nothing): the part of every mode's publisher figure that is not
//           delivery
// With --topics K (stream and ring modes), the publisher publishes one sample
// on each of K topics per period, in one batch (ChannelClient::publishAll, as
// the simulator does with what it has ready), and every subscriber process
// subscribes to all K.
// Prints a markdown table: medians over the runs, and each run's total.

#include <signal.h>
#include <sys/resource.h>
#include <sys/wait.h>
#include <time.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <mutex>
#include <sstream>
#include <stdexcept>
#include <string>
#include <thread>
#include <vector>

#include "behaviorlib/channel/channel_client.h"
#include "behaviorlib/channel/shm_ring.h"
#include "behaviorlib/v1/channel.pb.h"
#include "behaviorlib/v1/types.pb.h"
#include "support/server_process.h"

namespace {

using behaviorlib::channel::ShmRing;
namespace v1 = behaviorlib::v1;

const char* const kBrokerPath = BEHAVIORLIB_CHANNEL_BROKER_PATH;
constexpr char kTopic[] = "robots/bench/imu";

std::string topicName(int k) { return k == 0 ? kTopic : std::string(kTopic) + std::to_string(k); }

struct Options {
  double rate_hz = 1000;
  int subscribers = 10;
  double window_s = 10;
  int runs = 3;
  int topics = 1;
  std::vector<std::string> modes = {"pace", "floor", "stream", "ring"};
};

int64_t monotonicNs() {
  timespec t{};
  clock_gettime(CLOCK_MONOTONIC, &t);
  return static_cast<int64_t>(t.tv_sec) * 1'000'000'000 + t.tv_nsec;
}

double cpuUs() {
  rusage r{};
  getrusage(RUSAGE_SELF, &r);
  return (r.ru_utime.tv_sec + r.ru_stime.tv_sec) * 1e6 + r.ru_utime.tv_usec + r.ru_stime.tv_usec;
}

// utime + stime of another process, in µs.
double procCpuUs(pid_t pid) {
  std::ifstream in("/proc/" + std::to_string(pid) + "/stat");
  std::string stat((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  const auto close = stat.rfind(')');
  if (close == std::string::npos) throw std::runtime_error("cannot read /proc/<pid>/stat");
  std::istringstream fields(stat.substr(close + 2));
  std::string field;
  double ticks = 0;
  for (int i = 3; i <= 15 && fields >> field; ++i) {
    if (i == 14 || i == 15) ticks += std::stod(field);
  }
  return ticks * 1e6 / static_cast<double>(sysconf(_SC_CLK_TCK));
}

v1::Imu sample(uint64_t seq) {
  v1::Imu imu;
  const int64_t now = monotonicNs();
  imu.mutable_header()->mutable_stamp()->set_seconds(now / 1'000'000'000);
  imu.mutable_header()->mutable_stamp()->set_nanos(static_cast<int32_t>(now % 1'000'000'000));
  imu.mutable_header()->set_frame_id("bench/imu");
  imu.mutable_orientation()->set_w(1.0);
  imu.mutable_angular_velocity_rad_s()->set_x(0.01 * static_cast<double>(seq % 7));
  imu.mutable_linear_acceleration_m_s2()->set_z(9.81);
  return imu;
}

// One line a child writes to its pipe when done.
struct Report {
  double cpu_us = 0;
  uint64_t count = 0;
  uint64_t dropped = 0;
  double p50_ms = 0;
  double p99_ms = 0;
};

void writeReport(int fd, const Report& r) {
  char line[256];
  const int n = std::snprintf(line, sizeof line, "%.1f %llu %llu %.4f %.4f\n", r.cpu_us,
                              static_cast<unsigned long long>(r.count),
                              static_cast<unsigned long long>(r.dropped), r.p50_ms, r.p99_ms);
  if (write(fd, line, static_cast<size_t>(n)) != n) _exit(3);
}

Report readReport(int fd) {
  std::string text;
  char buf[256];
  ssize_t n = 0;
  while ((n = read(fd, buf, sizeof buf)) > 0) text.append(buf, static_cast<size_t>(n));
  Report r;
  unsigned long long count = 0;
  unsigned long long dropped = 0;
  if (std::sscanf(text.c_str(), "%lf %llu %llu %lf %lf", &r.cpu_us, &count, &dropped, &r.p50_ms,
                  &r.p99_ms) != 5) {
    throw std::runtime_error("a child reported nothing (it failed)");
  }
  r.count = count;
  r.dropped = dropped;
  return r;
}

double percentile(std::vector<double> v, double q) {
  if (v.empty()) return 0;
  std::sort(v.begin(), v.end());
  return v[std::min(v.size() - 1, static_cast<size_t>(q * static_cast<double>(v.size())))];
}

// A child: `body` gets the write end of its report pipe and the read end of
// the start pipe. Returns the child's pid and the parent's pipe ends.
struct Child {
  pid_t pid = -1;
  int report_fd = -1;
};

template <class F>
Child forkChild(int go_fd, F body) {
  int report[2];
  if (pipe(report) != 0) throw std::runtime_error("pipe failed");
  const pid_t pid = fork();
  if (pid < 0) throw std::runtime_error("fork failed");
  if (pid == 0) {
    close(report[0]);
    body(report[1], go_fd);
    _exit(0);
  }
  close(report[1]);
  return {pid, report[0]};
}

// Blocks until the parent closes the start pipe.
void awaitGo(int go_fd) {
  char c;
  while (read(go_fd, &c, 1) > 0) {
  }
}

void pace(int64_t start_ns, uint64_t i, int64_t period_ns) {
  const int64_t at = start_ns + static_cast<int64_t>(i) * period_ns;
  timespec t{static_cast<time_t>(at / 1'000'000'000), static_cast<long>(at % 1'000'000'000)};
  clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &t, nullptr);
}

struct RunResult {
  double publisher_us = 0;
  double broker_us = 0;
  double subscribers_us = 0;
  uint64_t published = 0;
  uint64_t delivered = 0;
  uint64_t dropped = 0;
  double p50_ms = 0;
  double p99_ms = 0;
  double totalPerDelivery() const {
    return delivered == 0 ? 0 : (publisher_us + broker_us + subscribers_us) / delivered;
  }
};

// A subscriber in a child process: reads `total` samples or until the
// deadline, measuring its CPU and each sample's latency from its stamp.
void subscriberChild(const std::string& address, bool ring, int topics, uint64_t total,
                     double deadline_s, int report_fd, int ready_fd) {
  behaviorlib::channel::ChannelClient client(address);
  std::vector<double> latency;
  latency.reserve(total);
  std::mutex mutex;  // the subscriptions' threads share `latency`
  std::atomic<uint64_t> received{0};
  std::vector<std::atomic<uint64_t>> dropped(static_cast<size_t>(topics));
  std::vector<std::unique_ptr<behaviorlib::channel::Subscription>> subs;
  for (int k = 0; k < topics; ++k) {
    subs.push_back(client.subscribe(
        topicName(k), {.mode = v1::DELIVERY_MODE_QUEUE, .queue_size = 1000, .shared_memory = ring},
        [&, k](const v1::SubscribeResponse& response) {
          v1::Imu imu;
          if (!response.sample().UnpackTo(&imu) || imu.header().frame_id() == "bench/warmup")
            return;
          const int64_t stamp =
              imu.header().stamp().seconds() * 1'000'000'000LL + imu.header().stamp().nanos();
          {
            std::lock_guard lock(mutex);
            latency.push_back(static_cast<double>(monotonicNs() - stamp) / 1e6);
          }
          dropped[static_cast<size_t>(k)].store(response.dropped_count());
          received.fetch_add(1);
        }));
  }
  const auto dropped_sum = [&] {
    uint64_t sum = 0;
    for (const auto& d : dropped) sum += d.load();
    return sum;
  };
  for (const auto& sub : subs) {
    if (!sub->waitConnected(std::chrono::seconds(10))) _exit(4);
  }
  const double cpu0 = cpuUs();
  if (write(ready_fd, "r", 1) != 1) _exit(5);
  const int64_t deadline = monotonicNs() + static_cast<int64_t>(deadline_s * 1e9);
  const uint64_t expected = total * static_cast<uint64_t>(topics);
  while (received.load() + dropped_sum() < expected && monotonicNs() < deadline) {
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  const double cpu = cpuUs() - cpu0;
  subs.clear();
  writeReport(report_fd, {cpu, received.load(), dropped_sum(), percentile(latency, 0.5),
                          percentile(latency, 0.99)});
}

void floorReaderChild(const std::string& ring_name, uint64_t total, double deadline_s,
                      int report_fd, int ready_fd) {
  auto ring = ShmRing::open(ring_name);
  if (!ring.ok()) _exit(6);
  std::vector<double> latency;
  latency.reserve(total);
  const double cpu0 = cpuUs();
  if (write(ready_fd, "r", 1) != 1) _exit(5);
  uint64_t next = 1;
  uint64_t dropped = 0;
  uint64_t received = 0;
  std::string bytes;
  v1::SubscribeResponse response;
  const int64_t deadline = monotonicNs() + static_cast<int64_t>(deadline_s * 1e9);
  while (received + dropped < total && monotonicNs() < deadline) {
    const uint32_t token = (*ring)->notifyToken();
    if ((*ring)->read(&next, false, &bytes, &dropped) == ShmRing::Read::kSample) {
      v1::Imu imu;
      if (!response.ParseFromString(bytes) || !response.sample().UnpackTo(&imu)) _exit(7);
      const int64_t stamp =
          imu.header().stamp().seconds() * 1'000'000'000LL + imu.header().stamp().nanos();
      latency.push_back(static_cast<double>(monotonicNs() - stamp) / 1e6);
      ++received;
    } else {
      (*ring)->wait(token, 100'000'000);
    }
  }
  writeReport(report_fd, {cpuUs() - cpu0, received, dropped, percentile(latency, 0.5),
                          percentile(latency, 0.99)});
}

RunResult runOnce(const Options& o, const std::string& mode) {
  const auto total = static_cast<uint64_t>(o.window_s * o.rate_hz);
  const auto period_ns = static_cast<int64_t>(1e9 / o.rate_hz);
  const double deadline_s = o.window_s * 3 + 10;
  // Several topics only through the broker (the floor writes one ring).
  const int topics = mode == "stream" || mode == "ring" ? o.topics : 1;
  support::ServerProcess broker(kBrokerPath, {});
  std::unique_ptr<ShmRing> floor_ring;
  const int subscriber_count = mode == "pace" ? 0 : o.subscribers;
  if (mode == "pace") {
  } else if (mode == "floor") {
    auto made = ShmRing::create(ShmRing::nameFor(getpid(), 1), 1024, 512);
    if (!made.ok()) throw std::runtime_error(made.status().ToString());
    floor_ring = std::move(*made);
  } else if (!broker.start()) {
    throw std::runtime_error("channel_broker: " + broker.error());
  }
  int go[2];
  int ready[2];
  if (pipe(go) != 0 || pipe(ready) != 0) throw std::runtime_error("pipe failed");
  std::vector<Child> subscribers;
  for (int i = 0; i < subscriber_count; ++i) {
    subscribers.push_back(forkChild(go[0], [&](int report_fd, int) {
      close(go[1]);
      close(ready[0]);
      if (mode == "floor") {
        floorReaderChild(floor_ring->name(), total, deadline_s, report_fd, ready[1]);
      } else {
        subscriberChild(broker.address(), mode == "ring", topics, total, deadline_s, report_fd,
                        ready[1]);
      }
    }));
  }
  for (int i = 0; i < subscriber_count; ++i) {
    char c;
    if (read(ready[0], &c, 1) != 1) throw std::runtime_error("a subscriber did not connect");
  }
  Child publisher = forkChild(go[0], [&](int report_fd, int go_fd) {
    close(go[1]);
    std::unique_ptr<behaviorlib::channel::ChannelClient> client;
    if (mode == "stream" || mode == "ring") {
      client = std::make_unique<behaviorlib::channel::ChannelClient>(broker.address());
      // Opens the stream and fixes the topic's type before the window.
      v1::Imu warmup = sample(0);
      warmup.mutable_header()->set_frame_id("bench/warmup");
      for (int k = 0; k < topics; ++k) {
        if (!client->publish(topicName(k), warmup).ok()) _exit(8);
      }
      if (!client->sync().ok()) _exit(8);
    }
    awaitGo(go_fd);
    const double cpu0 = cpuUs();
    const int64_t start = monotonicNs();
    std::string bytes;
    for (uint64_t i = 1; i <= total; ++i) {
      pace(start, i, period_ns);
      if (client && topics == 1) {
        if (!client->publish(kTopic, sample(i)).ok()) _exit(9);
      } else if (client) {
        std::vector<v1::Imu> imus(static_cast<size_t>(topics), sample(i));
        std::vector<behaviorlib::channel::ChannelClient::TopicSample> batch;
        for (int k = 0; k < topics; ++k)
          batch.push_back({topicName(k), &imus[static_cast<size_t>(k)]});
        if (!client->publishAll(batch).ok()) _exit(9);
      } else if (floor_ring) {
        v1::SubscribeResponse response;
        response.set_topic(kTopic);
        response.set_topic_seq(i);
        response.mutable_sample()->PackFrom(sample(i));
        bytes.clear();
        response.AppendToString(&bytes);
        floor_ring->write(i, bytes);
      }
    }
    if (client && !client->sync().ok()) _exit(10);
    writeReport(report_fd, {cpuUs() - cpu0, total * static_cast<uint64_t>(topics), 0, 0, 0});
  });
  const bool with_broker = mode == "stream" || mode == "ring";
  const double broker0 = with_broker ? procCpuUs(broker.pid()) : 0;
  close(go[1]);
  close(go[0]);
  RunResult result;
  const Report pub = readReport(publisher.report_fd);
  result.publisher_us = pub.cpu_us;
  result.published = pub.count;
  std::vector<double> p50s;
  std::vector<double> p99s;
  for (const Child& child : subscribers) {
    const Report r = readReport(child.report_fd);
    result.subscribers_us += r.cpu_us;
    result.delivered += r.count;
    result.dropped += r.dropped;
    p50s.push_back(r.p50_ms);
    p99s.push_back(r.p99_ms);
  }
  if (with_broker) result.broker_us = procCpuUs(broker.pid()) - broker0;
  for (const Child& child : subscribers) waitpid(child.pid, nullptr, 0);
  waitpid(publisher.pid, nullptr, 0);
  close(ready[0]);
  close(ready[1]);
  if (floor_ring) floor_ring->unlink();
  result.p50_ms = percentile(p50s, 0.5);
  result.p99_ms = p99s.empty() ? 0 : *std::max_element(p99s.begin(), p99s.end());
  return result;
}

double median(std::vector<double> v) { return percentile(std::move(v), 0.5); }

}  // namespace

int main(int argc, char** argv) {
  Options o;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    auto value = [&]() -> std::string {
      if (i + 1 >= argc) {
        std::fprintf(stderr, "channel_bench: %s needs a value\n", a.c_str());
        std::exit(2);
      }
      return argv[++i];
    };
    if (a == "--rate-hz") {
      o.rate_hz = std::stod(value());
    } else if (a == "--subscribers") {
      o.subscribers = std::stoi(value());
    } else if (a == "--window-s") {
      o.window_s = std::stod(value());
    } else if (a == "--runs") {
      o.runs = std::stoi(value());
    } else if (a == "--modes") {
      o.modes.clear();
      std::stringstream list(value());
      for (std::string m; std::getline(list, m, ',');) o.modes.push_back(m);
    } else if (a == "--topics") {
      o.topics = std::stoi(value());
    } else if (a == "--smoke") {
      o.rate_hz = 200;
      o.subscribers = 2;
      o.window_s = 1;
      o.runs = 1;
    } else {
      std::fprintf(stderr,
                   "usage: channel_bench [--rate-hz 1000] [--subscribers 10] [--window-s 10] "
                   "[--runs 3] [--modes pace,floor,stream,ring] [--topics 1] [--smoke]\n");
      return 2;
    }
  }
  if (o.rate_hz <= 0 || o.rate_hz > 100000 || o.subscribers < 1 || o.subscribers > 64 ||
      o.window_s <= 0 || o.window_s > 600 || o.runs < 1 || o.runs > 20 || o.topics < 1 ||
      o.topics > 32) {
    std::fprintf(stderr, "channel_bench: an option is out of range\n");
    return 2;
  }
  for (const auto& m : o.modes) {
    if (m != "pace" && m != "floor" && m != "stream" && m != "ring") {
      std::fprintf(stderr, "channel_bench: unknown mode '%s'\n", m.c_str());
      return 2;
    }
  }
  std::printf(
      "## channel_bench: 1 publisher at %.0f Hz on %d topic(s) -> %d subscriber processes, "
      "window %.0f s, %d run(s)\n\n",
      o.rate_hz, o.topics, o.subscribers, o.window_s, o.runs);
  std::printf(
      "| mode | delivered / expected | dropped | publisher µs / sample | broker µs / sample | "
      "a subscriber µs / delivery | **total µs / delivery** (each run) | latency p50 / "
      "max p99 (ms) |\n|---|---|---|---|---|---|---|---|\n");
  int failures = 0;
  for (const auto& mode : o.modes) {
    std::vector<RunResult> runs;
    try {
      for (int r = 0; r < o.runs; ++r) runs.push_back(runOnce(o, mode));
    } catch (const std::exception& e) {
      std::fprintf(stderr, "channel_bench: %s: %s\n", mode.c_str(), e.what());
      ++failures;
      continue;
    }
    std::vector<double> pub;
    std::vector<double> brk;
    std::vector<double> sub;
    std::vector<double> total;
    std::vector<double> p50;
    std::vector<double> p99;
    std::string each;
    uint64_t delivered = 0;
    uint64_t dropped = 0;
    for (const auto& r : runs) {
      pub.push_back(r.publisher_us / static_cast<double>(r.published));
      brk.push_back(r.broker_us / static_cast<double>(r.published));
      sub.push_back(r.subscribers_us / std::max<double>(1, static_cast<double>(r.delivered)));
      total.push_back(r.totalPerDelivery());
      p50.push_back(r.p50_ms);
      p99.push_back(r.p99_ms);
      char buf[32];
      std::snprintf(buf, sizeof buf, "%s%.2f", each.empty() ? "" : ", ", r.totalPerDelivery());
      each += buf;
      delivered += r.delivered;
      dropped += r.dropped;
      if (r.delivered == 0 && mode != "pace") ++failures;
    }
    if (mode == "pace") {
      std::printf("| pace | - | - | %.2f | - | - | - | - |\n", median(pub));
      continue;
    }
    const uint64_t expected =
        static_cast<uint64_t>(o.window_s * o.rate_hz) * static_cast<uint64_t>(o.subscribers) *
        static_cast<uint64_t>(mode == "floor" ? 1 : o.topics) * static_cast<uint64_t>(o.runs);
    std::printf("| %s | %llu / %llu | %llu | %.2f | %.2f | %.2f | **%.2f** (%s) | %.3f / %.3f |\n",
                mode.c_str(), static_cast<unsigned long long>(delivered),
                static_cast<unsigned long long>(expected), static_cast<unsigned long long>(dropped),
                median(pub), median(brk), median(sub), median(total), each.c_str(), median(p50),
                median(p99));
    std::fflush(stdout);
  }
  std::printf(
      "\nCPU per process over the window: getrusage in the publisher and subscribers, "
      "/proc/<pid>/stat for the broker. total = (publisher + broker + every subscriber) / "
      "samples delivered; medians over the runs.\n");
  return failures == 0 ? 0 : 1;
}
