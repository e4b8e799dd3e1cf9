#include "coordinator/control/fleet_control.h"

#include <grpcpp/grpcpp.h>

#include <thread>
#include <utility>
#include <vector>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "behaviorlib/error_details.h"

namespace behaviorlib::coordinator {

absl::Status systemError(const grpc::Status& status, const Registry::Route& route) {
  if (status.ok()) return absl::OkStatus();
  absl::Status s = errors::fromGrpc(status);
  s = errors::rewrap(s, absl::StrCat("robot ", route.robot_id, ", system ", route.system, " at ",
                                     route.address, ": ", status.error_message()));
  s = errors::withMetadata(s, {{"robot", route.robot_id}, {"system", route.system}});
  // toGrpc gives every error an ErrorInfo: a system's error without a reason
  // of its own arrives as ERROR_REASON_UNSPECIFIED.
  const std::string reason = errors::reasonOf(s);
  if ((reason.empty() || reason == v1::ErrorReason_Name(v1::ERROR_REASON_UNSPECIFIED)) &&
      (status.error_code() == grpc::StatusCode::UNAVAILABLE ||
       status.error_code() == grpc::StatusCode::DEADLINE_EXCEEDED)) {
    s = errors::withReason(s, v1::SYSTEM_UNAVAILABLE);
  }
  return s;
}

namespace {

absl::Status fromSystem(const grpc::Status& status, const Registry::Route& route) {
  return systemError(status, route);
}

}  // namespace

// The plan's steps, routed to the robot's systems.
class FleetControl::StepActions final : public PlanActions {
 public:
  StepActions(FleetControl& fleet, std::string robot_id, std::string target, std::string request_id)
      : fleet_(fleet),
        robot_id_(std::move(robot_id)),
        target_(std::move(target)),
        request_id_(std::move(request_id)) {}

  absl::Status checkSituation(const std::string& behavior) override {
    Registry::Route route;
    if (auto s = fleet_.route(robot_id_, behavior, &route); !s.ok()) return s;
    // A refusal computed from lagging state (a lease released a moment
    // ago) is asked again by applyPlan (ApplyOptions::lag_timeout).
    return fleet_.callCheckSituation(route, behavior);
  }

  absl::StatusOr<std::string> activate(const std::string& behavior,
                                       const google::protobuf::Struct& parameters) override {
    Registry::Route route;
    if (auto s = fleet_.route(robot_id_, behavior, &route); !s.ok()) return s;
    // Requirements get a request id derived from the target's, so that a
    // retried plan (a resumed mission) does not start them twice either.
    const std::string request_id =
        request_id_.empty()
            ? ""
            : (behavior == target_ ? request_id_ : absl::StrCat(request_id_, "/", behavior));
    auto response = fleet_.callActivate(route, behavior, parameters, request_id);
    if (!response.ok()) return response.status();
    if (!response->replayed() &&
        !fleet_.awaitSeen(response->activation_id(), fleet_.options_.event_timeout)) {
      return absl::DeadlineExceededError(
          absl::StrCat(behavior, " was activated (", response->activation_id(),
                       ") but its activated event did not reach the coordinator within ",
                       fleet_.options_.event_timeout.count(), " ms"));
    }
    if (behavior == target_) {
      target_response_ = *response;
      target_system_ = route.system;
    }
    return response->activation_id();
  }

  // The plan runs under the robot's lock (activateBehavior).
  absl::Status deactivate(const std::string& behavior) override {
    Registry::Route route;
    if (auto s = fleet_.route(robot_id_, behavior, &route); !s.ok()) return s;
    return fleet_.deactivateLocked(route, robot_id_, behavior, "").status();
  }

  v1::ActivateResponse target_response_;
  std::string target_system_;

 private:
  FleetControl& fleet_;
  std::string robot_id_;
  std::string target_;
  std::string request_id_;
};

FleetControl::FleetControl(Registry& registry, FleetEventLog& log,
                           std::shared_ptr<const Catalog> catalog, FleetControlOptions options)
    : registry_(registry), log_(log), catalog_(std::move(catalog)), options_(std::move(options)) {
  if (!catalog_) catalog_ = std::make_shared<Catalog>();
  auto subscription = log_.subscribe({}, [this] { drainEvents(); });
  {
    absl::MutexLock lock(&index_mutex_);
    subscription_ = std::move(subscription);
  }
  drainEvents();  // the replay is queued without a wake (and wakes before now found none)
}

FleetControl::~FleetControl() {
  stop();
  subscription_->cancel();
}

void FleetControl::stop() {
  absl::MutexLock lock(&index_mutex_);
  stopped_ = true;  // wakes the awaits (absl re-checks their conditions)
}

void FleetControl::drainEvents() {
  absl::MutexLock lock(&index_mutex_);
  if (!subscription_) return;
  while (FleetEventPtr event = subscription_->pop()) {
    if (!event->has_behavior_event()) continue;
    const v1::BehaviorEvent& e = event->behavior_event();
    if (e.activation_id().empty()) continue;
    if (e.has_activated() || e.has_finished()) {
      rememberLocked(e.activation_id());
    }
    if (e.has_finished()) {
      finished_[e.activation_id()] = {e.finished().cause(), e.finished().message()};
    }
  }
}

void FleetControl::rememberLocked(const std::string& activation_id) {
  if (!seen_.insert(activation_id).second) return;
  seen_order_.push_back(activation_id);
  while (seen_order_.size() > options_.remembered_activations) {
    seen_.erase(seen_order_.front());
    finished_.erase(seen_order_.front());
    deactivated_.erase(seen_order_.front());
    seen_order_.pop_front();
  }
}

void FleetControl::noteDeactivated(const std::string& activation_id) {
  absl::MutexLock lock(&index_mutex_);
  rememberLocked(activation_id);
  deactivated_.insert(activation_id);
}

std::vector<SystemLink::BehaviorView> FleetControl::robotView(const std::string& robot_id) const {
  std::vector<SystemLink::BehaviorView> view = registry_.robotBehaviors(robot_id);
  absl::MutexLock lock(&index_mutex_);
  for (auto& b : view) {
    const bool running =
        b.state == v1::BEHAVIOR_STATE_ACTIVE || b.state == v1::BEHAVIOR_STATE_PAUSED;
    if (running &&
        (finished_.contains(b.activation_id) || deactivated_.contains(b.activation_id))) {
      b.state = v1::BEHAVIOR_STATE_INACTIVE;
    }
  }
  return view;
}

PlanRequest FleetControl::planningView(const std::string& robot_id) const {
  PlanRequest view;
  view.robot_id = robot_id;
  for (const auto& b : robotView(robot_id)) {
    if (!b.system_up) continue;
    view.available.insert(b.name);
    if (b.state == v1::BEHAVIOR_STATE_ACTIVE || b.state == v1::BEHAVIOR_STATE_PAUSED) {
      view.active.insert(b.name);
    }
  }
  return view;
}

void FleetControl::awaitIndexLocked(const std::function<bool()>& found,
                                    std::chrono::milliseconds timeout) {
  auto ready = [&]() ABSL_EXCLUSIVE_LOCKS_REQUIRED(index_mutex_) { return stopped_ || found(); };
  index_mutex_.AwaitWithTimeout(absl::Condition(&ready), absl::FromChrono(timeout));
}

bool FleetControl::awaitSeen(const std::string& activation_id, std::chrono::milliseconds timeout) {
  absl::MutexLock lock(&index_mutex_);
  auto seen = [&]() ABSL_EXCLUSIVE_LOCKS_REQUIRED(index_mutex_) {
    return seen_.contains(activation_id);
  };
  awaitIndexLocked(seen, timeout);
  return !stopped_ && seen();
}

bool FleetControl::awaitFinishedSeen(const std::string& activation_id,
                                     std::chrono::milliseconds timeout) {
  absl::MutexLock lock(&index_mutex_);
  auto finished = [&]() ABSL_EXCLUSIVE_LOCKS_REQUIRED(index_mutex_) {
    return finished_.contains(activation_id);
  };
  awaitIndexLocked(finished, timeout);
  return !stopped_ && finished();
}

std::optional<FinishedActivation> FleetControl::awaitFinished(const std::string& /*robot*/,
                                                              const std::string& activation_id,
                                                              std::chrono::milliseconds timeout) {
  absl::MutexLock lock(&index_mutex_);
  awaitIndexLocked([&]() ABSL_EXCLUSIVE_LOCKS_REQUIRED(
                       index_mutex_) { return finished_.contains(activation_id); },
                   timeout);
  auto it = finished_.find(activation_id);
  if (it == finished_.end()) return std::nullopt;
  return it->second;
}

absl::Mutex& FleetControl::robotLock(const std::string& robot_id) {
  absl::MutexLock lock(&locks_mutex_);
  auto& slot = robot_locks_[robot_id];
  if (!slot) slot = std::make_unique<absl::Mutex>();
  return *slot;
}

absl::Status FleetControl::route(const std::string& robot_id, const std::string& behavior,
                                 Registry::Route* out) const {
  {
    absl::MutexLock lock(&index_mutex_);
    if (stopped_) {
      return errors::withReason(absl::CancelledError("the coordinator is shutting down"),
                                v1::SHUTTING_DOWN);
    }
  }
  return errors::fromGrpc(registry_.route(robot_id, behavior, out));
}

absl::StatusOr<v1::ActivateResponse> FleetControl::callActivate(
    const Registry::Route& route, const std::string& behavior,
    const google::protobuf::Struct& parameters, const std::string& request_id) {
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + options_.call_timeout);
  v1::ActivateBehaviorRequest request;
  request.set_behavior(behavior);
  *request.mutable_parameters() = parameters;
  request.set_request_id(request_id);
  v1::ActivateResponse response;
  grpc::Status status = route.stub->ActivateBehavior(&context, request, &response);
  if (!status.ok()) return fromSystem(status, route);
  return response;
}

absl::StatusOr<v1::DeactivateResponse> FleetControl::callDeactivate(
    const Registry::Route& route, const std::string& behavior, const std::string& activation_id) {
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + options_.call_timeout);
  v1::DeactivateBehaviorRequest request;
  request.set_behavior(behavior);
  request.set_activation_id(activation_id);
  v1::DeactivateResponse response;
  grpc::Status status = route.stub->DeactivateBehavior(&context, request, &response);
  if (!status.ok()) return fromSystem(status, route);
  return response;
}

bool FleetControl::callStillActive(const Registry::Route& route, const std::string& behavior) {
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + options_.call_timeout);
  v1::CheckBehaviorActivationRequest request;
  request.set_behavior(behavior);
  v1::CheckActivationResponse response;
  // Unanswered: trust the view (the plan then refuses, as before).
  if (!route.stub->CheckBehaviorActivation(&context, request, &response).ok()) return true;
  return response.active();
}

absl::Status FleetControl::callCheckSituation(const Registry::Route& route,
                                              const std::string& behavior) {
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + options_.call_timeout);
  v1::CheckBehaviorSituationRequest request;
  request.set_behavior(behavior);
  v1::CheckSituationResponse response;
  grpc::Status status = route.stub->CheckBehaviorSituation(&context, request, &response);
  if (!status.ok()) return fromSystem(status, route);
  if (response.feasible()) return absl::OkStatus();
  std::string reasons;
  for (const auto& r : response.reasons())
    absl::StrAppend(&reasons, reasons.empty() ? "" : "; ", r);
  std::vector<std::string> codes;
  for (int code : response.reason_codes()) {
    codes.push_back(v1::SituationReason_IsValid(code)
                        ? v1::SituationReason_Name(static_cast<v1::SituationReason>(code))
                        : std::to_string(code));
  }
  errors::Metadata about = {
      {"robot", route.robot_id}, {"system", route.system}, {"behavior", behavior}};
  if (!codes.empty()) about.emplace_back("situation_reasons", absl::StrJoin(codes, ","));
  return errors::withReason(absl::FailedPreconditionError(absl::StrCat(
                                behavior, " cannot be activated now: ",
                                reasons.empty() ? "its situation check failed" : reasons)),
                            v1::SITUATION_NOT_SUITABLE, about);
}

std::map<std::string, std::string> FleetControl::activeBehaviors(
    const std::string& robot_id) const {
  std::map<std::string, std::string> active;
  for (const auto& b : robotView(robot_id)) {
    if (b.state == v1::BEHAVIOR_STATE_ACTIVE || b.state == v1::BEHAVIOR_STATE_PAUSED) {
      active[b.name] = b.activation_id;
    }
  }
  return active;
}

absl::StatusOr<FleetControl::ActivateResult> FleetControl::activateBehavior(
    const ActivateRequest& request) {
  Registry::Route target_route;
  if (auto s = route(request.robot_id, request.behavior, &target_route); !s.ok()) return s;
  ActivateResult result;
  result.system = target_route.system;

  absl::MutexLock robot_lock(&robotLock(request.robot_id));
  if (request.skip_plan) {
    result.plan = {request.robot_id, request.behavior, {}};
    result.plan.steps.push_back({StepKind::kActivate, request.behavior, request.parameters,
                                 "the target (the catalog's plan skipped)"});
    if (request.dry_run) return result;
    auto response =
        callActivate(target_route, request.behavior, request.parameters, request.request_id);
    if (!response.ok()) return response.status();
    if (!response->replayed()) awaitSeen(response->activation_id(), options_.event_timeout);
    result.activation = std::move(*response);
    return result;
  }

  PlanRequest plan_request = planningView(request.robot_id);
  plan_request.target = request.behavior;
  plan_request.parameters = request.parameters;
  // A retried request (same request id) for a target that is active already
  // goes to its system, which answers with the activation it remembers.
  if (!request.request_id.empty() && plan_request.active.contains(request.behavior)) {
    result.plan = {request.robot_id, request.behavior, {}};
    result.plan.steps.push_back({StepKind::kActivate, request.behavior, request.parameters,
                                 "the target (a retry of request " + request.request_id + ")"});
    if (request.dry_run) return result;
    auto response =
        callActivate(target_route, request.behavior, request.parameters, request.request_id);
    if (!response.ok()) return response.status();
    result.activation = std::move(*response);
    return result;
  }
  // The view follows the systems' event streams, which can lag (activations
  // made directly on a system, a loaded machine): before refusing the target
  // as already active, ask its system, which knows.
  if (plan_request.active.contains(request.behavior) &&
      !callStillActive(target_route, request.behavior)) {
    plan_request.active.erase(request.behavior);
  }
  auto plan = makePlan(*catalog_, plan_request);
  if (!plan.ok()) return plan.status();
  result.plan = std::move(*plan);
  if (request.dry_run) return result;
  StepActions actions(*this, request.robot_id, request.behavior, request.request_id);
  auto applied = applyPlan(result.plan, actions, options_.apply);
  if (!applied.ok()) return applied.status();
  result.activation = std::move(actions.target_response_);
  result.system = actions.target_system_;
  return result;
}

absl::StatusOr<v1::DeactivateResponse> FleetControl::deactivateBehavior(
    const std::string& robot_id, const std::string& behavior, const std::string& activation_id,
    std::string* system) {
  Registry::Route r;
  if (auto s = route(robot_id, behavior, &r); !s.ok()) return s;
  if (system != nullptr) *system = r.system;
  absl::MutexLock robot_lock(&robotLock(robot_id));
  return deactivateLocked(r, robot_id, behavior, activation_id);
}

absl::StatusOr<v1::DeactivateResponse> FleetControl::deactivateLocked(
    const Registry::Route& r, const std::string& robot_id, const std::string& behavior,
    const std::string& activation_id) {
  auto response = callDeactivate(r, behavior, activation_id);
  if (!response.ok()) {
    // Inactive already is what the caller wants.
    if (response.status().code() == absl::StatusCode::kFailedPrecondition &&
        activation_id.empty() && !activeBehaviors(robot_id).contains(behavior)) {
      return v1::DeactivateResponse();
    }
    return response.status();
  }
  if (!response->activation_id().empty()) {
    // Read-your-writes: from here on this activation is not active for the
    // coordinator, whether or not its finished event has arrived.
    noteDeactivated(response->activation_id());
    if (!response->already_finished()) {
      awaitFinishedSeen(response->activation_id(), options_.event_timeout);
    }
  }
  return response;
}

absl::StatusOr<std::string> FleetControl::activate(const std::string& robot,
                                                   const std::string& behavior,
                                                   const google::protobuf::Struct& parameters,
                                                   const std::string& request_id) {
  auto done = activateBehavior({robot, behavior, parameters, request_id, false, false});
  if (!done.ok()) return done.status();
  return done->activation.activation_id();
}

absl::Status FleetControl::deactivate(const std::string& robot, const std::string& behavior) {
  return deactivateBehavior(robot, behavior, "").status();
}

template <class Request, class Response>
absl::Status FleetControl::callLifecycle(const std::string& robot, const std::string& behavior,
                                         grpc::Status (v1::BehaviorSystem::Stub::*method)(
                                             grpc::ClientContext*, const Request&, Response*)) {
  Registry::Route r;
  if (auto s = route(robot, behavior, &r); !s.ok()) return s;
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + options_.call_timeout);
  Request request;
  request.set_behavior(behavior);
  Response response;
  grpc::Status status = ((*r.stub).*method)(&context, request, &response);
  return status.ok() ? absl::OkStatus() : fromSystem(status, r);
}

absl::Status FleetControl::pause(const std::string& robot, const std::string& behavior) {
  return callLifecycle(robot, behavior, &v1::BehaviorSystem::Stub::PauseBehavior);
}

absl::Status FleetControl::resume(const std::string& robot, const std::string& behavior) {
  return callLifecycle(robot, behavior, &v1::BehaviorSystem::Stub::ResumeBehavior);
}

}  // namespace behaviorlib::coordinator
