#pragma once

// The Simulator gRPC service: time scale and lock-step, Step, WatchState,
// and (refused unless enabled) fault injection through a FaultInjector.

#include <grpcpp/grpcpp.h>

#include <atomic>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <set>
#include <string>
#include <vector>

#include "behaviorlib/v1/simulator.grpc.pb.h"
#include "formats/world/world.h"
#include "simulator/core/simulation.h"
#include "simulator/faults/fault_injector.h"
#include "simulator/service/latest_writer.h"
#include "simulator/service/time_grants.h"
#include "simulator/service/vehicle_models.h"

namespace behaviorlib::sim {

/// How the simulation is paced; shared with the stepping thread.
struct TimeControl {
  std::atomic<double> time_scale{1.0};
  std::atomic<bool> lock_step{false};
  /// Deterministic mode (--time-scale max): the simulator steps itself under
  /// time grants; SetTimeScale and Step are refused.
  std::atomic<bool> deterministic{false};
};

/// The world the vehicles fly in, replaced by Reset.
struct WorldControl {
  std::mutex mutex;
  std::shared_ptr<const world::World> world;  ///< outlives the vehicles that collide with it
  std::string world_arg;                      ///< path or shipped name; "" for an empty field
  std::string worlds_dir;                     ///< where shipped worlds are
  std::vector<std::string> fallback_ids;
  uint64_t seed = 1;  ///< of every random process (sensor noise)
  /// Runs under the simulation's mutex when the new vehicles are in place,
  /// before the next step, with the new world and seed: restarts the sensors.
  std::function<void(const std::shared_ptr<const world::World>& world, uint64_t seed)> on_reset;
};

/// Loads `world_arg` ("" -> an empty field) and puts its vehicles into
/// `simulation`, restarting time, with `seed` for every random process (then
/// control.seed). INVALID_ARGUMENT/NOT_FOUND naming the file, line and
/// problem for a bad world; then nothing changes.
absl::Status loadWorldInto(WorldControl& control, const std::string& world_arg, uint64_t seed,
                           WorldSource source, Simulation& simulation);

using StateWatcher = LatestWriter<v1::WatchStateResponse>;

class SimulatorService final : public v1::Simulator::CallbackService {
 public:
  /// `faults` null: InjectFailure is refused with FAILED_PRECONDITION
  /// (fault injection not enabled). Everything must outlive the service.
  SimulatorService(Simulation& simulation, TimeControl& time, WorldControl& worlds,
                   FaultInjector* faults);

  /// Ends every WatchState stream (shutdown).
  void shutdown();
  /// Serves FollowTime from `grants` (deterministic mode); null refuses it.
  void setTimeGrants(TimeGrants* grants) { grants_ = grants; }

  grpc::ServerUnaryReactor* Reset(grpc::CallbackServerContext* context,
                                  const v1::ResetRequest* request,
                                  v1::ResetResponse* response) override;
  grpc::ServerUnaryReactor* SetTimeScale(grpc::CallbackServerContext* context,
                                         const v1::SetTimeScaleRequest* request,
                                         v1::SetTimeScaleResponse* response) override;
  grpc::ServerUnaryReactor* Step(grpc::CallbackServerContext* context,
                                 const v1::StepRequest* request,
                                 v1::StepResponse* response) override;
  grpc::ServerUnaryReactor* InjectFailure(grpc::CallbackServerContext* context,
                                          const v1::InjectFailureRequest* request,
                                          v1::InjectFailureResponse* response) override;
  grpc::ServerWriteReactor<v1::WatchStateResponse>* WatchState(
      grpc::CallbackServerContext* context, const v1::WatchStateRequest* request) override;
  grpc::ServerBidiReactor<v1::FollowTimeRequest, v1::FollowTimeResponse>* FollowTime(
      grpc::CallbackServerContext* context) override;

 private:
  struct Watch {
    double period_s;
    double next_s = 0.0;
  };
  void removeWatcher(StateWatcher* watcher);

  Simulation& simulation_;
  TimeControl& time_;
  WorldControl& worlds_;
  FaultInjector* const faults_;
  TimeGrants* grants_ = nullptr;
  std::mutex watchers_mutex_;
  std::map<StateWatcher*, Watch> watchers_;
  bool shutting_down_ = false;
};

}  // namespace behaviorlib::sim
