#include "simulator/service/flight_controller_service.h"

#include <google/protobuf/util/time_util.h>

#include "behaviorlib/error_details.h"
#include "behaviorlib/server_kit/access_policy.h"
#include "behaviorlib/server_kit/barrier_metadata.h"
#include "behaviorlib/server_kit/reactor_order.h"
#include "simulator/service/latest_writer.h"
#include "simulator/service/messages.h"

namespace behaviorlib::sim {
namespace {

// Runs a platform call and finishes the reactor with its outcome. `fill`
// copies a successful value into the response.
template <class F, class Fill>
grpc::ServerUnaryReactor* platformCall(grpc::CallbackServerContext* context, Simulation& simulation,
                                       const std::string& robot_id, F&& call, Fill&& fill) {
  auto* reactor = context->DefaultReactor();
  if (auto s = server_kit::checkRobotScope(*context, robot_id, "command the vehicle"); !s.ok()) {
    reactor->Finish(errors::toGrpc(s));
    return reactor;
  }
  auto outer = simulation.withPlatform(robot_id, std::forward<F>(call));
  if (!outer.ok()) {
    reactor->Finish(errors::toGrpc(outer.status()));
  } else if (!outer->ok()) {
    reactor->Finish(errors::toGrpc(outer->status()));
  } else {
    fill(**outer);
    reactor->Finish(grpc::Status::OK);
  }
  return reactor;
}

bool sameStatus(const v1::FlightStatus& a, const v1::FlightStatus& b) {
  return a.state() == b.state() && a.lease_holder() == b.lease_holder() &&
         a.failsafe_active() == b.failsafe_active() &&
         std::abs(a.battery_ratio() - b.battery_ratio()) < 0.01;
}

}  // namespace

// One StreamSetpoints stream: applies each setpoint; the first refusal ends it.
class SetpointReader final
    : public server_kit::Ordered<grpc::ServerReadReactor<v1::SetpointRequest>> {
 public:
  SetpointReader(FlightControllerService* service, const grpc::CallbackServerContext& context,
                 v1::StreamSetpointsResponse* response)
      : service_(service), scope_(server_kit::robotScopeOf(context)), response_(response) {
    // A follower's stream, whose setpoints the next step waits for.
    if (SetpointBarrier* barrier = service_->setpointBarrier(); barrier != nullptr) {
      const auto& metadata = context.client_metadata();
      if (auto it = metadata.find(server_kit::kSetpointStreamMetadataKey); it != metadata.end()) {
        std::string key(it->second.data(), it->second.size());
        if (barrier->opened(key)) {
          barrier_ = barrier;
          key_ = std::move(key);
        }
      }
    }
    StartRead(&request_);
  }
  void OnReadDone(bool ok) override {
    ordered();
    if (!ok) {  // the client finished sending
      Finish(grpc::Status::OK);
      return;
    }
    auto applied = service_->applySetpoint(request_, scope_);
    if (barrier_ != nullptr) barrier_->read(key_);
    if (!applied.ok()) {
      Finish(errors::toGrpc(applied.status()));
      return;
    }
    response_->set_accepted_count(response_->accepted_count() + 1);
    StartRead(&request_);
  }
  void OnDone() override {
    ordered();
    if (barrier_ != nullptr) barrier_->ended(key_);
    delete this;
  }

 private:
  FlightControllerService* service_;
  SetpointBarrier* barrier_ = nullptr;  // a keyed stream's
  std::string key_;
  const server_kit::RobotScope scope_;  // the caller's, resolved once
  v1::StreamSetpointsResponse* response_;
  v1::SetpointRequest request_;
};

FlightControllerService::FlightControllerService(Simulation& simulation) : simulation_(simulation) {
  simulation_.addStepListener([this](SimTime now, const std::vector<VehicleReport>& vehicles) {
    std::lock_guard lock(watchers_mutex_);
    for (const auto& report : vehicles) {
      const std::string& id = *report.robot_id;
      v1::FlightStatus status =
          flightStatusMessage(id, now, *report.platform, report.snapshot.battery_ratio);
      auto it = last_status_.find(id);
      if (it != last_status_.end() && sameStatus(it->second, status)) continue;
      last_status_[id] = status;
      v1::WatchFlightStateResponse message;
      *message.mutable_status() = status;
      for (auto* watcher : watchers_) {
        if (watcher->key() == id) watcher->offer(message);
      }
    }
  });
}

FlightControllerService::~FlightControllerService() = default;

void FlightControllerService::shutdown() {
  std::lock_guard lock(watchers_mutex_);
  shutting_down_ = true;
  for (auto* watcher : watchers_) {
    watcher->end(errors::grpcError(grpc::StatusCode::UNAVAILABLE, v1::SHUTTING_DOWN,
                                   "the simulator is shutting down"));
  }
}

void FlightControllerService::removeWatcher(FlightStatusWatcher* watcher) {
  std::lock_guard lock(watchers_mutex_);
  watchers_.erase(watcher);
}

grpc::ServerUnaryReactor* FlightControllerService::AcquireLease(
    grpc::CallbackServerContext* context, const v1::AcquireLeaseRequest* request,
    v1::AcquireLeaseResponse* response) {
  // Taking the vehicle from its holder is for the safety policy and the
  // behavior systems (LAND), not for any operator, under an access policy.
  if (request->preempt()) {
    const std::optional<server_kit::Caller> caller = server_kit::callerOf(*context);
    if (caller && caller->policy && caller->roles.count(server_kit::Role::kSafety) == 0 &&
        caller->roles.count(server_kit::Role::kSystem) == 0 &&
        caller->roles.count(server_kit::Role::kAdmin) == 0) {
      auto* reactor = context->DefaultReactor();
      reactor->Finish(
          errors::grpcError(grpc::StatusCode::PERMISSION_DENIED, v1::ROLE_REQUIRED,
                            "a preempting AcquireLease needs the role safety or system; '" +
                                caller->identity + "' has neither",
                            {{"role", "safety,system"}, {"identity", caller->identity}}));
      return reactor;
    }
  }
  const auto ttl = std::chrono::nanoseconds(
      google::protobuf::util::TimeUtil::DurationToNanoseconds(request->ttl()));
  return platformCall(
      context, simulation_, request->robot_id(),
      [&](VehiclePlatform& p, SimTime now) {
        return p.acquireLease(request->holder(), ttl, request->preempt(), now);
      },
      [&](const v1::AcquireLeaseResponse& r) { *response = r; });
}

grpc::ServerUnaryReactor* FlightControllerService::RenewLease(grpc::CallbackServerContext* context,
                                                              const v1::RenewLeaseRequest* request,
                                                              v1::RenewLeaseResponse* response) {
  return platformCall(
      context, simulation_, request->robot_id(),
      [&](VehiclePlatform& p, SimTime now) { return p.renewLease(request->lease_id(), now); },
      [&](const v1::RenewLeaseResponse& r) { *response = r; });
}

grpc::ServerUnaryReactor* FlightControllerService::ReleaseLease(
    grpc::CallbackServerContext* context, const v1::ReleaseLeaseRequest* request,
    v1::ReleaseLeaseResponse* /*response*/) {
  return platformCall(
      context, simulation_, request->robot_id(),
      [&](VehiclePlatform& p, SimTime now) -> absl::StatusOr<bool> {
        if (absl::Status s = p.releaseLease(request->lease_id(), now); !s.ok()) return s;
        return true;
      },
      [](bool) {});
}

grpc::ServerUnaryReactor* FlightControllerService::ExecuteFlightAction(
    grpc::CallbackServerContext* context, const v1::ExecuteFlightActionRequest* request,
    v1::ExecuteFlightActionResponse* response) {
  return platformCall(
      context, simulation_, request->robot_id(),
      [&](VehiclePlatform& p, SimTime now) {
        return p.executeAction(request->action(), request->lease_id(),
                               request->takeoff_altitude_m(), request->confirm(), now);
      },
      [&](v1::FlightState state) { response->set_state(state); });
}

absl::StatusOr<v1::FlightState> FlightControllerService::applySetpoint(
    const v1::SetpointRequest& request, const server_kit::RobotScope& scope) {
  if (auto s = scope.permits(request.robot_id(), "command the vehicle"); !s.ok()) return s;
  auto outer = simulation_.withPlatform(request.robot_id(), [&](VehiclePlatform& p, SimTime now) {
    return p.setpoint(request, now);
  });
  if (!outer.ok()) return outer.status();
  return *outer;
}

grpc::ServerUnaryReactor* FlightControllerService::SendSetpoint(
    grpc::CallbackServerContext* context, const v1::SetpointRequest* request,
    v1::SendSetpointResponse* response) {
  auto* reactor = context->DefaultReactor();
  auto applied = applySetpoint(*request, server_kit::robotScopeOf(*context));
  if (applied.ok()) response->set_state(*applied);
  reactor->Finish(errors::toGrpc(applied.status()));
  return reactor;
}

grpc::ServerReadReactor<v1::SetpointRequest>* FlightControllerService::StreamSetpoints(
    grpc::CallbackServerContext* context, v1::StreamSetpointsResponse* response) {
  return new SetpointReader(this, *context, response);
}

grpc::ServerWriteReactor<v1::WatchFlightStateResponse>* FlightControllerService::WatchFlightState(
    grpc::CallbackServerContext* /*context*/, const v1::WatchFlightStateRequest* request) {
  auto* watcher = new FlightStatusWatcher(request->robot_id(),
                                          [this](FlightStatusWatcher* w) { removeWatcher(w); });
  // Registered under the simulation's mutex, then the watchers' one (the
  // order the step listener uses), so that the first message is the current
  // status and no later change is missed.
  auto registered = simulation_.withPlatform(
      request->robot_id(), [&](VehiclePlatform& p, SimTime now) -> grpc::Status {
        std::lock_guard lock(watchers_mutex_);
        if (shutting_down_) {
          return errors::grpcError(grpc::StatusCode::UNAVAILABLE, v1::SHUTTING_DOWN,
                                   "the simulator is shutting down");
        }
        // Battery as of the last step; the rest from the platform now.
        auto cached = last_status_.find(request->robot_id());
        v1::WatchFlightStateResponse message;
        *message.mutable_status() = flightStatusMessage(
            request->robot_id(), now, p,
            cached != last_status_.end() ? cached->second.battery_ratio() : 1.0);
        watchers_.insert(watcher);
        watcher->offer(message);
        return grpc::Status::OK;
      });
  if (!registered.ok()) {
    watcher->end(errors::toGrpc(registered.status()));
  } else if (!registered->ok()) {
    watcher->end(*registered);
  }
  return watcher;
}

}  // namespace behaviorlib::sim
