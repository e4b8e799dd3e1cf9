#include "coordinator/api/coordinator_service.h"

#include <google/protobuf/io/coded_stream.h>
#include <google/protobuf/util/time_util.h>
#include <grpcpp/support/proto_buffer_reader.h>
#include <grpcpp/support/proto_buffer_writer.h>

#include <memory>
#include <utility>

#include "behaviorlib/error_details.h"
#include "behaviorlib/server_kit/access_policy.h"
#include "behaviorlib/server_kit/log_stream.h"
#include "behaviorlib/server_kit/pagination.h"
#include "behaviorlib/server_kit/reactor_order.h"
#include "behaviorlib/server_kit/transport_security.h"
#include "coordinator/belief/belief_store.h"
#include "coordinator/control/fleet_control.h"
#include "coordinator/registry/systems_config.h"

namespace behaviorlib::coordinator {

namespace {

grpc::ServerUnaryReactor* finishNow(grpc::CallbackServerContext* context,
                                    const grpc::Status& status) {
  auto* reactor = context->DefaultReactor();
  reactor->Finish(status);
  return reactor;
}

// INVALID_ARGUMENT naming the faulty request field.
grpc::Status invalidField(const std::string& field, const std::string& message) {
  return errors::toGrpc(errors::withFieldViolation(
      errors::withReason(absl::InvalidArgumentError(message), v1::INVALID_REQUEST), field,
      message));
}

grpc::Status missing(const std::string& field, const std::string& hint) {
  return invalidField(field, field + " is empty: " + hint);
}

// A refusal of checkSystemIdentity: the caller's identity names another
// system.
grpc::Status identityMismatch(const absl::Status& status, const std::string& robot_id,
                              const std::string& system) {
  return errors::toGrpc(errors::withDefaultReason(status, v1::IDENTITY_MISMATCH,
                                                  {{"robot", robot_id}, {"system", system}}));
}

// A client context for a call made on behalf of `server`: its cancellation
// and deadline carry over, and the call never waits longer than `limit`.
std::unique_ptr<grpc::ClientContext> childContext(grpc::CallbackServerContext* server,
                                                  std::chrono::milliseconds limit) {
  auto context = grpc::ClientContext::FromCallbackServerContext(*server);
  context->set_deadline(std::chrono::system_clock::now() + limit);
  return context;
}

// The hosting system's refusal, with the system named (its details kept).
grpc::Status fromSystem(const grpc::Status& status, const Registry::Route& route) {
  return errors::toGrpc(systemError(status, route));
}

// WatchFleetEventsRequest.max_events_per_message is capped here.
constexpr uint32_t kMaxEventsPerMessage = 1024;
// A batch stops before this many bytes of events (one event may be larger):
// clients receive at most 4 MiB a message by default.
constexpr size_t kMaxBatchBytes = 1 << 20;

// WatchFleetEventsResponse fields (coordinator.proto) written from the
// events' stored wire forms: `event` (2) holds one FleetEvent, `events` (3) a
// FleetEventBatch, whose `events` (1) repeats FleetEvent. Protobuf writes an
// embedded message as its tag (field number << 3 | 2, length-delimited), its
// size as a varint, then its bytes; written here with protobuf's
// CodedOutputStream, the result parses as the typed message.
constexpr uint32_t kLengthDelimited = 2;
constexpr uint32_t kResponseEventTag = (2 << 3) | kLengthDelimited;
constexpr uint32_t kResponseEventsTag = (3 << 3) | kLengthDelimited;
constexpr uint32_t kBatchEventTag = (1 << 3) | kLengthDelimited;

size_t embeddedSize(uint32_t tag, size_t size) {
  using google::protobuf::io::CodedOutputStream;
  return CodedOutputStream::VarintSize32(tag) +
         CodedOutputStream::VarintSize32(static_cast<uint32_t>(size)) + size;
}

uint8_t* writeEmbeddedHeader(uint32_t tag, size_t size, uint8_t* out) {
  using google::protobuf::io::CodedOutputStream;
  out = CodedOutputStream::WriteTagToArray(tag, out);
  return CodedOutputStream::WriteVarint32ToArray(static_cast<uint32_t>(size), out);
}

// One WatchEvents message carrying `records`: a FleetEventBatch, or the single
// `event` field when `batch` is false (then records has one element).
grpc::ByteBuffer fleetEventsMessage(const std::vector<FleetEventRecordPtr>& records, bool batch) {
  size_t inner = 0;
  if (batch) {
    for (const auto& record : records) inner += embeddedSize(kBatchEventTag, record->wire().size());
  } else {
    inner = records.front()->wire().size();
  }
  const uint32_t outer_tag = batch ? kResponseEventsTag : kResponseEventTag;
  grpc::Slice slice(embeddedSize(outer_tag, inner));
  uint8_t* out = const_cast<uint8_t*>(slice.begin());
  out = writeEmbeddedHeader(outer_tag, inner, out);
  for (const auto& record : records) {
    const std::string& wire = record->wire();
    if (batch) out = writeEmbeddedHeader(kBatchEventTag, wire.size(), out);
    out = google::protobuf::io::CodedOutputStream::WriteRawToArray(
        wire.data(), static_cast<int>(wire.size()), out);
  }
  return grpc::ByteBuffer(&slice, 1);
}

// A message serialized the usual way.
grpc::ByteBuffer serialized(const google::protobuf::Message& message) {
  grpc::ByteBuffer buffer;
  bool own_buffer = false;
  grpc::GenericSerialize<grpc::ProtoBufferWriter, google::protobuf::Message>(message, &buffer,
                                                                             &own_buffer);
  return buffer;
}

// A WatchEvents call refused at once.
class RefusedEventStream final
    : public server_kit::Ordered<grpc::ServerWriteReactor<grpc::ByteBuffer>> {
 public:
  explicit RefusedEventStream(const grpc::Status& status) { Finish(status); }
  void OnDone() override {
    ordered();
    delete this;
  }
};

// One lifecycle call forwarded to a behavior system.
template <class Request, class Response>
struct ForwardedCall {
  std::unique_ptr<grpc::ClientContext> context;
  Registry::Route route;
  Request request;
  Response response;
};

// Sends a forwarded call to its system with `start` (one of the stub's async
// methods) and finishes `reactor` with the system's reply, which `put` moves
// into the fleet response beside the robot and system that served it.
template <class Request, class Response, class FleetResponse, class Start, class Put>
grpc::ServerUnaryReactor* forward(std::unique_ptr<ForwardedCall<Request, Response>> call,
                                  grpc::ServerUnaryReactor* reactor, FleetResponse* response,
                                  Start start, Put put) {
  auto* raw = call.release();
  start(*raw->route.stub->async(), raw->context.get(), &raw->request, &raw->response,
        server_kit::orderedCallback([raw, reactor, response, put](grpc::Status status) {
          std::unique_ptr<ForwardedCall<Request, Response>> owned(raw);
          if (!status.ok()) {
            reactor->Finish(fromSystem(status, owned->route));
            return;
          }
          response->set_robot_id(owned->route.robot_id);
          response->set_system(owned->route.system);
          put(response, std::move(owned->response));
          reactor->Finish(grpc::Status::OK);
        }));
  return reactor;
}

// Routes a call on a robot's behavior to the system that hosts it: finishes
// at once with the routing error (unknown robot or behavior, system down),
// else forwards `request` with a deadline of `timeout` (see forward()).
template <class Response, class Request, class FleetResponse, class Start, class Put>
grpc::ServerUnaryReactor* routed(const Registry& registry, std::chrono::milliseconds timeout,
                                 grpc::CallbackServerContext* context, const std::string& robot,
                                 Request request, FleetResponse* response, Start start, Put put) {
  auto call = std::make_unique<ForwardedCall<Request, Response>>();
  if (auto s = registry.route(robot, request.behavior(), &call->route); !s.ok()) {
    return finishNow(context, s);
  }
  call->context = childContext(context, timeout);
  call->request = std::move(request);
  return forward(std::move(call), context->DefaultReactor(), response, start, put);
}

}  // namespace

// One WatchEvents stream (LogStreamWriter). Each event's wire form is
// serialized once and shared by every subscriber: messages are written as
// bytes.
class FleetStreamReactor final
    : public server_kit::LogStreamWriter<FleetSubscription, grpc::ByteBuffer> {
 public:
  FleetStreamReactor(CoordinatorService* service, const v1::WatchFleetEventsRequest& request)
      : LogStreamWriter("the coordinator"), service_(service) {
    FleetSubscribeOptions options;
    options.since_seq = request.since_seq();
    options.incarnation = request.incarnation();
    options.robot_ids.assign(request.robot_ids().begin(), request.robot_ids().end());
    options.behaviors.assign(request.behaviors().begin(), request.behaviors().end());
    max_batch_ = std::clamp<uint32_t>(request.max_events_per_message(), 1, kMaxEventsPerMessage);
    service_->metrics_.subscribers.Increment();
    begin(service_->log_.subscribe(options, [this] { wake(); }));
  }

 private:
  void startMessage(const FleetSubscription& subscription, grpc::ByteBuffer* out) override {
    v1::WatchFleetEventsResponse start;
    *start.mutable_start() = subscription.start();
    *out = serialized(start);
  }

  bool eventsMessage(FleetSubscription& subscription, grpc::ByteBuffer* out) override {
    const std::vector<FleetEventRecordPtr> records =
        subscription.popRecordsUpTo(max_batch_, kMaxBatchBytes);
    if (records.empty()) return false;
    *out = fleetEventsMessage(records, max_batch_ > 1);
    return true;
  }

  void streamDone() override {
    service_->metrics_.subscribers.Decrement();
    service_->removeStream(this);
  }

  CoordinatorService* service_;
  uint32_t max_batch_ = 1;
};

CoordinatorService::CoordinatorService(Registry& registry, FleetEventLog& log,
                                       CoordinatorMetrics& metrics, FleetControl& fleet,
                                       BlockingPool& pool, CoordinatorServiceOptions options)
    : registry_(registry),
      log_(log),
      metrics_(metrics),
      fleet_(fleet),
      pool_(pool),
      options_(options) {}

CoordinatorService::~CoordinatorService() = default;

void CoordinatorService::shutdownStreams() {
  // Reactors delete themselves only after removeStream(), which needs
  // streams_mutex_, so every stream in the set is alive while we hold it.
  std::map<uint64_t, std::function<void()>> hooks;
  {
    absl::MutexLock lock(&streams_mutex_);
    shutting_down_ = true;
    for (auto* stream : streams_) stream->shutdown();
    hooks.swap(shutdown_hooks_);
  }
  for (auto& [id, hook] : hooks) hook();
}

uint64_t CoordinatorService::newHookId() {
  absl::MutexLock lock(&streams_mutex_);
  return next_hook_++;
}

bool CoordinatorService::addShutdownHook(uint64_t id, std::function<void()> hook) {
  absl::MutexLock lock(&streams_mutex_);
  if (shutting_down_) return false;
  shutdown_hooks_[id] = std::move(hook);
  return true;
}

void CoordinatorService::removeShutdownHook(uint64_t id) {
  absl::MutexLock lock(&streams_mutex_);
  shutdown_hooks_.erase(id);
}

void CoordinatorService::removeStream(FleetStreamReactor* stream) {
  absl::MutexLock lock(&streams_mutex_);
  streams_.erase(stream);
}

grpc::ServerUnaryReactor* CoordinatorService::RegisterSystem(
    grpc::CallbackServerContext* context, const v1::RegisterSystemRequest* request,
    v1::RegisterSystemResponse* response) {
  if (request->robot_id().empty()) return finishNow(context, missing("robot_id", "name the robot"));
  if (request->system().empty()) {
    return finishNow(context, missing("system", "name the behavior system"));
  }
  if (request->incarnation().empty()) {
    return finishNow(context, missing("incarnation", "send the system's incarnation id"));
  }
  // Under an access policy, a system registers only as the system and robot
  // its certificate names: no one else can take its place.
  if (absl::Status s =
          server_kit::checkSystemIdentity(*context, request->robot_id(), request->system());
      !s.ok()) {
    return finishNow(context, identityMismatch(s, request->robot_id(), request->system()));
  }
  if (!isHostPort(request->address())) {
    return finishNow(context, invalidField("address", "address '" + request->address() +
                                                          "': expected host:port of the system's "
                                                          "gRPC server, reachable from the "
                                                          "coordinator"));
  }
  // Read the system's own description at the address it advertises: this
  // both checks that the coordinator can reach it and gives the schemas.
  struct Describe {
    std::shared_ptr<grpc::Channel> channel;
    std::unique_ptr<v1::BehaviorSystem::Stub> stub;
    std::unique_ptr<grpc::ClientContext> context;
    v1::ListBehaviorsRequest request;
    v1::ListBehaviorsResponse description;
  };
  auto* reactor = context->DefaultReactor();
  auto* call = new Describe();
  call->channel =
      behaviorlib::server_kit::makeChannel(request->address(), fastReconnectArguments());
  call->stub = v1::BehaviorSystem::NewStub(call->channel);
  call->context = childContext(context, options_.describe_timeout);
  // One page of the largest size: a system is described by one call here.
  call->request.set_page_size(kMaxBehaviorsPerSystem);
  call->stub->async()->ListBehaviors(
      call->context.get(), &call->request, &call->description,
      server_kit::orderedCallback([this, call, reactor, request, response](grpc::Status status) {
        std::unique_ptr<Describe> owned(call);
        const std::string who = "robot " + request->robot_id() + " system " + request->system();
        const errors::Metadata about = {{"robot", request->robot_id()},
                                        {"system", request->system()}};
        if (!status.ok()) {
          reactor->Finish(errors::grpcError(
              grpc::StatusCode::UNAVAILABLE, v1::SYSTEM_UNAVAILABLE,
              "cannot read the behaviors of " + who + " at " + request->address() +
                  " (BehaviorSystem.ListBehaviors: " + status.error_message() +
                  "); is that address reachable from the coordinator?",
              about));
          return;
        }
        const auto& d = owned->description;
        if (d.robot_id() != request->robot_id() || d.system() != request->system() ||
            d.incarnation() != request->incarnation()) {
          reactor->Finish(errors::grpcError(
              grpc::StatusCode::FAILED_PRECONDITION, v1::IDENTITY_MISMATCH,
              request->address() + " serves robot " + d.robot_id() + " system " + d.system() +
                  " incarnation " + d.incarnation() + ", not the registered " + who +
                  " incarnation " + request->incarnation(),
              about));
          return;
        }
        if (!d.next_page_token().empty()) {
          errors::Metadata limit = about;
          limit.emplace_back("limit", std::to_string(kMaxBehaviorsPerSystem));
          reactor->Finish(
              errors::grpcError(grpc::StatusCode::RESOURCE_EXHAUSTED, v1::LIMIT_EXCEEDED,
                                who + " hosts more than " + std::to_string(kMaxBehaviorsPerSystem) +
                                    " behaviors, the most a coordinator registers per system",
                                limit));
          return;
        }
        // The catalog's rules must fit what the system serves (a default
        // parameter the behavior does not have is the catalog's mistake,
        // named with its file and line).
        if (const Catalog* catalog = fleet_.catalog(); catalog != nullptr) {
          for (const auto& b : d.behaviors()) {
            if (auto s = catalog->checkRegistration(b, request->system()); !s.ok()) {
              reactor->Finish(errors::toGrpc(s));
              return;
            }
          }
        }
        const grpc::Status registered = registry_.registerSystem(*request, d);
        if (registered.ok()) {
          response->set_coordinator_incarnation(log_.incarnation());
          *response->mutable_heartbeat_interval() =
              google::protobuf::util::TimeUtil::MillisecondsToDuration(
                  options_.heartbeat_interval.count());
          for (const auto& b : d.behaviors()) response->add_behaviors(b.name());
        }
        reactor->Finish(registered);
      }));
  return reactor;
}

grpc::ServerUnaryReactor* CoordinatorService::Heartbeat(grpc::CallbackServerContext* context,
                                                        const v1::HeartbeatRequest* request,
                                                        v1::HeartbeatResponse* response) {
  if (absl::Status s =
          server_kit::checkSystemIdentity(*context, request->robot_id(), request->system());
      !s.ok()) {
    return finishNow(context, identityMismatch(s, request->robot_id(), request->system()));
  }
  const grpc::Status status = registry_.heartbeat(*request);
  if (status.ok()) response->set_coordinator_incarnation(log_.incarnation());
  return finishNow(context, status);
}

grpc::ServerUnaryReactor* CoordinatorService::UnregisterSystem(
    grpc::CallbackServerContext* context, const v1::UnregisterSystemRequest* request,
    v1::UnregisterSystemResponse* /*response*/) {
  if (absl::Status s =
          server_kit::checkSystemIdentity(*context, request->robot_id(), request->system());
      !s.ok()) {
    return finishNow(context, identityMismatch(s, request->robot_id(), request->system()));
  }
  return finishNow(context, registry_.unregister(*request));
}

grpc::ServerUnaryReactor* CoordinatorService::ListSystems(grpc::CallbackServerContext* context,
                                                          const v1::ListSystemsRequest* request,
                                                          v1::ListSystemsResponse* response) {
  registry_.listSystems(request->robot_id(), response);
  return finishNow(context, server_kit::paginate<v1::SystemInfo>(
                                response->mutable_systems(),
                                [](const v1::SystemInfo& s) {
                                  return absl::StrCat(s.robot_id(), "\x1f", s.system(), "\x1f",
                                                      s.address());
                                },
                                *request, response->mutable_next_page_token()));
}

grpc::ServerUnaryReactor* CoordinatorService::ListBehaviors(
    grpc::CallbackServerContext* context, const v1::ListFleetBehaviorsRequest* request,
    v1::ListFleetBehaviorsResponse* response) {
  registry_.listBehaviors(request->robot_id(), request->behavior(), response);
  return finishNow(context, server_kit::paginate<v1::FleetBehavior>(
                                response->mutable_behaviors(),
                                [](const v1::FleetBehavior& b) {
                                  return absl::StrCat(b.robot_id(), "\x1f", b.description().name(),
                                                      "\x1f", b.system());
                                },
                                *request, response->mutable_next_page_token()));
}

grpc::ServerWriteReactor<grpc::ByteBuffer>* CoordinatorService::WatchEvents(
    grpc::CallbackServerContext* /*context*/, const grpc::ByteBuffer* raw_request) {
  v1::WatchFleetEventsRequest request;
  grpc::ByteBuffer copy(*raw_request);  // shares the slices
  if (grpc::Status parsed =
          grpc::GenericDeserialize<grpc::ProtoBufferReader, v1::WatchFleetEventsRequest>(&copy,
                                                                                         &request);
      !parsed.ok()) {
    return new RefusedEventStream(errors::grpcError(
        grpc::StatusCode::INVALID_ARGUMENT, v1::INVALID_REQUEST,
        "WatchEvents: the request is not a WatchFleetEventsRequest: " + parsed.error_message()));
  }
  auto* stream = new FleetStreamReactor(this, request);
  absl::MutexLock lock(&streams_mutex_);
  streams_.insert(stream);
  if (shutting_down_) stream->shutdown();
  return stream;
}

grpc::ServerUnaryReactor* CoordinatorService::ActivateBehavior(
    grpc::CallbackServerContext* context, const v1::ActivateFleetBehaviorRequest* request,
    v1::ActivateFleetBehaviorResponse* response) {
  if (auto s = server_kit::checkRobotScope(*context, request->robot_id(), "activate behaviors");
      !s.ok())
    return finishNow(context, errors::toGrpc(s));
  return runBlocking(context, [this, request, response] {
    auto done =
        fleet_.activateBehavior({request->robot_id(), request->behavior(), request->parameters(),
                                 request->request_id(), request->dry_run(), request->skip_plan()});
    if (!done.ok()) return errors::toGrpc(done.status());
    response->set_robot_id(request->robot_id());
    response->set_system(done->system);
    *response->mutable_activation() = std::move(done->activation);
    planToProto(done->plan, response->mutable_plan());
    return grpc::Status::OK;
  });
}

grpc::ServerUnaryReactor* CoordinatorService::DeactivateBehavior(
    grpc::CallbackServerContext* context, const v1::DeactivateFleetBehaviorRequest* request,
    v1::DeactivateFleetBehaviorResponse* response) {
  if (auto s = server_kit::checkRobotScope(*context, request->robot_id(), "deactivate behaviors");
      !s.ok())
    return finishNow(context, errors::toGrpc(s));
  return runBlocking(context, [this, request, response] {
    std::string system;
    auto done = fleet_.deactivateBehavior(request->robot_id(), request->behavior(),
                                          request->activation_id(), &system);
    if (!done.ok()) return errors::toGrpc(done.status());
    response->set_robot_id(request->robot_id());
    response->set_system(system);
    *response->mutable_result() = std::move(*done);
    return grpc::Status::OK;
  });
}

grpc::ServerUnaryReactor* CoordinatorService::CheckBehaviorSituation(
    grpc::CallbackServerContext* context, const v1::CheckFleetBehaviorSituationRequest* request,
    v1::CheckFleetBehaviorSituationResponse* response) {
  v1::CheckBehaviorSituationRequest forwarded;
  forwarded.set_behavior(request->behavior());
  return routed<v1::CheckSituationResponse>(
      registry_, options_.default_call_timeout, context, request->robot_id(), std::move(forwarded),
      response, [](auto& async, auto... args) { async.CheckBehaviorSituation(args...); },
      [](auto* r, auto&& reply) { *r->mutable_situation() = std::move(reply); });
}

grpc::ServerUnaryReactor* CoordinatorService::CheckFleetBehaviorActivation(
    grpc::CallbackServerContext* context, const v1::CheckFleetBehaviorActivationRequest* request,
    v1::CheckFleetBehaviorActivationResponse* response) {
  v1::CheckBehaviorActivationRequest forwarded;
  forwarded.set_behavior(request->behavior());
  return routed<v1::CheckActivationResponse>(
      registry_, options_.default_call_timeout, context, request->robot_id(), std::move(forwarded),
      response, [](auto& async, auto... args) { async.CheckBehaviorActivation(args...); },
      [](auto* r, auto&& reply) { *r->mutable_activation() = std::move(reply); });
}

grpc::ServerUnaryReactor* CoordinatorService::PauseFleetBehavior(
    grpc::CallbackServerContext* context, const v1::PauseFleetBehaviorRequest* request,
    v1::PauseFleetBehaviorResponse* response) {
  if (auto s = server_kit::checkRobotScope(*context, request->robot_id(), "pause behaviors");
      !s.ok())
    return finishNow(context, errors::toGrpc(s));
  v1::PauseBehaviorRequest forwarded;
  forwarded.set_behavior(request->behavior());
  forwarded.set_activation_id(request->activation_id());
  return routed<v1::PauseResponse>(
      registry_, options_.default_call_timeout, context, request->robot_id(), std::move(forwarded),
      response, [](auto& async, auto... args) { async.PauseBehavior(args...); },
      [](auto* r, auto&& reply) { *r->mutable_result() = std::move(reply); });
}

grpc::ServerUnaryReactor* CoordinatorService::ResumeFleetBehavior(
    grpc::CallbackServerContext* context, const v1::ResumeFleetBehaviorRequest* request,
    v1::ResumeFleetBehaviorResponse* response) {
  if (auto s = server_kit::checkRobotScope(*context, request->robot_id(), "resume behaviors");
      !s.ok())
    return finishNow(context, errors::toGrpc(s));
  v1::ResumeBehaviorRequest forwarded;
  forwarded.set_behavior(request->behavior());
  forwarded.set_activation_id(request->activation_id());
  return routed<v1::ResumeResponse>(
      registry_, options_.default_call_timeout, context, request->robot_id(), std::move(forwarded),
      response, [](auto& async, auto... args) { async.ResumeBehavior(args...); },
      [](auto* r, auto&& reply) { *r->mutable_result() = std::move(reply); });
}

grpc::ServerUnaryReactor* CoordinatorService::ModifyFleetBehavior(
    grpc::CallbackServerContext* context, const v1::ModifyFleetBehaviorRequest* request,
    v1::ModifyFleetBehaviorResponse* response) {
  if (auto s = server_kit::checkRobotScope(*context, request->robot_id(), "modify behaviors");
      !s.ok())
    return finishNow(context, errors::toGrpc(s));
  v1::ModifyBehaviorRequest forwarded;
  forwarded.set_behavior(request->behavior());
  forwarded.set_activation_id(request->activation_id());
  *forwarded.mutable_parameters() = request->parameters();
  return routed<v1::ModifyResponse>(
      registry_, options_.default_call_timeout, context, request->robot_id(), std::move(forwarded),
      response, [](auto& async, auto... args) { async.ModifyBehavior(args...); },
      [](auto* r, auto&& reply) { *r->mutable_result() = std::move(reply); });
}

}  // namespace behaviorlib::coordinator

// ---- Belief memory -----------------------------------------------------------

namespace behaviorlib::coordinator {
namespace {

// Who the caller of a belief call is, as its certificate or token says;
// empty for a plaintext call.
std::string authenticatedWriter(const grpc::ServerContextBase& context) {
  const std::optional<server_kit::Caller> caller = server_kit::callerOf(context);
  return caller ? caller->identity : std::string();
}

// A refusal of the belief store, with its reason: a key that is not one,
// a cap reached, a belief that is not there.
grpc::Status beliefError(const absl::Status& status, const std::string& key) {
  v1::ErrorReason reason = v1::ERROR_REASON_UNSPECIFIED;
  switch (status.code()) {
    case absl::StatusCode::kInvalidArgument:
      reason = v1::INVALID_REQUEST;
      break;
    case absl::StatusCode::kResourceExhausted:
      reason = v1::LIMIT_EXCEEDED;
      break;
    case absl::StatusCode::kNotFound:
      reason = v1::BELIEF_NOT_FOUND;
      break;
    default:
      break;
  }
  return errors::toGrpc(errors::withDefaultReason(status, reason, {{"key", key}}));
}

grpc::Status noBeliefs() {
  return errors::grpcError(grpc::StatusCode::FAILED_PRECONDITION, v1::FEATURE_NOT_ENABLED,
                           "this coordinator keeps no belief memory", {{"feature", "beliefs"}});
}

}  // namespace

grpc::ServerUnaryReactor* CoordinatorService::WriteBelief(grpc::CallbackServerContext* context,
                                                          const v1::WriteBeliefRequest* request,
                                                          v1::WriteBeliefResponse* response) {
  if (options_.beliefs == nullptr) return finishNow(context, noBeliefs());
  if (request->writer().empty()) {
    return finishNow(context, missing("writer", "say who writes the belief (\"operator\", ...)"));
  }
  auto written = options_.beliefs->write(request->key(), request->value(), request->writer(),
                                         request->type(), authenticatedWriter(*context));
  if (!written.ok()) return finishNow(context, beliefError(written.status(), request->key()));
  *response->mutable_belief() = *written;
  return finishNow(context, grpc::Status::OK);
}

grpc::ServerUnaryReactor* CoordinatorService::ReadBelief(grpc::CallbackServerContext* context,
                                                         const v1::ReadBeliefRequest* request,
                                                         v1::ReadBeliefResponse* response) {
  if (options_.beliefs == nullptr) return finishNow(context, noBeliefs());
  auto belief = options_.beliefs->get(request->key());
  if (!belief) {
    return finishNow(context, errors::grpcError(grpc::StatusCode::NOT_FOUND, v1::BELIEF_NOT_FOUND,
                                                "no belief '" + request->key() + "' in memory",
                                                {{"key", request->key()}}));
  }
  *response->mutable_belief() = *belief;
  return finishNow(context, grpc::Status::OK);
}

grpc::ServerUnaryReactor* CoordinatorService::ListBeliefs(grpc::CallbackServerContext* context,
                                                          const v1::ListBeliefsRequest* request,
                                                          v1::ListBeliefsResponse* response) {
  if (options_.beliefs == nullptr) return finishNow(context, noBeliefs());
  for (auto& belief : options_.beliefs->list(request->prefix())) {
    *response->add_beliefs() = std::move(belief);
  }
  return finishNow(context,
                   server_kit::paginate<v1::Belief>(
                       response->mutable_beliefs(), [](const v1::Belief& b) { return b.key(); },
                       *request, response->mutable_next_page_token()));
}

grpc::ServerUnaryReactor* CoordinatorService::DeleteBelief(grpc::CallbackServerContext* context,
                                                           const v1::DeleteBeliefRequest* request,
                                                           v1::DeleteBeliefResponse* /*response*/) {
  if (options_.beliefs == nullptr) return finishNow(context, noBeliefs());
  if (request->writer().empty()) {
    return finishNow(context, missing("writer", "say who deletes the belief"));
  }
  absl::Status erased =
      options_.beliefs->erase(request->key(), request->writer(), authenticatedWriter(*context));
  if (!erased.ok()) return finishNow(context, beliefError(erased, request->key()));
  return finishNow(context, grpc::Status::OK);
}

}  // namespace behaviorlib::coordinator
