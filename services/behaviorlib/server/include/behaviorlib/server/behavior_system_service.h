#pragma once

// The generic BehaviorSystem service of a behavior-system process:
// ListBehaviors (schemas from the descriptors), the resumable WatchEvents
// stream, and lifecycle calls that name the behavior and carry parameters as
// google.protobuf.Struct.

#include <grpcpp/grpcpp.h>

#include <map>
#include <set>
#include <string>

#include "absl/base/thread_annotations.h"
#include "absl/synchronization/mutex.h"
#include "behaviorlib/behavior_host.h"
#include "behaviorlib/server/lifecycle_calls.h"
#include "behaviorlib/v1/behavior.grpc.pb.h"

namespace behaviorlib::server {

class EventStreamReactor;

class BehaviorSystemService final : public v1::BehaviorSystem::CallbackService {
 public:
  /// `typed_services` maps a behavior name to the full name of its typed
  /// service (behaviors without one are reachable here only).
  BehaviorSystemService(BehaviorHost& host, const AcceptGate& gate,
                        std::map<std::string, std::string> typed_services);
  ~BehaviorSystemService() override;

  /// Ends every WatchEvents stream once the events queued for it are sent
  /// (status UNAVAILABLE: the client may resume elsewhere with since_seq).
  void shutdownStreams();

  grpc::ServerUnaryReactor* ListBehaviors(grpc::CallbackServerContext* context,
                                          const v1::ListBehaviorsRequest* request,
                                          v1::ListBehaviorsResponse* response) override;
  grpc::ServerWriteReactor<v1::WatchEventsResponse>* WatchEvents(
      grpc::CallbackServerContext* context, const v1::WatchEventsRequest* request) override;
  grpc::ServerUnaryReactor* ActivateBehavior(grpc::CallbackServerContext* context,
                                             const v1::ActivateBehaviorRequest* request,
                                             v1::ActivateResponse* response) override;
  grpc::ServerUnaryReactor* DeactivateBehavior(grpc::CallbackServerContext* context,
                                               const v1::DeactivateBehaviorRequest* request,
                                               v1::DeactivateResponse* response) override;
  grpc::ServerUnaryReactor* CheckBehaviorActivation(
      grpc::CallbackServerContext* context, const v1::CheckBehaviorActivationRequest* request,
      v1::CheckActivationResponse* response) override;
  grpc::ServerUnaryReactor* CheckBehaviorSituation(grpc::CallbackServerContext* context,
                                                   const v1::CheckBehaviorSituationRequest* request,
                                                   v1::CheckSituationResponse* response) override;
  grpc::ServerUnaryReactor* PauseBehavior(grpc::CallbackServerContext* context,
                                          const v1::PauseBehaviorRequest* request,
                                          v1::PauseResponse* response) override;
  grpc::ServerUnaryReactor* ResumeBehavior(grpc::CallbackServerContext* context,
                                           const v1::ResumeBehaviorRequest* request,
                                           v1::ResumeResponse* response) override;
  grpc::ServerUnaryReactor* ModifyBehavior(grpc::CallbackServerContext* context,
                                           const v1::ModifyBehaviorRequest* request,
                                           v1::ModifyResponse* response) override;

 private:
  friend class EventStreamReactor;
  // The behavior, or nullptr with `status` set to NOT_FOUND.
  BehaviorExecutionManager* lookup(const std::string& name, grpc::Status* status) const;
  // Parameters of `behavior` from a Struct (INVALID_ARGUMENT on bad input).
  std::unique_ptr<google::protobuf::Message> fromStruct(const BehaviorExecutionManager& behavior,
                                                        const google::protobuf::Struct& in,
                                                        grpc::Status* status) const;
  void removeStream(EventStreamReactor* stream);

  BehaviorHost& host_;
  const AcceptGate& gate_;
  std::map<std::string, std::string> typed_services_;
  absl::Mutex streams_mutex_;
  std::set<EventStreamReactor*> streams_ ABSL_GUARDED_BY(streams_mutex_);
  bool shutting_down_ ABSL_GUARDED_BY(streams_mutex_) = false;
};

}  // namespace behaviorlib::server
