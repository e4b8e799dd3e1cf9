#include "behaviorlib/server/lifecycle_calls.h"

#include "behaviorlib/error_details.h"
#include "behaviorlib/server_kit/access_policy.h"

namespace behaviorlib::server {
namespace {

// Completion that copies the behavior's answer into the gRPC response and
// finishes the reactor. The reactor and response stay valid until Finish.
template <class T>
Done<T> finishInto(grpc::ServerUnaryReactor* reactor, T* response) {
  return [reactor, response](absl::StatusOr<T> result) {
    if (result.ok()) {
      *response = std::move(*result);
      reactor->Finish(grpc::Status::OK);
    } else {
      reactor->Finish(errors::toGrpc(result.status()));
    }
  };
}

grpc::Status shuttingDown() {
  return errors::grpcError(grpc::StatusCode::UNAVAILABLE, v1::SHUTTING_DOWN,
                           "the behavior system is shutting down");
}

// Why `gate` refuses a call that commands a behavior (`what`), or OK.
grpc::Status refusal(const grpc::CallbackServerContext& context, const AcceptGate& gate,
                     std::string_view what) {
  if (!gate.accepting()) return shuttingDown();
  if (gate.robot().empty()) return grpc::Status::OK;
  return errors::toGrpc(server_kit::checkRobotScope(context, gate.robot(), what));
}

}  // namespace

grpc::ServerUnaryReactor* finishNow(grpc::CallbackServerContext* context,
                                    const grpc::Status& status) {
  auto* reactor = context->DefaultReactor();
  reactor->Finish(status);
  return reactor;
}

grpc::ServerUnaryReactor* activateCall(grpc::CallbackServerContext* context, const AcceptGate& gate,
                                       BehaviorExecutionManager& behavior,
                                       std::unique_ptr<google::protobuf::Message> parameters,
                                       const std::string& request_id,
                                       v1::ActivateResponse* response) {
  const auto received = std::chrono::steady_clock::now();
  if (auto r = refusal(*context, gate, "activate behaviors"); !r.ok()) return finishNow(context, r);
  auto* reactor = context->DefaultReactor();
  behavior.activate(std::move(parameters), request_id, finishInto(reactor, response), received);
  return reactor;
}

grpc::ServerUnaryReactor* deactivateCall(grpc::CallbackServerContext* context,
                                         const AcceptGate& gate, BehaviorExecutionManager& behavior,
                                         const std::string& activation_id,
                                         v1::DeactivateResponse* response) {
  if (auto r = refusal(*context, gate, "deactivate behaviors"); !r.ok())
    return finishNow(context, r);
  auto* reactor = context->DefaultReactor();
  behavior.deactivate(activation_id, finishInto(reactor, response));
  return reactor;
}

grpc::ServerUnaryReactor* checkActivationCall(grpc::CallbackServerContext* context,
                                              BehaviorExecutionManager& behavior,
                                              v1::CheckActivationResponse* response) {
  *response = behavior.checkActivation();
  return finishNow(context, grpc::Status::OK);
}

grpc::ServerUnaryReactor* checkSituationCall(grpc::CallbackServerContext* context,
                                             const AcceptGate& gate,
                                             BehaviorExecutionManager& behavior,
                                             v1::CheckSituationResponse* response) {
  if (!gate.accepting()) return finishNow(context, shuttingDown());
  auto* reactor = context->DefaultReactor();
  behavior.checkSituationNow(finishInto(reactor, response));
  return reactor;
}

grpc::ServerUnaryReactor* pauseCall(grpc::CallbackServerContext* context, const AcceptGate& gate,
                                    BehaviorExecutionManager& behavior,
                                    const std::string& activation_id, v1::PauseResponse* response) {
  if (auto r = refusal(*context, gate, "pause behaviors"); !r.ok()) return finishNow(context, r);
  auto* reactor = context->DefaultReactor();
  behavior.pause(activation_id, finishInto(reactor, response));
  return reactor;
}

grpc::ServerUnaryReactor* resumeCall(grpc::CallbackServerContext* context, const AcceptGate& gate,
                                     BehaviorExecutionManager& behavior,
                                     const std::string& activation_id,
                                     v1::ResumeResponse* response) {
  if (auto r = refusal(*context, gate, "resume behaviors"); !r.ok()) return finishNow(context, r);
  auto* reactor = context->DefaultReactor();
  behavior.resume(activation_id, finishInto(reactor, response));
  return reactor;
}

grpc::ServerUnaryReactor* modifyCall(grpc::CallbackServerContext* context, const AcceptGate& gate,
                                     BehaviorExecutionManager& behavior,
                                     const std::string& activation_id,
                                     std::unique_ptr<google::protobuf::Message> update,
                                     v1::ModifyResponse* response) {
  if (auto r = refusal(*context, gate, "modify behaviors"); !r.ok()) return finishNow(context, r);
  auto* reactor = context->DefaultReactor();
  behavior.modify(activation_id, std::move(update), finishInto(reactor, response));
  return reactor;
}

}  // namespace behaviorlib::server
