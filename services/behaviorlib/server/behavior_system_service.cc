#include "behaviorlib/server/behavior_system_service.h"

#include <google/protobuf/descriptor.h>
#include <google/protobuf/message.h>
#include <google/protobuf/util/time_util.h>

#include "behaviorlib/documentation.h"
#include "behaviorlib/error_details.h"
#include "behaviorlib/parameters.h"
#include "behaviorlib/server_kit/log_stream.h"
#include "behaviorlib/server_kit/pagination.h"
#include "behaviorlib/v1/options.pb.h"

namespace behaviorlib::server {

namespace {
// WatchEventsRequest.max_events_per_message is capped here.
constexpr uint32_t kMaxEventsPerMessage = 1024;
}  // namespace

// One WatchEvents stream (LogStreamWriter): the start message, then the
// subscription's events, one or a batch per message.
class EventStreamReactor final
    : public server_kit::LogStreamWriter<EventSubscription, v1::WatchEventsResponse> {
 public:
  EventStreamReactor(BehaviorSystemService* service, const v1::WatchEventsRequest& request)
      : LogStreamWriter("the behavior system"), service_(service) {
    SubscribeOptions options;
    options.since_seq = request.since_seq();
    options.incarnation = request.incarnation();
    options.behaviors.assign(request.behaviors().begin(), request.behaviors().end());
    max_batch_ = std::min<uint32_t>(request.max_events_per_message(), kMaxEventsPerMessage);
    begin(service_->host_.events().subscribe(options, [this] { wake(); }));
  }

 private:
  void startMessage(const EventSubscription& subscription, v1::WatchEventsResponse* out) override {
    *out->mutable_start() = subscription.start();
  }

  bool eventsMessage(EventSubscription& subscription, v1::WatchEventsResponse* out) override {
    if (max_batch_ > 1) {
      const std::vector<EventPtr> events = subscription.popUpTo(max_batch_);
      if (events.empty()) return false;
      auto* batch = out->mutable_events();
      batch->mutable_events()->Clear();
      for (const EventPtr& event : events) *batch->add_events() = *event;
      return true;
    }
    EventPtr event = subscription.pop();
    if (!event) return false;
    *out->mutable_event() = *event;
    return true;
  }

  void streamDone() override { service_->removeStream(this); }

  BehaviorSystemService* service_;
  uint32_t max_batch_ = 1;
};

BehaviorSystemService::BehaviorSystemService(BehaviorHost& host, const AcceptGate& gate,
                                             std::map<std::string, std::string> typed_services)
    : host_(host), gate_(gate), typed_services_(std::move(typed_services)) {}

BehaviorSystemService::~BehaviorSystemService() {
  // The server's Shutdown has waited for every stream's OnDone, so none is
  // left. Taking the lock orders the last removeStream() before the set is
  // destroyed for ThreadSanitizer too, which cannot see the order gRPC keeps
  // inside libgrpc++.
  absl::MutexLock lock(&streams_mutex_);
}

void BehaviorSystemService::shutdownStreams() {
  // Reactors delete themselves only after removeStream(), which needs
  // streams_mutex_, so every stream in the set is alive while we hold it.
  absl::MutexLock lock(&streams_mutex_);
  shutting_down_ = true;
  for (auto* stream : streams_) stream->shutdown();
}

void BehaviorSystemService::removeStream(EventStreamReactor* stream) {
  absl::MutexLock lock(&streams_mutex_);
  streams_.erase(stream);
}

BehaviorExecutionManager* BehaviorSystemService::lookup(const std::string& name,
                                                        grpc::Status* status) const {
  if (auto* behavior = host_.find(name)) return behavior;
  std::string known;
  for (const auto& b : host_.behaviors()) known += (known.empty() ? "" : ", ") + b->name();
  *status = errors::grpcError(
      grpc::StatusCode::NOT_FOUND, v1::UNKNOWN_BEHAVIOR,
      "unknown behavior '" + name + "'; " + host_.system() + " hosts: " + known,
      {{"robot", host_.robotId()}, {"system", host_.system()}, {"behavior", name}});
  return nullptr;
}

std::unique_ptr<google::protobuf::Message> BehaviorSystemService::fromStruct(
    const BehaviorExecutionManager& behavior, const google::protobuf::Struct& in,
    grpc::Status* status) const {
  const auto* prototype = google::protobuf::MessageFactory::generated_factory()->GetPrototype(
      &behavior.parametersType());
  std::unique_ptr<google::protobuf::Message> message(prototype->New());
  if (absl::Status s = params::fromStruct(in, message.get()); !s.ok()) {
    *status = errors::toGrpc(s);
    return nullptr;
  }
  return message;
}

grpc::ServerUnaryReactor* BehaviorSystemService::ListBehaviors(
    grpc::CallbackServerContext* context, const v1::ListBehaviorsRequest* request,
    v1::ListBehaviorsResponse* response) {
  // A bad page request costs no description.
  if (grpc::Status s = server_kit::paginate<v1::BehaviorDescription>(
          response->mutable_behaviors(), [](const auto& d) { return d.name(); }, *request,
          response->mutable_next_page_token());
      !s.ok()) {
    return finishNow(context, s);
  }
  response->set_robot_id(host_.robotId());
  response->set_system(host_.system());
  response->set_incarnation(host_.events().incarnation());
  const auto* pool = google::protobuf::DescriptorPool::generated_pool();
  for (const auto& behavior : host_.behaviors()) {
    auto* d = response->add_behaviors();
    d->set_name(behavior->name());
    d->set_parameters_type(behavior->parametersType().full_name());
    if (auto it = typed_services_.find(behavior->name()); it != typed_services_.end()) {
      d->set_service(it->second);
      if (const auto* service = pool->FindServiceByName(it->second)) {
        const auto& info = service->options().GetExtension(v1::behavior);
        d->set_description(info.description().empty() ? leadingComment(it->second)
                                                      : info.description());
        d->set_kind(info.kind());
      }
    }
    params::describe(behavior->parametersType(), d->mutable_parameters());
    *d->mutable_maximum_execution_time() = google::protobuf::util::TimeUtil::NanosecondsToDuration(
        behavior->options().maximum_execution_time.count());
    d->set_frequency_hz(behavior->options().frequency_hz);
    d->set_state(behavior->state());
  }
  return finishNow(context, server_kit::paginate<v1::BehaviorDescription>(
                                response->mutable_behaviors(),
                                [](const v1::BehaviorDescription& d) { return d.name(); }, *request,
                                response->mutable_next_page_token()));
}

grpc::ServerWriteReactor<v1::WatchEventsResponse>* BehaviorSystemService::WatchEvents(
    grpc::CallbackServerContext* /*context*/, const v1::WatchEventsRequest* request) {
  auto* stream = new EventStreamReactor(this, *request);
  absl::MutexLock lock(&streams_mutex_);
  streams_.insert(stream);
  if (shutting_down_) stream->shutdown();
  return stream;
}

grpc::ServerUnaryReactor* BehaviorSystemService::ActivateBehavior(
    grpc::CallbackServerContext* context, const v1::ActivateBehaviorRequest* request,
    v1::ActivateResponse* response) {
  grpc::Status status;
  auto* behavior = lookup(request->behavior(), &status);
  if (!behavior) return finishNow(context, status);
  auto parameters = fromStruct(*behavior, request->parameters(), &status);
  if (!parameters) return finishNow(context, status);
  return activateCall(context, gate_, *behavior, std::move(parameters), request->request_id(),
                      response);
}

grpc::ServerUnaryReactor* BehaviorSystemService::DeactivateBehavior(
    grpc::CallbackServerContext* context, const v1::DeactivateBehaviorRequest* request,
    v1::DeactivateResponse* response) {
  grpc::Status status;
  auto* behavior = lookup(request->behavior(), &status);
  if (!behavior) return finishNow(context, status);
  return deactivateCall(context, gate_, *behavior, request->activation_id(), response);
}

grpc::ServerUnaryReactor* BehaviorSystemService::CheckBehaviorActivation(
    grpc::CallbackServerContext* context, const v1::CheckBehaviorActivationRequest* request,
    v1::CheckActivationResponse* response) {
  grpc::Status status;
  auto* behavior = lookup(request->behavior(), &status);
  if (!behavior) return finishNow(context, status);
  return checkActivationCall(context, *behavior, response);
}

grpc::ServerUnaryReactor* BehaviorSystemService::CheckBehaviorSituation(
    grpc::CallbackServerContext* context, const v1::CheckBehaviorSituationRequest* request,
    v1::CheckSituationResponse* response) {
  grpc::Status status;
  auto* behavior = lookup(request->behavior(), &status);
  if (!behavior) return finishNow(context, status);
  return checkSituationCall(context, gate_, *behavior, response);
}

grpc::ServerUnaryReactor* BehaviorSystemService::PauseBehavior(
    grpc::CallbackServerContext* context, const v1::PauseBehaviorRequest* request,
    v1::PauseResponse* response) {
  grpc::Status status;
  auto* behavior = lookup(request->behavior(), &status);
  if (!behavior) return finishNow(context, status);
  return pauseCall(context, gate_, *behavior, request->activation_id(), response);
}

grpc::ServerUnaryReactor* BehaviorSystemService::ResumeBehavior(
    grpc::CallbackServerContext* context, const v1::ResumeBehaviorRequest* request,
    v1::ResumeResponse* response) {
  grpc::Status status;
  auto* behavior = lookup(request->behavior(), &status);
  if (!behavior) return finishNow(context, status);
  return resumeCall(context, gate_, *behavior, request->activation_id(), response);
}

grpc::ServerUnaryReactor* BehaviorSystemService::ModifyBehavior(
    grpc::CallbackServerContext* context, const v1::ModifyBehaviorRequest* request,
    v1::ModifyResponse* response) {
  grpc::Status status;
  auto* behavior = lookup(request->behavior(), &status);
  if (!behavior) return finishNow(context, status);
  auto update = fromStruct(*behavior, request->parameters(), &status);
  if (!update) return finishNow(context, status);
  return modifyCall(context, gate_, *behavior, request->activation_id(), std::move(update),
                    response);
}

}  // namespace behaviorlib::server
