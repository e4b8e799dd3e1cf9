// The metrics every server exposes (server_metrics.h): gRPC calls counted
// and timed by a real server on loopback (with a fake clock), the process
// metrics of this process, and the build info.

#include "behaviorlib/server_kit/server_metrics.h"

#include <grpcpp/generic/generic_stub.h>
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>
#include <prometheus/metric_family.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <ctime>
#include <map>
#include <mutex>
#include <thread>
#include <vector>

#include "behaviorlib/v1/coordinator.grpc.pb.h"

namespace behaviorlib::server_kit {
namespace {

namespace v1 = behaviorlib::v1;
using Labels = std::map<std::string, std::string>;

// Two methods to call: a unary one that knows one mission, and a stream
// that sends one update and lasts until its client cancels it.
class Missions final : public v1::Coordinator::Service {
 public:
  grpc::Status GetMission(grpc::ServerContext*, const v1::GetMissionRequest* request,
                          v1::GetMissionResponse*) override {
    if (request->mission_id() == "known") return grpc::Status::OK;
    return {grpc::StatusCode::NOT_FOUND, "no mission " + request->mission_id()};
  }
  grpc::Status WatchMission(grpc::ServerContext* context, const v1::WatchMissionRequest*,
                            grpc::ServerWriter<v1::WatchMissionResponse>* writer) override {
    writer->Write(v1::WatchMissionResponse());
    while (!context->IsCancelled()) std::this_thread::sleep_for(std::chrono::milliseconds(1));
    return grpc::Status::CANCELLED;
  }
};

// The sample of `name` whose labels include `labels`; nullptr if none.
const prometheus::ClientMetric* find(const std::vector<prometheus::MetricFamily>& families,
                                     const std::string& name, const Labels& labels) {
  for (const auto& family : families) {
    if (family.name != name) continue;
    for (const auto& metric : family.metric) {
      size_t matched = 0;
      for (const auto& label : metric.label) {
        auto it = labels.find(label.name);
        if (it != labels.end() && it->second == label.value) ++matched;
      }
      if (matched == labels.size()) return &metric;
    }
  }
  return nullptr;
}

double counter(const std::vector<prometheus::MetricFamily>& families, const std::string& name,
               const Labels& labels) {
  const prometheus::ClientMetric* metric = find(families, name, labels);
  return metric == nullptr ? -1 : metric->counter.value;
}

TEST(GrpcCodeName, SpellsTheSpecificationsNames) {
  EXPECT_EQ(grpcCodeName(grpc::StatusCode::OK), "OK");
  EXPECT_EQ(grpcCodeName(grpc::StatusCode::NOT_FOUND), "NOT_FOUND");
  EXPECT_EQ(grpcCodeName(grpc::StatusCode::UNAUTHENTICATED), "UNAUTHENTICATED");
  EXPECT_EQ(grpcCodeName(static_cast<grpc::StatusCode>(42)), "CODE_42");
}

class ServerMetricsTest : public ::testing::Test {
 protected:
  void SetUp() override {
    grpc::ServerBuilder builder;
    builder.RegisterService(&service_);
    int port = 0;
    builder.AddListeningPort("127.0.0.1:0", grpc::InsecureServerCredentials(), &port);
    std::vector<std::unique_ptr<grpc::experimental::ServerInterceptorFactoryInterface>> creators;
    // Every reading of the clock is 2 ms after the one before.
    creators.push_back(makeServerMetricsInterceptor(registry_, [this] {
      return std::chrono::steady_clock::time_point(std::chrono::milliseconds(2 * ticks_++));
    }));
    builder.experimental().SetInterceptorCreators(std::move(creators));
    server_ = builder.BuildAndStart();
    ASSERT_NE(server_, nullptr);
    ASSERT_GT(port, 0);
    channel_ = grpc::CreateChannel("127.0.0.1:" + std::to_string(port),
                                   grpc::InsecureChannelCredentials());
    stub_ = v1::Coordinator::NewStub(channel_);
  }
  void TearDown() override {
    if (server_) server_->Shutdown(std::chrono::system_clock::now() + std::chrono::seconds(2));
  }

  grpc::Status get(const std::string& mission_id) {
    grpc::ClientContext context;
    v1::GetMissionRequest request;
    request.set_mission_id(mission_id);
    v1::GetMissionResponse response;
    return stub_->GetMission(&context, request, &response);
  }

  Missions service_;
  prometheus::Registry registry_;
  std::atomic<int64_t> ticks_{0};
  std::unique_ptr<grpc::Server> server_;
  std::shared_ptr<grpc::Channel> channel_;
  std::unique_ptr<v1::Coordinator::Stub> stub_;
};

TEST_F(ServerMetricsTest, CountsAndTimesUnaryCallsByCode) {
  ASSERT_TRUE(get("known").ok());
  ASSERT_EQ(get("unknown").error_code(), grpc::StatusCode::NOT_FOUND);
  ASSERT_TRUE(get("known").ok());

  const auto families = registry_.Collect();
  const Labels method = {{"grpc_type", "unary"},
                         {"grpc_service", "behaviorlib.v1.Coordinator"},
                         {"grpc_method", "GetMission"}};
  EXPECT_EQ(counter(families, "grpc_server_started_total", method), 3);
  Labels ok = method, not_found = method;
  ok["grpc_code"] = "OK";
  not_found["grpc_code"] = "NOT_FOUND";
  EXPECT_EQ(counter(families, "grpc_server_handled_total", ok), 2);
  EXPECT_EQ(counter(families, "grpc_server_handled_total", not_found), 1);
  // Only the codes seen have a series.
  Labels internal = method;
  internal["grpc_code"] = "INTERNAL";
  EXPECT_EQ(find(families, "grpc_server_handled_total", internal), nullptr);

  // Each call read the clock twice, 2 ms apart.
  const prometheus::ClientMetric* seconds = find(families, "grpc_server_handling_seconds", method);
  ASSERT_NE(seconds, nullptr);
  EXPECT_EQ(seconds->histogram.sample_count, 3u);
  EXPECT_NEAR(seconds->histogram.sample_sum, 0.006, 1e-9);
  for (const auto& bucket : seconds->histogram.bucket) {
    const uint64_t expected = bucket.upper_bound >= 0.002 ? 3 : 0;
    EXPECT_EQ(bucket.cumulative_count, expected) << "le=" << bucket.upper_bound;
  }
}

TEST_F(ServerMetricsTest, MethodsTheProtosDoNotDeclareShareOneSeries) {
  // Any caller may name any method: those names must not become series.
  grpc::GenericStub generic(channel_);
  for (const char* method : {"/evil.Service/M0", "/evil.Service/M1",
                             "/behaviorlib.v1.Coordinator/NoSuchMethod", "nonsense"}) {
    grpc::ClientContext context;
    grpc::Slice empty("");
    grpc::ByteBuffer request(&empty, 1), response;
    grpc::Status status;
    std::mutex mutex;
    std::condition_variable done;
    bool finished = false;
    generic.UnaryCall(&context, method, grpc::StubOptions(), &request, &response,
                      [&](grpc::Status s) {
                        std::lock_guard<std::mutex> lock(mutex);
                        status = std::move(s);
                        finished = true;
                        done.notify_one();
                      });
    std::unique_lock<std::mutex> lock(mutex);
    done.wait(lock, [&] { return finished; });
    EXPECT_EQ(status.error_code(), grpc::StatusCode::UNIMPLEMENTED) << method;
  }
  ASSERT_TRUE(get("known").ok());
  const auto families = registry_.Collect();
  for (const auto& family : families) {
    for (const auto& metric : family.metric) {
      for (const auto& label : metric.label) {
        EXPECT_EQ(label.value.find("evil"), std::string::npos) << family.name;
        EXPECT_NE(label.value, "NoSuchMethod") << family.name;
      }
    }
  }
  EXPECT_EQ(counter(families, "grpc_server_handled_total",
                    {{"grpc_service", "unknown"},
                     {"grpc_method", "unknown"},
                     {"grpc_code", "UNIMPLEMENTED"}}),
            4);
  EXPECT_EQ(counter(families, "grpc_server_handled_total",
                    {{"grpc_method", "GetMission"}, {"grpc_code", "OK"}}),
            1);
}

TEST_F(ServerMetricsTest, AStreamItsClientCancelsEndsCancelled) {
  {
    grpc::ClientContext context;
    auto reader = stub_->WatchMission(&context, v1::WatchMissionRequest());
    v1::WatchMissionResponse response;
    ASSERT_TRUE(reader->Read(&response));
    context.TryCancel();
    while (reader->Read(&response)) {
    }
    EXPECT_EQ(reader->Finish().error_code(), grpc::StatusCode::CANCELLED);
  }
  const Labels method = {{"grpc_type", "server_stream"},
                         {"grpc_service", "behaviorlib.v1.Coordinator"},
                         {"grpc_method", "WatchMission"},
                         {"grpc_code", "CANCELLED"}};
  // The server finishes the call after the client has seen it end: wait for
  // that (bounded), not for a time.
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(30);
  while (counter(registry_.Collect(), "grpc_server_handled_total", method) < 1 &&
         std::chrono::steady_clock::now() < deadline) {
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
  }
  const auto families = registry_.Collect();
  EXPECT_EQ(counter(families, "grpc_server_handled_total", method), 1);
  EXPECT_EQ(counter(families, "grpc_server_started_total",
                    {{"grpc_type", "server_stream"}, {"grpc_method", "WatchMission"}}),
            1);
}

TEST(ParseProcStat, CountsFieldsFromTheLastParenthesis) {
  // A command name with a space and a parenthesis; fields 3.. as proc(5).
  const std::string text =
      "1234 (my (odd) name) S 1 1234 1234 0 -1 4194560 500 0 0 0 "
      "250 150 0 0 20 0 9 0 7000 123456789 2048 18446744073709551615 1 1 0 0 0 0 0 0 0 0 0 0 "
      "17 1 0 0 0 0 0\n";
  const auto stat = parseProcStat(text, 100, 4096);
  ASSERT_TRUE(stat.has_value());
  EXPECT_DOUBLE_EQ(stat->cpu_seconds, 4.0);  // (250 + 150) / 100
  EXPECT_DOUBLE_EQ(stat->start_seconds_after_boot, 70.0);
  EXPECT_EQ(stat->virtual_memory_bytes, 123456789u);
  EXPECT_EQ(stat->resident_memory_bytes, 2048u * 4096u);

  EXPECT_FALSE(parseProcStat("", 100, 4096).has_value());
  EXPECT_FALSE(parseProcStat("1 (x) S 1 2 3", 100, 4096).has_value());
  EXPECT_FALSE(parseProcStat(text, 0, 4096).has_value());
}

TEST(ProcessCollector, ReportsThisProcess) {
  // Some CPU time to report.
  volatile double sink = 0;
  const clock_t until = clock() + CLOCKS_PER_SEC / 20;
  while (clock() < until) sink = sink + 1;
  const auto families = makeProcessCollector()->Collect();
  auto value = [&](const std::string& name) {
    const prometheus::ClientMetric* metric = find(families, name, {});
    EXPECT_NE(metric, nullptr) << name;
    if (metric == nullptr) return -1.0;
    return name == "process_cpu_seconds_total" ? metric->counter.value : metric->gauge.value;
  };
  EXPECT_GT(value("process_cpu_seconds_total"), 0.0);
  EXPECT_GT(value("process_resident_memory_bytes"), 1 << 20);
  EXPECT_GT(value("process_virtual_memory_bytes"), value("process_resident_memory_bytes"));
  EXPECT_GE(value("process_open_fds"), 3);  // stdin, stdout, stderr
  EXPECT_GE(value("process_max_fds"), value("process_open_fds"));
  const double now_s = static_cast<double>(std::time(nullptr));
  EXPECT_GT(value("process_start_time_seconds"), now_s - 3600);
  EXPECT_LE(value("process_start_time_seconds"), now_s + 1);
}

TEST(ProcessCollector, CountsTheHeapInUse) {
  auto in_use = [] {
    const auto families = makeProcessCollector()->Collect();
    const prometheus::ClientMetric* metric =
        find(families, "behaviorlib_process_heap_in_use_bytes", {});
    EXPECT_NE(metric, nullptr);
    EXPECT_NE(find(families, "behaviorlib_process_heap_free_bytes", {}), nullptr);
    return metric == nullptr ? -1.0 : metric->gauge.value;
  };
  const double before = in_use();
  constexpr size_t kBytes = 32u << 20;
  {
    std::vector<char> held(kBytes, 1);
    EXPECT_GE(in_use() - before, static_cast<double>(kBytes));
    EXPECT_GE(heapStat().in_use_bytes, kBytes);
  }
  EXPECT_LT(in_use() - before, static_cast<double>(kBytes));
}

TEST(BuildInfo, IsOneWithTheVersions) {
  prometheus::Registry registry;
  addBuildInfo(registry);
  const auto families = registry.Collect();
  const prometheus::ClientMetric* info =
      find(families, "behaviorlib_build_info", {{"grpc_version", grpc::Version()}});
  ASSERT_NE(info, nullptr);
  EXPECT_EQ(info->gauge.value, 1);
  std::map<std::string, std::string> labels;
  for (const auto& label : info->label) labels[label.name] = label.value;
  EXPECT_FALSE(labels["version"].empty());
  EXPECT_NE(labels["version"], "unknown");
  EXPECT_FALSE(labels["protobuf_version"].empty());
  EXPECT_FALSE(labels["compiler"].empty());
}

}  // namespace
}  // namespace behaviorlib::server_kit
