// coordinator_bench_system: a behavior system of many trivial behaviors for
// coordinator_bench. Each behavior behaves like WAIT (parameters
// behaviorlib.v1.WaitParameters): it finishes GOAL_ACHIEVED once its active
// time reaches duration_s, so duration_s 0 finishes on the first tick (the
// one that runs at once after activation) and a long duration keeps it active
// until it is deactivated. The behaviors are reachable through the generic
// BehaviorSystem service only.
//
//   coordinator_bench_system --bench-system bench_system_03 --bench-behaviors 50
//       --bench-first 101 --robot-id bench --coordinator 127.0.0.1:PORT
//       --listen 127.0.0.1:0 --port-file /tmp/ports
//
// This hosts BENCH_0101 .. BENCH_0150 as system "bench_system_03". The --bench-*
// flags are this program's own; every other flag is a behavior system's
// (runBehaviorSystem; run --help).

#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <memory>
#include <string>
#include <vector>

#include "behaviorlib/behavior_execution_manager.h"
#include "behaviorlib/server/behavior_system_main.h"
// grpc::Service must be complete where the builder is used.
#include "behaviorlib/v1/behavior.grpc.pb.h"
#include "behaviorlib/v1/behaviors/basic_quadrotor_behaviors.pb.h"

namespace behaviorlib::bench {
namespace {

class BenchBehavior final : public Behavior<v1::WaitParameters> {
 public:
  explicit BenchBehavior(std::string name) : Behavior(std::move(name)) {}

 protected:
  absl::Status onActivate() override {
    wanted_ = seconds(parameters().duration_s());
    return absl::OkStatus();
  }

  Verdict checkGoal() override {
    return activeTime() >= wanted_ ? Verdict::finish("waited") : Verdict::keepGoing();
  }

 private:
  Duration wanted_{0};
};

struct BenchFlags {
  std::string system = "coordinator_bench_system";
  int behaviors = 5;
  int first = 1;
};

// Removes the --bench-* flags from argv (both "--flag value" and
// "--flag=value"); false with a message on a bad value.
bool takeBenchFlags(int* argc, char** argv, BenchFlags* flags) {
  std::vector<char*> rest = {argv[0]};
  for (int i = 1; i < *argc; ++i) {
    std::string arg = argv[i];
    std::string value;
    const auto eq = arg.find('=');
    const std::string name = eq == std::string::npos ? arg : arg.substr(0, eq);
    if (name != "--bench-system" && name != "--bench-behaviors" && name != "--bench-first") {
      rest.push_back(argv[i]);
      continue;
    }
    if (eq != std::string::npos) {
      value = arg.substr(eq + 1);
    } else if (i + 1 < *argc) {
      value = argv[++i];
    } else {
      std::fprintf(stderr, "coordinator_bench_system: %s needs a value\n", name.c_str());
      return false;
    }
    if (name == "--bench-system") {
      flags->system = value;
      continue;
    }
    char* end = nullptr;
    const long n = std::strtol(value.c_str(), &end, 10);
    if (end == value.c_str() || *end != '\0' || n < 1 || n > 9999) {
      std::fprintf(stderr,
                   "coordinator_bench_system: %s must be an integer in [1, 9999], not '%s'\n",
                   name.c_str(), value.c_str());
      return false;
    }
    (name == "--bench-behaviors" ? flags->behaviors : flags->first) = static_cast<int>(n);
  }
  if (flags->system.empty()) {
    std::fprintf(stderr, "coordinator_bench_system: --bench-system is empty\n");
    return false;
  }
  *argc = static_cast<int>(rest.size());
  for (size_t i = 0; i < rest.size(); ++i) argv[i] = rest[i];
  argv[rest.size()] = nullptr;
  return true;
}

}  // namespace
}  // namespace behaviorlib::bench

int main(int argc, char** argv) {
  namespace bench = behaviorlib::bench;
  bench::BenchFlags flags;
  if (!bench::takeBenchFlags(&argc, argv, &flags)) return 2;
  return behaviorlib::server::runBehaviorSystem(
      argc, argv, flags.system, [&flags](behaviorlib::server::BehaviorSystemBuilder& builder) {
        for (int i = 0; i < flags.behaviors; ++i) {
          char name[32];
          std::snprintf(name, sizeof(name), "BENCH_%04d", flags.first + i);
          builder.addGeneric(std::make_unique<bench::BenchBehavior>(name));
        }
      });
}
