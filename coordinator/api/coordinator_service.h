#pragma once

// The gRPC face of the coordinator (behaviorlib.v1.Coordinator): registration
// and heartbeats into the Registry, the fleet-wide lists, the resumable
// WatchEvents stream over the FleetEventLog, and lifecycle calls routed to the
// hosting behavior system.
//
//   FleetEventLog log;
//   Registry registry(log, metrics, options);
//   CoordinatorService service(registry, log, metrics, {.heartbeat_interval = 1s});
//   builder.RegisterService(&service);
//   ...
//   service.shutdownStreams();   // on SIGTERM, before the server shuts down

#include <grpcpp/grpcpp.h>

#include <chrono>
#include <functional>
#include <map>
#include <memory>
#include <set>
#include <string>
#include <string_view>

#include "absl/base/thread_annotations.h"
#include "absl/synchronization/mutex.h"
#include "behaviorlib/v1/coordinator.grpc.pb.h"
#include "coordinator/events/fleet_event_log.h"
#include "coordinator/metrics/coordinator_metrics.h"
#include "coordinator/registry/registry.h"

namespace behaviorlib::coordinator {

class FleetStreamReactor;
class MissionStreamReactor;
class BeliefStreamReactor;
class BeliefStore;
class BlockingPool;
class FleetControl;
class MissionManager;
class SafetyController;
class VehicleStreamReactor;
class VehicleTelemetry;

struct CoordinatorServiceOptions {
  /// Told to systems at registration: how often to send Heartbeat.
  std::chrono::milliseconds heartbeat_interval{1000};
  /// Deadline of the ListBehaviors call made during RegisterSystem.
  std::chrono::milliseconds describe_timeout{3000};
  /// Deadline of a routed lifecycle call when the client set none.
  std::chrono::milliseconds default_call_timeout{30000};
  /// Belief memory served by WriteBelief/ReadBelief/...; must outlive the
  /// service. Null: those calls answer FAILED_PRECONDITION.
  BeliefStore* beliefs = nullptr;
  /// Missions; null: mission calls answer FAILED_PRECONDITION.
  MissionManager* missions = nullptr;
  /// EmergencyLand and Kill; null: they answer FAILED_PRECONDITION.
  SafetyController* safety = nullptr;
  /// GetVehicleSample and WatchVehicle; null: they answer
  /// FAILED_PRECONDITION (the coordinator has no --channel).
  VehicleTelemetry* telemetry = nullptr;
};

// WatchEvents is a raw method: its events are written from their stored
// wire forms (FleetEventRecord), serialized once for every subscriber.
class CoordinatorService final
    : public v1::Coordinator::WithRawCallbackMethod_WatchEvents<v1::Coordinator::CallbackService> {
 public:
  /// `fleet` is the one path of ActivateBehavior and DeactivateBehavior
  /// (the catalog's plan, the read-your-writes wait); the other lifecycle
  /// calls are forwarded to the robot's system as they are. `pool` runs the
  /// blocking work (those two, the mission and safety calls).
  CoordinatorService(Registry& registry, FleetEventLog& log, CoordinatorMetrics& metrics,
                     FleetControl& fleet, BlockingPool& pool, CoordinatorServiceOptions options);
  ~CoordinatorService() override;

  /// Ends every WatchEvents stream once what is queued for it is sent
  /// (UNAVAILABLE with the since_seq to resume from), and refuses new ones.
  void shutdownStreams();

  grpc::ServerUnaryReactor* RegisterSystem(grpc::CallbackServerContext* context,
                                           const v1::RegisterSystemRequest* request,
                                           v1::RegisterSystemResponse* response) override;
  grpc::ServerUnaryReactor* Heartbeat(grpc::CallbackServerContext* context,
                                      const v1::HeartbeatRequest* request,
                                      v1::HeartbeatResponse* response) override;
  grpc::ServerUnaryReactor* UnregisterSystem(grpc::CallbackServerContext* context,
                                             const v1::UnregisterSystemRequest* request,
                                             v1::UnregisterSystemResponse* response) override;
  grpc::ServerUnaryReactor* ListSystems(grpc::CallbackServerContext* context,
                                        const v1::ListSystemsRequest* request,
                                        v1::ListSystemsResponse* response) override;
  grpc::ServerUnaryReactor* ListBehaviors(grpc::CallbackServerContext* context,
                                          const v1::ListFleetBehaviorsRequest* request,
                                          v1::ListFleetBehaviorsResponse* response) override;
  grpc::ServerWriteReactor<grpc::ByteBuffer>* WatchEvents(grpc::CallbackServerContext* context,
                                                          const grpc::ByteBuffer* request) override;
  grpc::ServerUnaryReactor* WriteBelief(grpc::CallbackServerContext* context,
                                        const v1::WriteBeliefRequest* request,
                                        v1::WriteBeliefResponse* response) override;
  grpc::ServerUnaryReactor* ReadBelief(grpc::CallbackServerContext* context,
                                       const v1::ReadBeliefRequest* request,
                                       v1::ReadBeliefResponse* response) override;
  grpc::ServerUnaryReactor* ListBeliefs(grpc::CallbackServerContext* context,
                                        const v1::ListBeliefsRequest* request,
                                        v1::ListBeliefsResponse* response) override;
  grpc::ServerUnaryReactor* DeleteBelief(grpc::CallbackServerContext* context,
                                         const v1::DeleteBeliefRequest* request,
                                         v1::DeleteBeliefResponse* response) override;
  grpc::ServerWriteReactor<v1::WatchBeliefsResponse>* WatchBeliefs(
      grpc::CallbackServerContext* context, const v1::WatchBeliefsRequest* request) override;
  grpc::ServerUnaryReactor* StartMission(grpc::CallbackServerContext* context,
                                         const v1::StartMissionRequest* request,
                                         v1::StartMissionResponse* response) override;
  grpc::ServerUnaryReactor* CheckMission(grpc::CallbackServerContext* context,
                                         const v1::CheckMissionRequest* request,
                                         v1::CheckMissionResponse* response) override;
  grpc::ServerUnaryReactor* GetMission(grpc::CallbackServerContext* context,
                                       const v1::GetMissionRequest* request,
                                       v1::GetMissionResponse* response) override;
  grpc::ServerUnaryReactor* ListMissions(grpc::CallbackServerContext* context,
                                         const v1::ListMissionsRequest* request,
                                         v1::ListMissionsResponse* response) override;
  grpc::ServerWriteReactor<v1::WatchMissionResponse>* WatchMission(
      grpc::CallbackServerContext* context, const v1::WatchMissionRequest* request) override;
  grpc::ServerUnaryReactor* PauseMission(grpc::CallbackServerContext* context,
                                         const v1::MissionControlRequest* request,
                                         v1::MissionControlResponse* response) override;
  grpc::ServerUnaryReactor* ResumeMission(grpc::CallbackServerContext* context,
                                          const v1::MissionControlRequest* request,
                                          v1::MissionControlResponse* response) override;
  grpc::ServerUnaryReactor* AbortMission(grpc::CallbackServerContext* context,
                                         const v1::MissionControlRequest* request,
                                         v1::MissionControlResponse* response) override;
  grpc::ServerUnaryReactor* EmergencyLand(grpc::CallbackServerContext* context,
                                          const v1::SafetyActionRequest* request,
                                          v1::SafetyActionResponse* response) override;
  grpc::ServerUnaryReactor* Kill(grpc::CallbackServerContext* context,
                                 const v1::SafetyActionRequest* request,
                                 v1::SafetyActionResponse* response) override;
  grpc::ServerUnaryReactor* GetVehicleSample(grpc::CallbackServerContext* context,
                                             const v1::GetVehicleSampleRequest* request,
                                             v1::GetVehicleSampleResponse* response) override;
  grpc::ServerWriteReactor<v1::WatchVehicleResponse>* WatchVehicle(
      grpc::CallbackServerContext* context, const v1::WatchVehicleRequest* request) override;
  grpc::ServerUnaryReactor* ActivateBehavior(grpc::CallbackServerContext* context,
                                             const v1::ActivateFleetBehaviorRequest* request,
                                             v1::ActivateFleetBehaviorResponse* response) override;
  grpc::ServerUnaryReactor* DeactivateBehavior(
      grpc::CallbackServerContext* context, const v1::DeactivateFleetBehaviorRequest* request,
      v1::DeactivateFleetBehaviorResponse* response) override;
  grpc::ServerUnaryReactor* CheckBehaviorSituation(
      grpc::CallbackServerContext* context, const v1::CheckFleetBehaviorSituationRequest* request,
      v1::CheckFleetBehaviorSituationResponse* response) override;
  // Forwarded to the hosting system's BehaviorSystem call.
  grpc::ServerUnaryReactor* CheckFleetBehaviorActivation(
      grpc::CallbackServerContext* context, const v1::CheckFleetBehaviorActivationRequest* request,
      v1::CheckFleetBehaviorActivationResponse* response) override;
  grpc::ServerUnaryReactor* PauseFleetBehavior(grpc::CallbackServerContext* context,
                                               const v1::PauseFleetBehaviorRequest* request,
                                               v1::PauseFleetBehaviorResponse* response) override;
  grpc::ServerUnaryReactor* ResumeFleetBehavior(grpc::CallbackServerContext* context,
                                                const v1::ResumeFleetBehaviorRequest* request,
                                                v1::ResumeFleetBehaviorResponse* response) override;
  grpc::ServerUnaryReactor* ModifyFleetBehavior(grpc::CallbackServerContext* context,
                                                const v1::ModifyFleetBehaviorRequest* request,
                                                v1::ModifyFleetBehaviorResponse* response) override;

 private:
  friend class FleetStreamReactor;
  friend class MissionStreamReactor;
  friend class BeliefStreamReactor;
  friend class VehicleStreamReactor;
  void removeStream(FleetStreamReactor* stream);
  /// PERMISSION_DENIED when the caller is bound to another robot than the
  /// mission's (RobotScope); the mission lookup's error; else OK.
  grpc::Status missionScopeRefusal(const grpc::CallbackServerContext& context,
                                   const std::string& mission_id, std::string_view what) const;
  /// Runs `work` on the blocking pool and finishes the call with its status.
  grpc::ServerUnaryReactor* runBlocking(grpc::CallbackServerContext* context,
                                        std::function<grpc::Status()> work);
  /// Streams (WatchMission, WatchBeliefs) are ended by shutdownStreams():
  /// addShutdownHook returns false (and keeps nothing) once it has run.
  uint64_t newHookId();
  bool addShutdownHook(uint64_t id, std::function<void()> hook);
  /// For a QueuedStream: ends it with UNAVAILABLE (SHUTTING_DOWN) and
  /// `message` when the streams are shut down (hook `id`). False, with the
  /// stream ended already, when they are shut down by now.
  template <class Stream>
  bool endOnShutdown(uint64_t id, const std::shared_ptr<typename Stream::Core>& core,
                     std::string message);
  void removeShutdownHook(uint64_t id);

  Registry& registry_;
  FleetEventLog& log_;
  CoordinatorMetrics& metrics_;
  FleetControl& fleet_;
  BlockingPool& pool_;
  const CoordinatorServiceOptions options_;
  absl::Mutex streams_mutex_;
  std::set<FleetStreamReactor*> streams_ ABSL_GUARDED_BY(streams_mutex_);
  bool shutting_down_ ABSL_GUARDED_BY(streams_mutex_) = false;
  uint64_t next_hook_ ABSL_GUARDED_BY(streams_mutex_) = 1;
  std::map<uint64_t, std::function<void()>> shutdown_hooks_ ABSL_GUARDED_BY(streams_mutex_);
};

}  // namespace behaviorlib::coordinator
