// bench_behavior_system: a behavior system hosting seven probe behaviors,
// PROBE_1 .. PROBE_7, for system_bench. A probe behaves like WAIT (parameters
// behaviorlib.v1.WaitParameters; it finishes GOAL_ACHIEVED once its active
// time reaches duration_s) and stamps CLOCK_MONOTONIC into the shared-memory
// file named by BEHAVIORLIB_BENCH_SHM:
//   - when the first onExecute of an activation starts;
//   - when checkGoal decides that the goal is reached.
// The probes are reachable through the generic BehaviorSystem service only
// (ActivateBehavior with Struct parameters {"duration_s": x}).
//
// Flags are those of every behavior system (runBehaviorSystem); run --help.

#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <memory>
#include <string>

#include "behaviorlib/behavior_execution_manager.h"
#include "behaviorlib/server/behavior_system_main.h"
// grpc::Service must be complete where the builder is used.
#include "behaviorlib/v1/behavior.grpc.pb.h"
#include "behaviorlib/v1/behaviors/basic_quadrotor_behaviors.pb.h"
#include "bench/bench_shm.h"

namespace behaviorlib::bench {
namespace {

class ProbeBehavior final : public Behavior<v1::WaitParameters> {
 public:
  ProbeBehavior(std::string name, ProbeSlot* slot) : Behavior(std::move(name)), slot_(slot) {}

 protected:
  absl::Status onActivate() override {
    first_execute_pending_ = true;
    wanted_ = seconds(parameters().duration_s());
    return absl::OkStatus();
  }

  void onExecute() override {
    if (!first_execute_pending_) return;
    first_execute_pending_ = false;
    slot_->first_execute_ns.store(monotonicNs(), std::memory_order_relaxed);
    slot_->first_execute_seq.fetch_add(1, std::memory_order_release);
  }

  Verdict checkGoal() override {
    if (activeTime() < wanted_) return Verdict::keepGoing();
    slot_->goal_ns.store(monotonicNs(), std::memory_order_relaxed);
    slot_->goal_seq.fetch_add(1, std::memory_order_release);
    return Verdict::finish("probe goal reached");
  }

 private:
  ProbeSlot* slot_;
  bool first_execute_pending_ = false;
  Duration wanted_{0};
};

SharedStamps* openStamps() {
  const char* path = std::getenv(kShmEnv);
  if (path != nullptr && *path != '\0') {
    SharedStamps* stamps = mapSharedStamps(path, /*create=*/false);
    if (stamps == nullptr || stamps->magic != kShmMagic) {
      std::fprintf(stderr, "bench_behavior_system: cannot map %s=%s (create it first)\n", kShmEnv,
                   path);
      std::exit(2);
    }
    return stamps;
  }
  // No client watching: stamp into private memory.
  return new SharedStamps{};
}

}  // namespace
}  // namespace behaviorlib::bench

int main(int argc, char** argv) {
  using behaviorlib::server::BehaviorSystemBuilder;
  namespace bench = behaviorlib::bench;
  bench::SharedStamps* stamps = bench::openStamps();
  return behaviorlib::server::runBehaviorSystem(
      argc, argv, "bench_behavior_system", [stamps](BehaviorSystemBuilder& builder) {
        for (int i = 0; i < bench::kProbeCount; ++i) {
          builder.addGeneric(std::make_unique<bench::ProbeBehavior>(
              "PROBE_" + std::to_string(i + 1), &stamps->probes[i]));
        }
      });
}
