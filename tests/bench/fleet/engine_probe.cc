// engine_probe: one end of a pose stream between two hosts, carried by one of
// three engines, for engine_bench.py.
//
//   engine_probe --engine nats --role pub|sub --url nats://ADDR:4222
//                [--nats-send-asap false|true]
//   engine_probe --engine dds  --role pub|sub [--dds-qos reliable|best-effort]
//   engine_probe --engine grpc --role pub|sub --channel ADDR:PORT
//   common: [--rate-hz 200] [--seconds 10] [--topic robots/drone1/pose]
//           [--timeout-s S] [--settle-ms 500]
//
// The publisher sends rate-hz * seconds behaviorlib.v1.PoseStamped samples,
// numbered 1..N in header.seq, each stamped with CLOCK_REALTIME just before it
// is handed to the engine (every network namespace of a machine shares that
// clock, so the subscriber's receive time minus the stamp is the one-way
// latency). The engines:
//   nats  the serialized google.protobuf.Any (as the data channel wraps a
//         sample) on subject robots.drone1.pose of a NATS server; the client
//         buffers a publication for its flusher thread unless
//         --nats-send-asap true (natsOptions_SetSendAsap) writes it at once;
//   dds   the same bytes in a behaviorlib_bench::EngineSample
//         (engine_probe.idl) on a Cyclone DDS topic; the domain and the
//         network come from CYCLONEDDS_URI;
//   grpc  the data channel itself: ChannelClient::publish to a channel_broker,
//         and a QUEUE subscription on its stream (no shared-memory ring).
// The subscriber prints `ready` once its subscription is in place, then one
// JSON line when it has every sample, when SIGTERM/SIGINT arrives or after
// timeout-s: samples received and lost, latency median/p99/max in ms, and its
// CPU seconds (getrusage, all threads) between the first and the last sample.
// The publisher waits until its engine is connected (dds: until it matches a
// reader, then settle-ms), prints `sending`, sends, and prints one JSON line
// with its CPU seconds over the sending loop.
// Exit status: 0 done, 1 an engine error, 2 a usage error.

#include "engine_probe_idl/engine_probe.h"  // idlc, from engine_probe.idl

#include <signal.h>
#include <sys/resource.h>
#include <time.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <memory>
#include <mutex>
#include <stdexcept>
#include <string>
#include <thread>
#include <unordered_set>
#include <vector>

#include "behaviorlib/channel/channel_client.h"
#include "behaviorlib/v1/channel.pb.h"
#include "behaviorlib/v1/types.pb.h"
#include "dds/dds.h"
#include "google/protobuf/any.pb.h"
#include "nats/nats.h"

namespace {

namespace v1 = behaviorlib::v1;

struct Options {
  std::string engine;
  std::string role;
  std::string url;
  std::string channel;
  std::string topic = "robots/drone1/pose";
  std::string dds_qos = "best-effort";
  bool nats_send_asap = false;
  double rate_hz = 200;
  double seconds = 10;
  double timeout_s = -1;  // seconds + 30 unless given
  int settle_ms = 500;
};

std::atomic<bool> g_stop{false};

void onSignal(int) { g_stop.store(true); }

int64_t realtimeNs() {
  timespec t{};
  clock_gettime(CLOCK_REALTIME, &t);
  return static_cast<int64_t>(t.tv_sec) * 1'000'000'000 + t.tv_nsec;
}

double cpuSeconds() {
  rusage r{};
  getrusage(RUSAGE_SELF, &r);
  return static_cast<double>(r.ru_utime.tv_sec + r.ru_stime.tv_sec) +
         static_cast<double>(r.ru_utime.tv_usec + r.ru_stime.tv_usec) / 1e6;
}

uint64_t expectedCount(const Options& o) {
  return static_cast<uint64_t>(std::llround(o.rate_hz * o.seconds));
}

// A pose like a vehicle's ground truth: every field set, so the sample has
// its real size (proto3 leaves zeros out).
v1::PoseStamped makePose(uint64_t seq) {
  v1::PoseStamped p;
  auto* h = p.mutable_header();
  h->set_frame_id("world");
  h->set_seq(seq);
  h->set_robot_id("drone1");
  auto* pos = p.mutable_pose()->mutable_position_m();
  pos->set_x(12.5 + 0.001 * static_cast<double>(seq));
  pos->set_y(-3.25 + 0.002 * static_cast<double>(seq));
  pos->set_z(10.125);
  auto* q = p.mutable_pose()->mutable_orientation();
  q->set_w(0.9238795325);
  q->set_x(0.0012);
  q->set_y(-0.0021);
  q->set_z(0.3826834324);
  return p;
}

void stampNow(v1::PoseStamped* p) {
  const int64_t now = realtimeNs();
  auto* stamp = p->mutable_header()->mutable_stamp();
  stamp->set_seconds(now / 1'000'000'000);
  stamp->set_nanos(static_cast<int32_t>(now % 1'000'000'000));
}

std::string packAny(const v1::PoseStamped& p) {
  google::protobuf::Any any;
  any.PackFrom(p);
  return any.SerializeAsString();
}

// What the subscriber saw; the engines' callbacks may run on any thread.
class Receiver {
 public:
  explicit Receiver(uint64_t expected) : expected_(expected) { latencies_ms_.reserve(expected); }

  void onPose(const v1::PoseStamped& p) {
    const int64_t now = realtimeNs();
    const double cpu = cpuSeconds();
    const auto& s = p.header().stamp();
    const int64_t sent = s.seconds() * 1'000'000'000 + s.nanos();
    std::lock_guard<std::mutex> lock(mu_);
    if (!seqs_.insert(p.header().seq()).second) {
      ++duplicates_;
      return;
    }
    latencies_ms_.push_back(static_cast<double>(now - sent) / 1e6);
    if (latencies_ms_.size() == 1) {
      first_cpu_ = cpu;
      first_ns_ = now;
    }
    last_cpu_ = cpu;
    last_ns_ = now;
    if (seqs_.size() >= expected_) complete_.store(true);
  }

  void onAnyBytes(const void* data, size_t size) {
    google::protobuf::Any any;
    v1::PoseStamped p;
    if (!any.ParseFromArray(data, static_cast<int>(size)) || !any.UnpackTo(&p)) {
      std::lock_guard<std::mutex> lock(mu_);
      ++malformed_;
      return;
    }
    onPose(p);
  }

  bool complete() const { return complete_.load(); }

  void printJson(const Options& o, const std::string& error) {
    std::lock_guard<std::mutex> lock(mu_);
    std::vector<double> v = latencies_ms_;
    std::sort(v.begin(), v.end());
    auto quantile = [&v](double q) {
      if (v.empty()) return 0.0;
      const size_t rank = static_cast<size_t>(std::ceil(q * static_cast<double>(v.size())));
      return v[std::min(v.size() - 1, rank == 0 ? 0 : rank - 1)];
    };
    const uint64_t received = seqs_.size();
    std::printf(
        "{\"engine\": \"%s\", \"role\": \"sub\", \"expected\": %llu, \"received\": %llu, "
        "\"lost\": %llu, \"duplicates\": %llu, \"malformed\": %llu, "
        "\"latency_ms\": {\"median\": %.3f, \"p99\": %.3f, \"max\": %.3f}, "
        "\"cpu_s\": %.4f, \"window_s\": %.3f, \"error\": \"%s\"}\n",
        o.engine.c_str(), static_cast<unsigned long long>(expected_),
        static_cast<unsigned long long>(received),
        static_cast<unsigned long long>(expected_ > received ? expected_ - received : 0),
        static_cast<unsigned long long>(duplicates_), static_cast<unsigned long long>(malformed_),
        quantile(0.5), quantile(0.99), v.empty() ? 0.0 : v.back(), last_cpu_ - first_cpu_,
        static_cast<double>(last_ns_ - first_ns_) / 1e9, error.c_str());
    std::fflush(stdout);
  }

 private:
  const uint64_t expected_;
  std::mutex mu_;
  std::unordered_set<uint64_t> seqs_;
  std::vector<double> latencies_ms_;
  uint64_t duplicates_ = 0;
  uint64_t malformed_ = 0;
  double first_cpu_ = 0, last_cpu_ = 0;
  int64_t first_ns_ = 0, last_ns_ = 0;
  std::atomic<bool> complete_{false};
};

void printReady() {
  std::printf("ready\n");
  std::fflush(stdout);
}

// Waits until every sample arrived, a signal, or the timeout.
void waitReceiving(const Options& o, const Receiver& receiver) {
  const auto deadline = std::chrono::steady_clock::now() +
                        std::chrono::milliseconds(static_cast<int64_t>(o.timeout_s * 1000));
  while (!g_stop.load() && !receiver.complete() && std::chrono::steady_clock::now() < deadline) {
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
}

// Calls send(seq) for seq 1..N at the rate, on an absolute schedule; prints
// the publisher's line. send returns false on an engine error.
template <class Send>
int runPublisher(const Options& o, Send send) {
  const uint64_t n = expectedCount(o);
  const auto period = std::chrono::nanoseconds(static_cast<int64_t>(1e9 / o.rate_hz));
  uint64_t sent = 0, errors = 0;
  std::printf("sending\n");
  std::fflush(stdout);
  const double cpu0 = cpuSeconds();
  const auto start = std::chrono::steady_clock::now();
  auto next = start;
  for (uint64_t seq = 1; seq <= n && !g_stop.load(); ++seq) {
    std::this_thread::sleep_until(next);
    next += period;
    if (send(seq)) {
      ++sent;
    } else {
      ++errors;
    }
  }
  const double wall =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  const double cpu = cpuSeconds() - cpu0;
  std::printf(
      "{\"engine\": \"%s\", \"role\": \"pub\", \"sent\": %llu, \"errors\": %llu, "
      "\"cpu_s\": %.4f, \"window_s\": %.3f, \"cpu_total_s\": %.4f}\n",
      o.engine.c_str(), static_cast<unsigned long long>(sent),
      static_cast<unsigned long long>(errors), cpu, wall, cpuSeconds());
  std::fflush(stdout);
  return errors == 0 ? 0 : 1;
}

// ---- NATS ----

std::string natsSubject(std::string topic) {
  std::replace(topic.begin(), topic.end(), '/', '.');
  return topic;
}

void onNatsMessage(natsConnection*, natsSubscription*, natsMsg* msg, void* closure) {
  static_cast<Receiver*>(closure)->onAnyBytes(natsMsg_GetData(msg),
                                              static_cast<size_t>(natsMsg_GetDataLength(msg)));
  natsMsg_Destroy(msg);
}

int runNats(const Options& o) {
  natsOptions* opts = nullptr;
  natsConnection* conn = nullptr;
  natsSubscription* sub = nullptr;
  int rc = 1;
  natsStatus s = natsOptions_Create(&opts);
  if (s == NATS_OK) s = natsOptions_SetURL(opts, o.url.c_str());
  if (s == NATS_OK) s = natsOptions_SetTimeout(opts, 5000);
  if (s == NATS_OK) s = natsOptions_SetSendAsap(opts, o.nats_send_asap);
  if (s == NATS_OK) s = natsConnection_Connect(&conn, opts);
  if (s != NATS_OK) {
    std::fprintf(stderr, "engine_probe: NATS connect to %s: %s\n", o.url.c_str(),
                 natsStatus_GetText(s));
  } else if (o.role == "sub") {
    Receiver receiver(expectedCount(o));
    s = natsConnection_Subscribe(&sub, conn, natsSubject(o.topic).c_str(), onNatsMessage,
                                 &receiver);
    if (s == NATS_OK) s = natsSubscription_SetPendingLimits(sub, 1'000'000, 1 << 30);
    if (s == NATS_OK) s = natsConnection_FlushTimeout(conn, 5000);  // the server has the SUB
    if (s == NATS_OK) {
      printReady();
      waitReceiving(o, receiver);
      natsSubscription_Unsubscribe(sub);
      natsSubscription_Destroy(sub);  // no callback runs after this
      sub = nullptr;
      receiver.printJson(o, "");
      rc = 0;
    } else {
      std::fprintf(stderr, "engine_probe: NATS subscribe: %s\n", natsStatus_GetText(s));
      if (sub != nullptr) natsSubscription_Destroy(sub);
    }
  } else {
    const std::string subject = natsSubject(o.topic);
    rc = runPublisher(o, [&](uint64_t seq) {
      v1::PoseStamped p = makePose(seq);
      stampNow(&p);
      const std::string bytes = packAny(p);
      return natsConnection_Publish(conn, subject.c_str(), bytes.data(),
                                    static_cast<int>(bytes.size())) == NATS_OK;
    });
    if (natsConnection_FlushTimeout(conn, 10000) != NATS_OK) rc = 1;
  }
  if (conn != nullptr) natsConnection_Destroy(conn);
  natsOptions_Destroy(opts);
  nats_Close();
  return rc;
}

// ---- Cyclone DDS ----

std::string ddsTopicName(std::string topic) {
  std::replace(topic.begin(), topic.end(), '/', '_');
  return topic;
}

void onDdsData(dds_entity_t reader, void* arg) {
  auto* receiver = static_cast<Receiver*>(arg);
  constexpr int kBatch = 32;
  for (;;) {
    void* samples[kBatch] = {};
    dds_sample_info_t infos[kBatch];
    const dds_return_t n = dds_take(reader, samples, infos, kBatch, kBatch);
    if (n <= 0) return;
    for (dds_return_t i = 0; i < n; ++i) {
      if (!infos[i].valid_data) continue;
      const auto* s = static_cast<const behaviorlib_bench_EngineSample*>(samples[i]);
      receiver->onAnyBytes(s->payload._buffer, s->payload._length);
    }
    dds_return_loan(reader, samples, n);
  }
}

int runDds(const Options& o) {
  const dds_entity_t participant = dds_create_participant(DDS_DOMAIN_DEFAULT, nullptr, nullptr);
  if (participant < 0) {
    std::fprintf(stderr, "engine_probe: dds_create_participant: %s\n", dds_strretcode(participant));
    return 1;
  }
  dds_qos_t* qos = dds_create_qos();
  if (o.dds_qos == "reliable") {
    dds_qset_reliability(qos, DDS_RELIABILITY_RELIABLE, DDS_SECS(1));
  } else {
    dds_qset_reliability(qos, DDS_RELIABILITY_BEST_EFFORT, 0);
  }
  dds_qset_history(qos, DDS_HISTORY_KEEP_LAST, 100);
  int rc = 1;
  const dds_entity_t topic = dds_create_topic(participant, &behaviorlib_bench_EngineSample_desc,
                                              ddsTopicName(o.topic).c_str(), qos, nullptr);
  if (topic < 0) {
    std::fprintf(stderr, "engine_probe: dds_create_topic: %s\n", dds_strretcode(topic));
  } else if (o.role == "sub") {
    Receiver receiver(expectedCount(o));
    dds_listener_t* listener = dds_create_listener(&receiver);
    dds_lset_data_available(listener, onDdsData);
    const dds_entity_t reader = dds_create_reader(participant, topic, qos, listener);
    dds_delete_listener(listener);
    if (reader < 0) {
      std::fprintf(stderr, "engine_probe: dds_create_reader: %s\n", dds_strretcode(reader));
    } else {
      printReady();
      waitReceiving(o, receiver);
      dds_delete(reader);  // no listener runs after this
      receiver.printJson(o, "");
      rc = 0;
    }
  } else {
    const dds_entity_t writer = dds_create_writer(participant, topic, qos, nullptr);
    if (writer < 0) {
      std::fprintf(stderr, "engine_probe: dds_create_writer: %s\n", dds_strretcode(writer));
    } else {
      // Discovery: wait for the subscriber's reader, then let it learn of us.
      const auto deadline = std::chrono::steady_clock::now() +
                            std::chrono::milliseconds(static_cast<int64_t>(o.timeout_s * 1000));
      dds_publication_matched_status_t matched{};
      while (!g_stop.load() && std::chrono::steady_clock::now() < deadline) {
        if (dds_get_publication_matched_status(writer, &matched) == DDS_RETCODE_OK &&
            matched.current_count > 0) {
          break;
        }
        std::this_thread::sleep_for(std::chrono::milliseconds(10));
      }
      if (matched.current_count == 0) {
        std::fprintf(stderr, "engine_probe: no DDS reader matched within %.0f s\n", o.timeout_s);
      } else {
        std::this_thread::sleep_for(std::chrono::milliseconds(o.settle_ms));
        rc = runPublisher(o, [&](uint64_t seq) {
          v1::PoseStamped p = makePose(seq);
          stampNow(&p);
          std::string bytes = packAny(p);
          behaviorlib_bench_EngineSample sample{};
          sample.payload._buffer = reinterpret_cast<uint8_t*>(bytes.data());
          sample.payload._length = static_cast<uint32_t>(bytes.size());
          sample.payload._maximum = static_cast<uint32_t>(bytes.size());
          sample.payload._release = false;
          return dds_write(writer, &sample) == DDS_RETCODE_OK;
        });
        if (o.dds_qos == "reliable") {
          dds_wait_for_acks(writer, DDS_SECS(10));
        } else {
          // Best effort: the last datagrams left on the write; give the
          // reader a moment before the participant says goodbye.
          std::this_thread::sleep_for(std::chrono::milliseconds(200));
        }
      }
    }
  }
  dds_delete_qos(qos);
  dds_delete(participant);
  return rc;
}

// ---- the data channel (gRPC) ----

int runGrpc(const Options& o) {
  behaviorlib::channel::ChannelClient channel(o.channel);
  if (o.role == "sub") {
    Receiver receiver(expectedCount(o));
    behaviorlib::channel::SubscribeOptions options;
    options.mode = v1::DELIVERY_MODE_QUEUE;
    options.queue_size = 10000;
    options.shared_memory = false;
    auto sub = channel.subscribeTyped<v1::PoseStamped>(
        o.topic, options, [&receiver](const v1::PoseStamped& p) { receiver.onPose(p); });
    if (!sub->waitConnected(std::chrono::milliseconds(static_cast<int64_t>(o.timeout_s * 1000)))) {
      std::fprintf(stderr, "engine_probe: no subscription at %s: %s\n", o.channel.c_str(),
                   sub->status().ToString().c_str());
      return 1;
    }
    printReady();
    waitReceiving(o, receiver);
    sub.reset();  // joins the reader thread
    receiver.printJson(o, "");
    return 0;
  }
  // One round trip first, so the connection is up before the first sample.
  auto topics =
      channel.listTopics("", std::chrono::milliseconds(static_cast<int64_t>(o.timeout_s * 1000)));
  if (!topics.ok()) {
    std::fprintf(stderr, "engine_probe: channel %s: %s\n", o.channel.c_str(),
                 topics.status().ToString().c_str());
    return 1;
  }
  int rc = runPublisher(o, [&](uint64_t seq) {
    v1::PoseStamped p = makePose(seq);
    stampNow(&p);
    return channel.publish(o.topic, p).ok();
  });
  auto accepted = channel.flush();
  if (!accepted.ok()) {
    std::fprintf(stderr, "engine_probe: publish stream: %s\n",
                 accepted.status().ToString().c_str());
    rc = 1;
  }
  return rc;
}

int usage() {
  std::fprintf(stderr,
               "usage: engine_probe --engine nats|dds|grpc --role pub|sub [--url nats://A:P] "
               "[--nats-send-asap false|true] [--channel A:P] [--dds-qos best-effort|reliable] "
               "[--rate-hz 200] [--seconds 10] "
               "[--topic robots/drone1/pose] [--timeout-s S] [--settle-ms 500]\n");
  return 2;
}

}  // namespace

int main(int argc, char** argv) {
  Options o;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    if (a == "--help") return usage();
    if (i + 1 >= argc) {
      std::fprintf(stderr, "engine_probe: %s needs a value\n", a.c_str());
      return usage();
    }
    const std::string value = argv[++i];
    try {
      if (a == "--engine") {
        o.engine = value;
      } else if (a == "--role") {
        o.role = value;
      } else if (a == "--url") {
        o.url = value;
      } else if (a == "--channel") {
        o.channel = value;
      } else if (a == "--topic") {
        o.topic = value;
      } else if (a == "--dds-qos") {
        o.dds_qos = value;
      } else if (a == "--rate-hz") {
        o.rate_hz = std::stod(value);
      } else if (a == "--seconds") {
        o.seconds = std::stod(value);
      } else if (a == "--timeout-s") {
        o.timeout_s = std::stod(value);
      } else if (a == "--nats-send-asap") {
        if (value != "true" && value != "false") throw std::invalid_argument(value);
        o.nats_send_asap = value == "true";
      } else if (a == "--settle-ms") {
        o.settle_ms = std::stoi(value);
      } else {
        std::fprintf(stderr, "engine_probe: unknown option %s\n", a.c_str());
        return usage();
      }
    } catch (const std::exception&) {
      std::fprintf(stderr, "engine_probe: bad value for %s: %s\n", a.c_str(), value.c_str());
      return 2;
    }
  }
  if (o.timeout_s < 0) o.timeout_s = o.seconds + 30;
  const bool engine_ok = (o.engine == "nats" && !o.url.empty()) || o.engine == "dds" ||
                         (o.engine == "grpc" && !o.channel.empty());
  if (!engine_ok || (o.role != "pub" && o.role != "sub") ||
      (o.dds_qos != "best-effort" && o.dds_qos != "reliable") || !(o.rate_hz > 0) ||
      o.rate_hz > 100000 || !(o.seconds > 0) || o.seconds > 3600 || o.timeout_s <= 0 ||
      o.settle_ms < 0) {
    return usage();
  }
  struct sigaction sa {};
  sa.sa_handler = onSignal;
  sigaction(SIGTERM, &sa, nullptr);
  sigaction(SIGINT, &sa, nullptr);
  if (o.engine == "nats") return runNats(o);
  if (o.engine == "dds") return runDds(o);
  return runGrpc(o);
}
