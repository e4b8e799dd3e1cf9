// The coordinator's blocking calls and its mission, belief-watch, safety and
// vehicle-telemetry RPCs (the rest of CoordinatorService is in
// coordinator_service.cc).

#include <deque>
#include <limits>
#include <memory>
#include <thread>
#include <utility>

#include "absl/base/thread_annotations.h"
#include "absl/strings/str_format.h"
#include "absl/synchronization/mutex.h"
#include "behaviorlib/error_details.h"
#include "behaviorlib/server_kit/access_policy.h"
#include "behaviorlib/server_kit/pagination.h"
#include "behaviorlib/server_kit/reactor_order.h"
#include "coordinator/api/blocking_pool.h"
#include "coordinator/api/coordinator_service.h"
#include "coordinator/api/queued_stream.h"
#include "coordinator/belief/belief_store.h"
#include "coordinator/control/fleet_control.h"
#include "coordinator/control/mission_manager.h"
#include "coordinator/safety/safety.h"
#include "coordinator/telemetry/vehicle_telemetry.h"

namespace behaviorlib::coordinator {

namespace {

grpc::ServerUnaryReactor* finishWith(grpc::CallbackServerContext* context,
                                     const grpc::Status& status) {
  auto* reactor = context->DefaultReactor();
  reactor->Finish(status);
  return reactor;
}

// A feature this coordinator was started without; `feature` is its name in
// the error's metadata.
grpc::Status notServed(const std::string& feature, const std::string& what,
                       const std::string& flag) {
  return errors::grpcError(grpc::StatusCode::FAILED_PRECONDITION, v1::FEATURE_NOT_ENABLED,
                           "this coordinator does not serve " + what + " (" + flag + ")",
                           {{"feature", feature}});
}

grpc::Status shuttingDown(const std::string& message) {
  return errors::grpcError(grpc::StatusCode::UNAVAILABLE, v1::SHUTTING_DOWN, message);
}

bool missionEnded(const v1::MissionStatus& status) {
  return status.has_end_time() || status.state() == v1::MISSION_STATE_SUCCEEDED;
}

}  // namespace

template <class Stream>
bool CoordinatorService::endOnShutdown(uint64_t id,
                                       const std::shared_ptr<typename Stream::Core>& core,
                                       std::string message) {
  const bool added = addShutdownHook(id, [core, message = std::move(message)] {
    absl::MutexLock lock(&core->mutex);
    if (core->stream != nullptr) {
      auto* stream = static_cast<Stream*>(core->stream);
      stream->assertLocked();
      stream->endLocked(shuttingDown(message));
    }
  });
  if (!added) {
    absl::MutexLock lock(&core->mutex);
    auto* stream = static_cast<Stream*>(core->stream);
    stream->assertLocked();
    stream->endLocked(shuttingDown("the coordinator is shutting down"));
  }
  return added;
}

// WatchMission: the mission's status now, then after every change, until it
// ends.
class MissionStreamReactor final : public QueuedStream<v1::WatchMissionResponse> {
 public:
  MissionStreamReactor(CoordinatorService* service, const std::string& mission_id)
      : service_(service), hook_(service->newHookId()) {
    auto core = this->core();
    MissionManager* missions = service_->options_.missions;
    if (missions == nullptr) {
      absl::MutexLock lock(&core->mutex);
      endLocked(notServed("missions", "missions", "started without missions"));
      return;
    }
    auto token = missions->watch(mission_id, [core](const v1::MissionStatus& status) {
      absl::MutexLock lock(&core->mutex);
      if (core->stream == nullptr) return;
      v1::WatchMissionResponse message;
      *message.mutable_status() = status;
      auto* stream = static_cast<MissionStreamReactor*>(core->stream);
      stream->assertLocked();
      stream->pushLocked(std::move(message), missionEnded(status));
    });
    if (!token.ok()) {
      absl::MutexLock lock(&core->mutex);
      endLocked(errors::toGrpc(token.status()));
      return;
    }
    token_ = *token;
    service_->endOnShutdown<MissionStreamReactor>(
        hook_, core, "the coordinator is shutting down; watch the mission again");
  }

 private:
  void onDone() override {
    service_->removeShutdownHook(hook_);
    if (token_ != 0) service_->options_.missions->unwatch(token_);
  }

  CoordinatorService* service_;
  uint64_t hook_;
  uint64_t token_ = 0;
};

// WatchBeliefs: the changes after since_version, then new ones, from a
// thread of its own that waits on the belief store.
class BeliefStreamReactor final : public QueuedStream<v1::WatchBeliefsResponse> {
 public:
  BeliefStreamReactor(CoordinatorService* service, const v1::WatchBeliefsRequest& request)
      : service_(service), hook_(service->newHookId()) {
    auto core = this->core();
    BeliefStore* beliefs = service_->options_.beliefs;
    if (beliefs == nullptr) {
      absl::MutexLock lock(&core->mutex);
      endLocked(notServed("beliefs", "belief memory", "started without it"));
      return;
    }
    if (!service_->endOnShutdown<BeliefStreamReactor>(
            hook_, core, "the coordinator is shutting down; resume with since_version"))
      return;
    thread_ = std::thread([this, core, beliefs, prefix = request.prefix(),
                           since = request.since_version()]() mutable {
      // since_version 0: the current beliefs first (no tombstones).
      if (since == 0) {
        const uint64_t now = beliefs->version();
        absl::MutexLock lock(&core->mutex);
        if (core->stream == nullptr) return;
        assertLocked();  // core->stream is this stream
        for (auto& belief : beliefs->list(prefix)) {
          v1::WatchBeliefsResponse message;
          *message.mutable_belief() = std::move(belief);
          pushLocked(std::move(message), false);
        }
        since = now;
      }
      while (!stop_.load()) {
        auto changes = beliefs->waitForChanges(since, prefix, std::chrono::milliseconds(100));
        absl::MutexLock lock(&core->mutex);
        if (core->stream == nullptr) return;
        assertLocked();  // core->stream is this stream
        for (auto& belief : changes) {
          since = std::max<uint64_t>(since, belief.version());
          v1::WatchBeliefsResponse message;
          *message.mutable_belief() = std::move(belief);
          pushLocked(std::move(message), false);
        }
      }
    });
  }

 private:
  void onDone() override {
    stop_.store(true);
    if (thread_.joinable()) thread_.join();
    service_->removeShutdownHook(hook_);
  }

  CoordinatorService* service_;
  uint64_t hook_;
  std::atomic<bool> stop_{false};
  std::thread thread_;
};

// WatchVehicle: a vehicle's samples, from a broker subscription of its own
// (rate-limited by the broker); a slow reader gets the newest few.
class VehicleStreamReactor final : public QueuedStream<v1::WatchVehicleResponse> {
 public:
  // Unsent samples kept for a slow reader; older ones are dropped.
  static constexpr size_t kMaxQueued = 8;

  VehicleStreamReactor(CoordinatorService* service, const grpc::CallbackServerContext& context,
                       const v1::WatchVehicleRequest& request)
      : service_(service), hook_(service->newHookId()) {
    auto core = this->core();
    VehicleTelemetry* telemetry = service_->options_.telemetry;
    {
      absl::MutexLock lock(&core->mutex);
      boundQueueLocked(kMaxQueued);
    }
    if (telemetry == nullptr) {
      absl::MutexLock lock(&core->mutex);
      endLocked(notServed("telemetry", "the vehicles' telemetry", "started without --channel"));
      return;
    }
    if (!service_->endOnShutdown<VehicleStreamReactor>(
            hook_, core, "the coordinator is shutting down; watch the vehicle again"))
      return;
    auto watch =
        telemetry->watch(callerKey(context), request, [core](v1::WatchVehicleResponse message) {
          absl::MutexLock lock(&core->mutex);
          if (core->stream == nullptr) return;
          auto* stream = static_cast<VehicleStreamReactor*>(core->stream);
          stream->assertLocked();
          message.set_dropped_count(message.dropped_count() + stream->droppedLocked());
          stream->pushLocked(std::move(message), false);
        });
    if (!watch.ok()) {
      absl::MutexLock lock(&core->mutex);
      endLocked(errors::toGrpc(watch.status()));
      return;
    }
    watch_ = *std::move(watch);
  }

 private:
  // Whom the per-caller bound counts: the authenticated identity, else the
  // peer's address without its port.
  static std::string callerKey(const grpc::CallbackServerContext& context) {
    if (auto caller = server_kit::callerOf(context); caller && !caller->identity.empty()) {
      return caller->identity;
    }
    std::string peer = context.peer();
    if (const size_t colon = peer.rfind(':'); colon != std::string::npos && colon > 5) {
      peer.resize(colon);
    }
    return peer;
  }
  void onDone() override {
    watch_.reset();  // the subscription's reader is joined before the slot is freed
    service_->removeShutdownHook(hook_);
  }

  CoordinatorService* service_;
  uint64_t hook_;
  std::unique_ptr<VehicleTelemetry::Watch> watch_;
};

grpc::ServerWriteReactor<v1::WatchVehicleResponse>* CoordinatorService::WatchVehicle(
    grpc::CallbackServerContext* context, const v1::WatchVehicleRequest* request) {
  return new VehicleStreamReactor(this, *context, *request);
}

grpc::ServerUnaryReactor* CoordinatorService::GetVehicleSample(
    grpc::CallbackServerContext* context, const v1::GetVehicleSampleRequest* request,
    v1::GetVehicleSampleResponse* response) {
  VehicleTelemetry* telemetry = options_.telemetry;
  if (telemetry == nullptr) {
    return finishWith(
        context, notServed("telemetry", "the vehicles' telemetry", "started without --channel"));
  }
  // The broker read may wait (a gated topic): off the callback threads.
  return runBlocking(context, [telemetry, request, response] {
    auto sample = telemetry->latest(request->robot_id(), request->kind(), request->max_age_s());
    if (!sample.ok()) return errors::toGrpc(sample.status());
    *response->mutable_sample() = *std::move(sample);
    return grpc::Status::OK;
  });
}

grpc::ServerUnaryReactor* CoordinatorService::runBlocking(grpc::CallbackServerContext* context,
                                                          std::function<grpc::Status()> work) {
  auto* reactor = context->DefaultReactor();
  if (!pool_.post([reactor, work = std::move(work)] { reactor->Finish(work()); })) {
    reactor->Finish(shuttingDown("the coordinator is shutting down"));
  }
  return reactor;
}

grpc::ServerWriteReactor<v1::WatchBeliefsResponse>* CoordinatorService::WatchBeliefs(
    grpc::CallbackServerContext* /*context*/, const v1::WatchBeliefsRequest* request) {
  return new BeliefStreamReactor(this, *request);
}

// A caller bound to a robot controls only that robot's missions.
grpc::Status CoordinatorService::missionScopeRefusal(const grpc::CallbackServerContext& context,
                                                     const std::string& mission_id,
                                                     std::string_view what) const {
  const server_kit::RobotScope scope = server_kit::robotScopeOf(context);
  if (!scope.bound()) return grpc::Status::OK;
  auto status = options_.missions->get(mission_id);
  if (!status.ok()) return errors::toGrpc(status.status());
  return errors::toGrpc(scope.permits(status->robot_id(), what));
}

grpc::ServerUnaryReactor* CoordinatorService::StartMission(grpc::CallbackServerContext* context,
                                                           const v1::StartMissionRequest* request,
                                                           v1::StartMissionResponse* response) {
  if (options_.missions == nullptr)
    return finishWith(context, notServed("missions", "missions", "no missions"));
  if (auto s = server_kit::checkRobotScope(*context, request->robot_id(), "start missions");
      !s.ok())
    return finishWith(context, errors::toGrpc(s));
  // Checking the file against the registry and starting are quick; the
  // mission then runs on its own thread.
  auto started = options_.missions->start(*request);
  if (!started.ok()) return finishWith(context, errors::toGrpc(started.status()));
  *response->mutable_status() = std::move(*started);
  return finishWith(context, grpc::Status::OK);
}

grpc::ServerUnaryReactor* CoordinatorService::CheckMission(grpc::CallbackServerContext* context,
                                                           const v1::CheckMissionRequest* request,
                                                           v1::CheckMissionResponse* response) {
  if (options_.missions == nullptr)
    return finishWith(context, notServed("missions", "missions", "no missions"));
  // Parsing, the registry's behaviors and the catalog's plans: no call to
  // another process.
  auto checked = options_.missions->check(*request);
  if (!checked.ok()) return finishWith(context, errors::toGrpc(checked.status()));
  *response = std::move(*checked);
  return finishWith(context, grpc::Status::OK);
}

grpc::ServerUnaryReactor* CoordinatorService::GetMission(grpc::CallbackServerContext* context,
                                                         const v1::GetMissionRequest* request,
                                                         v1::GetMissionResponse* response) {
  if (options_.missions == nullptr)
    return finishWith(context, notServed("missions", "missions", "no missions"));
  auto status = options_.missions->get(request->mission_id());
  if (!status.ok()) return finishWith(context, errors::toGrpc(status.status()));
  *response->mutable_status() = std::move(*status);
  return finishWith(context, grpc::Status::OK);
}

grpc::ServerUnaryReactor* CoordinatorService::ListMissions(grpc::CallbackServerContext* context,
                                                           const v1::ListMissionsRequest* request,
                                                           v1::ListMissionsResponse* response) {
  if (options_.missions == nullptr)
    return finishWith(context, notServed("missions", "missions", "no missions"));
  for (auto& status : options_.missions->list()) *response->add_missions() = std::move(status);
  // Newest first: the key runs backwards in start time.
  return finishWith(context, server_kit::paginate<v1::MissionStatus>(
                                 response->mutable_missions(),
                                 [](const v1::MissionStatus& m) {
                                   return absl::StrFormat("%020d.%09d/%s",
                                                          std::numeric_limits<int64_t>::max() -
                                                              m.start_time().seconds(),
                                                          999999999 - m.start_time().nanos(),
                                                          m.mission_id());
                                 },
                                 *request, response->mutable_next_page_token()));
}

grpc::ServerWriteReactor<v1::WatchMissionResponse>* CoordinatorService::WatchMission(
    grpc::CallbackServerContext* /*context*/, const v1::WatchMissionRequest* request) {
  return new MissionStreamReactor(this, request->mission_id());
}

grpc::ServerUnaryReactor* CoordinatorService::PauseMission(grpc::CallbackServerContext* context,
                                                           const v1::MissionControlRequest* request,
                                                           v1::MissionControlResponse* response) {
  if (options_.missions == nullptr)
    return finishWith(context, notServed("missions", "missions", "no missions"));
  if (auto refused = missionScopeRefusal(*context, request->mission_id(), "pause missions");
      !refused.ok())
    return finishWith(context, refused);
  auto status = options_.missions->pause(request->mission_id());
  if (!status.ok()) return finishWith(context, errors::toGrpc(status.status()));
  *response->mutable_status() = std::move(*status);
  return finishWith(context, grpc::Status::OK);
}

grpc::ServerUnaryReactor* CoordinatorService::ResumeMission(
    grpc::CallbackServerContext* context, const v1::MissionControlRequest* request,
    v1::MissionControlResponse* response) {
  if (options_.missions == nullptr)
    return finishWith(context, notServed("missions", "missions", "no missions"));
  if (auto refused = missionScopeRefusal(*context, request->mission_id(), "resume missions");
      !refused.ok())
    return finishWith(context, refused);
  auto status = options_.missions->resume(request->mission_id());
  if (!status.ok()) return finishWith(context, errors::toGrpc(status.status()));
  *response->mutable_status() = std::move(*status);
  return finishWith(context, grpc::Status::OK);
}

grpc::ServerUnaryReactor* CoordinatorService::AbortMission(grpc::CallbackServerContext* context,
                                                           const v1::MissionControlRequest* request,
                                                           v1::MissionControlResponse* response) {
  if (options_.missions == nullptr)
    return finishWith(context, notServed("missions", "missions", "no missions"));
  if (auto refused = missionScopeRefusal(*context, request->mission_id(), "abort missions");
      !refused.ok())
    return finishWith(context, refused);
  auto status = options_.missions->abort(request->mission_id(), request->reason());
  if (!status.ok()) return finishWith(context, errors::toGrpc(status.status()));
  *response->mutable_status() = std::move(*status);
  return finishWith(context, grpc::Status::OK);
}

grpc::ServerUnaryReactor* CoordinatorService::EmergencyLand(grpc::CallbackServerContext* context,
                                                            const v1::SafetyActionRequest* request,
                                                            v1::SafetyActionResponse* response) {
  if (options_.safety == nullptr) {
    return finishWith(context,
                      notServed("safety", "safety actions", "start it with --flight-controller"));
  }
  return runBlocking(context, [this, request, response] {
    auto done = options_.safety->emergencyLand(request->robot_id(), request->reason());
    if (!done.ok()) return errors::toGrpc(done.status());
    response->set_message(*done);
    return grpc::Status::OK;
  });
}

grpc::ServerUnaryReactor* CoordinatorService::Kill(grpc::CallbackServerContext* context,
                                                   const v1::SafetyActionRequest* request,
                                                   v1::SafetyActionResponse* response) {
  if (options_.safety == nullptr) {
    return finishWith(context,
                      notServed("safety", "safety actions", "start it with --flight-controller"));
  }
  return runBlocking(context, [this, request, response] {
    auto done = options_.safety->kill(request->robot_id(), request->confirm(), request->reason());
    if (!done.ok()) return errors::toGrpc(done.status());
    response->set_message(*done);
    return grpc::Status::OK;
  });
}

}  // namespace behaviorlib::coordinator
