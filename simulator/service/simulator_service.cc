#include "simulator/service/simulator_service.h"

#include <google/protobuf/util/time_util.h>

#include <cmath>

#include "behaviorlib/error_details.h"
#include "behaviorlib/server_kit/reactor_order.h"
#include "simulator/service/messages.h"
#include "simulator/service/vehicle_models.h"

namespace behaviorlib::sim {
namespace {

using google::protobuf::util::TimeUtil;

grpc::ServerUnaryReactor* finish(grpc::CallbackServerContext* context, const grpc::Status& s) {
  auto* reactor = context->DefaultReactor();
  reactor->Finish(s);
  return reactor;
}

// INVALID_ARGUMENT naming the faulty request field.
grpc::Status invalidField(const std::string& field, const std::string& message) {
  return errors::toGrpc(errors::withFieldViolation(
      errors::withReason(absl::InvalidArgumentError(message), v1::INVALID_REQUEST), field,
      message));
}

grpc::Status shuttingDown() {
  return errors::grpcError(grpc::StatusCode::UNAVAILABLE, v1::SHUTTING_DOWN,
                           "the simulator is shutting down");
}

// For what the simulator does not do in its current mode, or was started
// without.
grpc::Status notNow(std::string feature, std::string message) {
  return errors::grpcError(grpc::StatusCode::FAILED_PRECONDITION, v1::FEATURE_NOT_ENABLED,
                           std::move(message), {{"feature", std::move(feature)}});
}

}  // namespace

absl::Status loadWorldInto(WorldControl& control, const std::string& world_arg, uint64_t seed,
                           WorldSource source, Simulation& simulation) {
  auto world = std::make_shared<world::World>();
  if (!world_arg.empty()) {
    auto loaded = loadWorldByName(world_arg, control.worlds_dir, source);
    if (!loaded.ok()) return loaded.status();
    *world = std::move(*loaded);
  }
  std::shared_ptr<const world::World> shared = world;
  simulation.resetVehicles(makeVehicles(*world, control.fallback_ids, seed), [&] {
    if (control.on_reset) control.on_reset(shared, seed);
  });
  // The old world may go now: no vehicle refers to it any more (the sensors
  // hold the world they use).
  control.world = std::move(shared);
  control.world_arg = world_arg;
  control.seed = seed;
  return absl::OkStatus();
}

SimulatorService::SimulatorService(Simulation& simulation, TimeControl& time, WorldControl& worlds,
                                   FaultInjector* faults)
    : simulation_(simulation), time_(time), worlds_(worlds), faults_(faults) {
  simulation_.addStepListener([this](SimTime now, const std::vector<VehicleReport>& vehicles) {
    std::lock_guard lock(watchers_mutex_);
    if (watchers_.empty()) return;
    const double t = std::chrono::duration<double>(now).count();
    for (auto& [watcher, watch] : watchers_) {
      if (t + 1e-9 < watch.next_s && watch.next_s - t <= watch.period_s) continue;
      watch.next_s = t + watch.period_s;
      for (const auto& report : vehicles) {
        if (!watcher->key().empty() && watcher->key() != *report.robot_id) continue;
        v1::WatchStateResponse message;
        *message.mutable_state() = vehicleStateMessage(*report.robot_id, now, report);
        watcher->offer(message);
      }
    }
  });
}

void SimulatorService::shutdown() {
  std::lock_guard lock(watchers_mutex_);
  shutting_down_ = true;
  for (auto& [watcher, watch] : watchers_) {
    watcher->end(shuttingDown());
  }
}

void SimulatorService::removeWatcher(StateWatcher* watcher) {
  std::lock_guard lock(watchers_mutex_);
  watchers_.erase(watcher);
}

grpc::ServerUnaryReactor* SimulatorService::Reset(grpc::CallbackServerContext* context,
                                                  const v1::ResetRequest* request,
                                                  v1::ResetResponse* response) {
  std::lock_guard lock(worlds_.mutex);
  // The current world came from the configuration; another is confined to
  // --worlds-dir.
  const bool same = request->world().empty();
  const std::string world = same ? worlds_.world_arg : request->world();
  const uint64_t seed = request->seed() != 0 ? request->seed() : worlds_.seed;
  if (absl::Status s =
          loadWorldInto(worlds_, world, seed,
                        same ? WorldSource::kConfiguration : WorldSource::kRequest, simulation_);
      !s.ok()) {
    return finish(context, errors::toGrpc(s));
  }
  for (const auto& id : simulation_.robotIds()) response->add_robot_ids(id);
  *response->mutable_time() = TimeUtil::NanosecondsToTimestamp(simulation_.now().count());
  return finish(context, grpc::Status::OK);
}

grpc::ServerUnaryReactor* SimulatorService::SetTimeScale(grpc::CallbackServerContext* context,
                                                         const v1::SetTimeScaleRequest* request,
                                                         v1::SetTimeScaleResponse* response) {
  if (time_.deterministic.load()) {
    return finish(context, notNow("wall_clock_mode",
                                  "the simulator runs in deterministic mode (--time-scale "
                                  "max): time advances under its followers' grants"));
  }
  if (!request->lock_step()) {
    const double scale = request->time_scale();
    if (!std::isfinite(scale) || scale < 0.1 || scale > 1000.0) {
      return finish(context,
                    invalidField("time_scale", "time_scale must be within [0.1, 1000], got " +
                                                   std::to_string(scale)));
    }
    time_.time_scale.store(scale);
  }
  time_.lock_step.store(request->lock_step());
  response->set_time_scale(time_.time_scale.load());
  response->set_lock_step(time_.lock_step.load());
  return finish(context, grpc::Status::OK);
}

grpc::ServerUnaryReactor* SimulatorService::Step(grpc::CallbackServerContext* context,
                                                 const v1::StepRequest* request,
                                                 v1::StepResponse* response) {
  if (time_.deterministic.load()) {
    return finish(context, notNow("wall_clock_mode",
                                  "the simulator steps itself in deterministic mode "
                                  "(--time-scale max)"));
  }
  if (!time_.lock_step.load()) {
    return finish(context, notNow("lock_step",
                                  "Step needs lock-step mode: call SetTimeScale with "
                                  "lock_step = true first"));
  }
  const int64_t ns = TimeUtil::DurationToNanoseconds(request->duration());
  if (ns <= 0 || ns > int64_t{3600} * 1000000000) {
    return finish(context, invalidField("duration", "duration must be within (0, 3600 s]"));
  }
  simulation_.advance(std::chrono::nanoseconds(ns));
  *response->mutable_time() = TimeUtil::NanosecondsToTimestamp(simulation_.now().count());
  return finish(context, grpc::Status::OK);
}

grpc::ServerBidiReactor<v1::FollowTimeRequest, v1::FollowTimeResponse>*
SimulatorService::FollowTime(grpc::CallbackServerContext* context) {
  if (grants_ != nullptr) return grants_->follow(server_kit::robotScopeOf(*context));
  class Refused final
      : public server_kit::Ordered<
            grpc::ServerBidiReactor<v1::FollowTimeRequest, v1::FollowTimeResponse>> {
   public:
    Refused() {
      Finish(notNow("deterministic_mode",
                    "FollowTime needs the deterministic mode (simulator --time-scale max)"));
    }
    void OnDone() override {
      ordered();
      delete this;
    }
  };
  (void)context;
  return new Refused();
}

grpc::ServerUnaryReactor* SimulatorService::InjectFailure(grpc::CallbackServerContext* context,
                                                          const v1::InjectFailureRequest* request,
                                                          v1::InjectFailureResponse* /*response*/) {
  if (faults_ == nullptr) {
    return finish(context, notNow("fault_injection",
                                  "fault injection is disabled; start the simulator with "
                                  "--enable-fault-injection"));
  }
  // Under the worlds' mutex: never half-way through a Reset.
  std::lock_guard lock(worlds_.mutex);
  return finish(context, errors::toGrpc(faults_->inject(*request)));
}

grpc::ServerWriteReactor<v1::WatchStateResponse>* SimulatorService::WatchState(
    grpc::CallbackServerContext* /*context*/, const v1::WatchStateRequest* request) {
  // One robot id per stream in this version (empty: all vehicles).
  const std::string key = request->robot_ids_size() == 1 ? request->robot_ids(0) : "";
  auto* watcher = new StateWatcher(key, [this](StateWatcher* w) { removeWatcher(w); });
  if (request->robot_ids_size() > 1) {
    watcher->end(invalidField("robot_ids", "name one robot id, or none for all vehicles"));
    return watcher;
  }
  if (!key.empty()) {
    if (auto s = simulation_.vehicleState(key); !s.ok()) {
      watcher->end(errors::toGrpc(
          errors::withDefaultReason(errors::rewrap(s.status(), absl::StatusCode::kNotFound,
                                                   std::string(s.status().message())),
                                    v1::UNKNOWN_VEHICLE, {{"robot", key}})));
      return watcher;
    }
  }
  const double rate = request->rate_hz() > 0 ? std::min(request->rate_hz(), 1000.0) : 50.0;
  // The current state first, also while time stands still (lock-step). Not
  // under watchers_mutex_: the step listener takes it with the simulation's
  // mutex held.
  simulation_.visitVehicles(key, [&](SimTime now, const VehicleReport& report) {
    v1::WatchStateResponse message;
    *message.mutable_state() = vehicleStateMessage(*report.robot_id, now, report);
    watcher->offer(message);
  });
  std::lock_guard lock(watchers_mutex_);
  if (shutting_down_) {
    watcher->end(shuttingDown());
    return watcher;
  }
  watchers_[watcher] = Watch{1.0 / rate};
  return watcher;
}

}  // namespace behaviorlib::sim
