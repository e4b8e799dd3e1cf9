// tick_bench: the library's own cost of one monitoring tick (the paper's t1
// plus the bookkeeping around it): BehaviorExecutionManager::execute() of an
// active behavior whose user functions do nothing.
//
// The behavior runs in a BehaviorHost on a FakeClock: it is activated (its
// worker runs the first tick and then sleeps, because the fake clock never
// reaches the next tick), and the benchmark loop calls execute() directly.
//
//   tick_bench                                   # 10 repetitions, aggregates
//   tick_bench --benchmark_min_time=0.01 --benchmark_repetitions=2   # ctest smoke
//
// BM_TickNoWorkWithMetricsEvery10ms sleeps 10 ms before each timed tick, as a
// behavior's worker does at 100 Hz (cold caches); its p50_ns/p99_ns counters
// are per-tick percentiles (100 ticks per repetition).
//
// Defaults (unless given): --benchmark_repetitions=10
// --benchmark_report_aggregates_only=true; read the _median rows. Exits 1 when
// a behavior cannot be started or activated, or a tick ends its activation.

#include <benchmark/benchmark.h>
#include <prometheus/registry.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include "behaviorlib/behavior_execution_manager.h"
#include "behaviorlib/behavior_host.h"
#include "behaviorlib/clock.h"
#include "behaviorlib/server/behavior_metrics.h"
#include "behaviorlib/v1/behaviors/basic_quadrotor_behaviors.pb.h"

namespace behaviorlib::bench {
namespace {

std::atomic<bool> g_failed{false};

/// No user work at all: every user function is the library's default.
class NoWorkBehavior final : public Behavior<v1::WaitParameters> {
 public:
  NoWorkBehavior() : Behavior("NO_WORK") {}
};

/// WAIT's checkGoal (reads the clock and the parameters) and nothing else.
class WaitLikeBehavior final : public Behavior<v1::WaitParameters> {
 public:
  WaitLikeBehavior() : Behavior("WAIT_LIKE") {}

 protected:
  Verdict checkGoal() override {
    const auto wanted = seconds(parameters().duration_s());
    return activeTime() >= wanted ? Verdict::finish("waited") : Verdict::keepGoing();
  }
};

void fail(benchmark::State& state, const std::string& message) {
  std::fprintf(stderr, "tick_bench: FAILED: %s\n", message.c_str());
  g_failed = true;
  state.SkipWithError(message.c_str());
}

// Ticks timed one by one after a 10 ms sleep each, as on a behavior's worker
// at 100 Hz (caches and branch predictors go cold between ticks); reported
// as manual time plus per-tick p50/p99 counters.
void coldTicks(benchmark::State& state, BehaviorExecutionManager& behavior) {
  std::vector<double> ns;
  ns.reserve(static_cast<size_t>(state.max_iterations));
  for (auto _ : state) {
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
    const auto t0 = std::chrono::steady_clock::now();
    behavior.execute();
    const auto t1 = std::chrono::steady_clock::now();
    const double d = std::chrono::duration<double>(t1 - t0).count();
    state.SetIterationTime(d);
    ns.push_back(d * 1e9);
  }
  if (ns.empty()) return;
  std::sort(ns.begin(), ns.end());
  auto at = [&](double q) {
    size_t rank = static_cast<size_t>(std::ceil(q * static_cast<double>(ns.size())));
    return ns[std::clamp<size_t>(rank, 1, ns.size()) - 1];
  };
  state.counters["p50_ns"] = at(0.5);
  state.counters["p99_ns"] = at(0.99);
}

template <class B>
void tick(benchmark::State& state, bool with_metrics, bool cold = false) {
  FakeClock clock;
  BehaviorHostOptions options;
  options.robot_id = "bench";
  options.system = "tick_bench";
  BehaviorHost host(options, clock);
  prometheus::Registry registry;
  server::BehaviorMetrics metrics(registry, "bench", "tick_bench");
  if (with_metrics) host.setObserverFactory(metrics.observerFactory());
  auto owned = std::make_unique<B>();
  B* behavior = owned.get();
  host.add(std::move(owned));
  if (absl::Status s = host.start(); !s.ok()) {
    return fail(state, "start: " + std::string(s.message()));
  }
  auto parameters = std::make_unique<v1::WaitParameters>();
  parameters->set_duration_s(86400);
  BehaviorExecutionManager& engine = detail::engineOf(*behavior);
  if (auto r = engine.activateAndWait(std::move(parameters)); !r.ok()) {
    host.stop();
    return fail(state, "activate: " + std::string(r.status().message()));
  }

  if (cold) {
    coldTicks(state, engine);
  } else {
    for (auto _ : state) engine.execute();
  }

  if (engine.state() != v1::BEHAVIOR_STATE_ACTIVE) {
    fail(state, "the activation ended during the ticks");
  }
  host.stop();
}

void BM_TickNoWorkWithMetrics(benchmark::State& state) { tick<NoWorkBehavior>(state, true); }
void BM_TickNoWorkNoObserver(benchmark::State& state) { tick<NoWorkBehavior>(state, false); }
void BM_TickWaitLikeWithMetrics(benchmark::State& state) { tick<WaitLikeBehavior>(state, true); }

void BM_TickNoWorkWithMetricsEvery10ms(benchmark::State& state) {
  tick<NoWorkBehavior>(state, true, /*cold=*/true);
}

void BM_TickNoWorkNoObserverEvery10ms(benchmark::State& state) {
  tick<NoWorkBehavior>(state, false, /*cold=*/true);
}

BENCHMARK(BM_TickNoWorkWithMetrics);
BENCHMARK(BM_TickNoWorkNoObserver);
BENCHMARK(BM_TickWaitLikeWithMetrics);
// 100 ticks of 10 ms: one second per repetition.
BENCHMARK(BM_TickNoWorkWithMetricsEvery10ms)->UseManualTime()->Iterations(100);
BENCHMARK(BM_TickNoWorkNoObserverEvery10ms)->UseManualTime()->Iterations(100);

bool hasFlag(int argc, char** argv, const char* prefix) {
  for (int i = 1; i < argc; ++i) {
    if (std::strncmp(argv[i], prefix, std::strlen(prefix)) == 0) return true;
  }
  return false;
}

}  // namespace
}  // namespace behaviorlib::bench

int main(int argc, char** argv) {
  using behaviorlib::bench::hasFlag;
  std::vector<std::string> defaults;
  if (!hasFlag(argc, argv, "--benchmark_repetitions")) {
    defaults.push_back("--benchmark_repetitions=10");
  }
  if (!hasFlag(argc, argv, "--benchmark_report_aggregates_only")) {
    defaults.push_back("--benchmark_report_aggregates_only=true");
  }
  std::vector<char*> args(argv, argv + argc);
  for (auto& d : defaults) args.push_back(d.data());
  int count = static_cast<int>(args.size());
  args.push_back(nullptr);
  benchmark::Initialize(&count, args.data());
  if (benchmark::ReportUnrecognizedArguments(count, args.data())) return 2;
  benchmark::RunSpecifiedBenchmarks();
  benchmark::Shutdown();
  return behaviorlib::bench::g_failed ? 1 : 0;
}
