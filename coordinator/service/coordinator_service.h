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
#include <mutex>
#include <set>

#include "behaviorlib/v1/coordinator.grpc.pb.h"
#include "coordinator/service/coordinator_metrics.h"
#include "coordinator/service/fleet_event_log.h"
#include "coordinator/service/registry.h"

namespace behaviorlib::coordinator {

class FleetStreamReactor;
class BeliefStore;

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
};

class CoordinatorService final : public v1::Coordinator::CallbackService {
 public:
  CoordinatorService(Registry& registry, FleetEventLog& log, CoordinatorMetrics& metrics,
                     CoordinatorServiceOptions options);
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
  grpc::ServerWriteReactor<v1::WatchFleetEventsResponse>* WatchEvents(
      grpc::CallbackServerContext* context, const v1::WatchFleetEventsRequest* request) override;
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
  grpc::ServerUnaryReactor* ActivateBehavior(grpc::CallbackServerContext* context,
                                             const v1::ActivateFleetBehaviorRequest* request,
                                             v1::ActivateFleetBehaviorResponse* response) override;
  grpc::ServerUnaryReactor* DeactivateBehavior(
      grpc::CallbackServerContext* context, const v1::DeactivateFleetBehaviorRequest* request,
      v1::DeactivateFleetBehaviorResponse* response) override;
  grpc::ServerUnaryReactor* CheckBehaviorSituation(
      grpc::CallbackServerContext* context, const v1::CheckFleetBehaviorSituationRequest* request,
      v1::CheckFleetBehaviorSituationResponse* response) override;

 private:
  friend class FleetStreamReactor;
  class BeliefStore;
  void removeStream(FleetStreamReactor* stream);

  Registry& registry_;
  FleetEventLog& log_;
  CoordinatorMetrics& metrics_;
  const CoordinatorServiceOptions options_;
  std::mutex streams_mutex_;
  std::set<FleetStreamReactor*> streams_;
  bool shutting_down_ = false;
};

}  // namespace behaviorlib::coordinator
