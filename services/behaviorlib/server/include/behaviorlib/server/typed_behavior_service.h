#pragma once

// TypedBehaviorService<S>: serves the generated typed service S of one behavior
// (e.g. behaviorlib::v1::Wait) over its BehaviorExecutionManager. The request
// types are deduced from S's generated callback methods, so adding a behavior
// needs no hand-written server:
//
//   TypedBehaviorService<v1::Wait> wait_service(wait_behavior, gate);
//   builder.RegisterService(&wait_service);
//
// S must have the behavior lifecycle RPCs: Activate(XActivateRequest{request_id,
// parameters}), Deactivate, CheckActivation, CheckSituation, Pause, Resume,
// Modify(XModifyRequest{activation_id, parameters}).

#include <grpcpp/grpcpp.h>

#include "behaviorlib/behavior_execution_manager.h"
#include "behaviorlib/server/lifecycle_calls.h"

namespace behaviorlib::server {
namespace detail {

template <class C, class Request, class Response>
Request requestOf(grpc::ServerUnaryReactor* (C::*)(grpc::CallbackServerContext*, const Request*,
                                                   Response*));

// Moves a typed parameter message into an owned, type-erased one.
template <class Params>
std::unique_ptr<google::protobuf::Message> ownedCopy(const Params& parameters) {
  auto copy = std::make_unique<Params>(parameters);
  return copy;
}

}  // namespace detail

template <class S>
class TypedBehaviorService final : public S::CallbackService {
  using Base = typename S::CallbackService;
  using ActivateRequest = decltype(detail::requestOf(&Base::Activate));
  using ModifyRequest = decltype(detail::requestOf(&Base::Modify));

 public:
  TypedBehaviorService(BehaviorExecutionManager& behavior, const AcceptGate& gate)
      : behavior_(behavior), gate_(gate) {}

  grpc::ServerUnaryReactor* Activate(grpc::CallbackServerContext* context,
                                     const ActivateRequest* request,
                                     v1::ActivateResponse* response) override {
    return activateCall(context, gate_, behavior_, detail::ownedCopy(request->parameters()),
                        request->request_id(), response);
  }
  grpc::ServerUnaryReactor* Deactivate(grpc::CallbackServerContext* context,
                                       const v1::DeactivateRequest* request,
                                       v1::DeactivateResponse* response) override {
    return deactivateCall(context, gate_, behavior_, request->activation_id(), response);
  }
  grpc::ServerUnaryReactor* CheckActivation(grpc::CallbackServerContext* context,
                                            const v1::CheckActivationRequest* /*request*/,
                                            v1::CheckActivationResponse* response) override {
    return checkActivationCall(context, behavior_, response);
  }
  grpc::ServerUnaryReactor* CheckSituation(grpc::CallbackServerContext* context,
                                           const v1::CheckSituationRequest* /*request*/,
                                           v1::CheckSituationResponse* response) override {
    return checkSituationCall(context, gate_, behavior_, response);
  }
  grpc::ServerUnaryReactor* Pause(grpc::CallbackServerContext* context,
                                  const v1::PauseRequest* request,
                                  v1::PauseResponse* response) override {
    return pauseCall(context, gate_, behavior_, request->activation_id(), response);
  }
  grpc::ServerUnaryReactor* Resume(grpc::CallbackServerContext* context,
                                   const v1::ResumeRequest* request,
                                   v1::ResumeResponse* response) override {
    return resumeCall(context, gate_, behavior_, request->activation_id(), response);
  }
  grpc::ServerUnaryReactor* Modify(grpc::CallbackServerContext* context,
                                   const ModifyRequest* request,
                                   v1::ModifyResponse* response) override {
    return modifyCall(context, gate_, behavior_, request->activation_id(),
                      detail::ownedCopy(request->parameters()), response);
  }

 private:
  BehaviorExecutionManager& behavior_;
  const AcceptGate& gate_;
};

}  // namespace behaviorlib::server
