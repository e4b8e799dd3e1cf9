#pragma once

// The uniform interface of one behavior over gRPC's callback API, shared by
// every typed behavior service (TypedBehaviorService<S>) and the generic
// BehaviorSystem service: each function starts the call on the behavior and
// finishes `context`'s reactor when the behavior answers.

#include <grpcpp/grpcpp.h>

#include <atomic>
#include <memory>
#include <string>

#include "behaviorlib/behavior_execution_manager.h"
#include "behaviorlib/v1/behavior.pb.h"

namespace behaviorlib::server {

/// Refuses lifecycle calls once the process is shutting down, and the
/// calls of an identity bound to another robot than the system's own
/// (RobotScope): a system's certificate commands only its robot's behaviors.
class AcceptGate {
 public:
  AcceptGate() = default;
  explicit AcceptGate(std::string robot_id) : robot_id_(std::move(robot_id)) {}

  bool accepting() const { return accepting_.load(std::memory_order_acquire); }
  void close() { accepting_.store(false, std::memory_order_release); }
  /// The robot whose behaviors this process hosts (empty: not known).
  const std::string& robot() const { return robot_id_; }

 private:
  std::atomic<bool> accepting_{true};
  const std::string robot_id_;
};

grpc::ServerUnaryReactor* activateCall(grpc::CallbackServerContext* context, const AcceptGate& gate,
                                       BehaviorExecutionManager& behavior,
                                       std::unique_ptr<google::protobuf::Message> parameters,
                                       const std::string& request_id,
                                       v1::ActivateResponse* response);
grpc::ServerUnaryReactor* deactivateCall(grpc::CallbackServerContext* context,
                                         const AcceptGate& gate, BehaviorExecutionManager& behavior,
                                         const std::string& activation_id,
                                         v1::DeactivateResponse* response);
grpc::ServerUnaryReactor* checkActivationCall(grpc::CallbackServerContext* context,
                                              BehaviorExecutionManager& behavior,
                                              v1::CheckActivationResponse* response);
grpc::ServerUnaryReactor* checkSituationCall(grpc::CallbackServerContext* context,
                                             const AcceptGate& gate,
                                             BehaviorExecutionManager& behavior,
                                             v1::CheckSituationResponse* response);
grpc::ServerUnaryReactor* pauseCall(grpc::CallbackServerContext* context, const AcceptGate& gate,
                                    BehaviorExecutionManager& behavior,
                                    const std::string& activation_id, v1::PauseResponse* response);
grpc::ServerUnaryReactor* resumeCall(grpc::CallbackServerContext* context, const AcceptGate& gate,
                                     BehaviorExecutionManager& behavior,
                                     const std::string& activation_id,
                                     v1::ResumeResponse* response);
grpc::ServerUnaryReactor* modifyCall(grpc::CallbackServerContext* context, const AcceptGate& gate,
                                     BehaviorExecutionManager& behavior,
                                     const std::string& activation_id,
                                     std::unique_ptr<google::protobuf::Message> update,
                                     v1::ModifyResponse* response);

/// A reactor finished at once with `status`.
grpc::ServerUnaryReactor* finishNow(grpc::CallbackServerContext* context,
                                    const grpc::Status& status);

}  // namespace behaviorlib::server
