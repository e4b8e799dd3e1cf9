#include "behaviorlib/console/gateway.h"

#include <google/protobuf/descriptor.pb.h>
#include <google/protobuf/descriptor_database.h>
#include <google/protobuf/struct.pb.h>
#include <google/protobuf/util/json_util.h>
#include <google/protobuf/util/type_resolver.h>
#include <google/protobuf/util/type_resolver_util.h>
#include <httplib.h>

#include <algorithm>
#include <cstdio>
#include <functional>
#include <set>
#include <utility>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/time/time.h"
#include "behaviorlib/embedded_descriptors.h"
#include "behaviorlib/error_details.h"
#include "google/rpc/status.pb.h"

namespace behaviorlib::console {

namespace {

namespace pbu = google::protobuf::util;

constexpr char kTypeUrlPrefix[] = "type.googleapis.com";

// Messages to JSON through the descriptors of every behaviorlib proto and
// its imports (embedded::descriptorSet()), not the process's generated pool:
// a channel sample's Any may hold any of our types, linked in or not.
class JsonPrinter {
 public:
  JsonPrinter() : pool_(&database_) {
    google::protobuf::FileDescriptorSet set;
    const std::string_view bytes = embedded::descriptorSet();
    if (set.ParseFromArray(bytes.data(), static_cast<int>(bytes.size()))) {
      for (const auto& file : set.file()) database_.Add(file);
    }
    resolver_.reset(pbu::NewTypeResolverForDescriptorPool(kTypeUrlPrefix, &pool_));
    options_.preserve_proto_field_names = true;
    options_.always_print_primitive_fields = true;
  }

  std::string print(const google::protobuf::Message& message) const {
    std::string out;
    const auto status = pbu::BinaryToJsonString(
        resolver_.get(), absl::StrCat(kTypeUrlPrefix, "/", message.GetDescriptor()->full_name()),
        message.SerializeAsString(), &out, options_);
    if (!status.ok()) {
      google::protobuf::Struct error;
      (*error.mutable_fields())["json_error"].set_string_value(status.ToString());
      pbu::MessageToJsonString(error, &out);
    }
    return out;
  }

 private:
  google::protobuf::SimpleDescriptorDatabase database_;
  google::protobuf::DescriptorPool pool_;
  std::unique_ptr<pbu::TypeResolver> resolver_;
  pbu::JsonPrintOptions options_;
};

std::string toJson(const google::protobuf::Message& message) {
  static const JsonPrinter printer;
  return printer.print(message);
}

// The HTTP status of a gRPC code, as google.api's HTTP mapping gives it.
int httpStatus(grpc::StatusCode code) {
  switch (code) {
    case grpc::StatusCode::OK:
      return 200;
    case grpc::StatusCode::INVALID_ARGUMENT:
    case grpc::StatusCode::FAILED_PRECONDITION:
    case grpc::StatusCode::OUT_OF_RANGE:
      return 400;
    case grpc::StatusCode::UNAUTHENTICATED:
      return 401;
    case grpc::StatusCode::PERMISSION_DENIED:
      return 403;
    case grpc::StatusCode::NOT_FOUND:
      return 404;
    case grpc::StatusCode::ALREADY_EXISTS:
    case grpc::StatusCode::ABORTED:
      return 409;
    case grpc::StatusCode::RESOURCE_EXHAUSTED:
      return 429;
    case grpc::StatusCode::CANCELLED:
      return 499;
    case grpc::StatusCode::UNIMPLEMENTED:
      return 501;
    case grpc::StatusCode::UNAVAILABLE:
      return 503;
    case grpc::StatusCode::DEADLINE_EXCEEDED:
      return 504;
    default:
      return 500;
  }
}

struct Reply {
  int status = 200;
  std::string json;
};

// A refused call: the google.rpc.Status with its details, as JSON. The
// access policy's refusal gets its ErrorInfo back (errors::fromGrpc).
Reply errorReply(const grpc::Status& status) {
  google::rpc::Status body;
  grpc::Status wire = status;
  if (status.error_details().empty()) {
    const absl::Status rebuilt = errors::fromGrpc(status);
    if (errors::errorInfo(rebuilt).has_value()) wire = errors::toGrpc(rebuilt);
  }
  if (wire.error_details().empty() || !body.ParseFromString(wire.error_details())) {
    body.set_code(static_cast<int>(status.error_code()));
    body.set_message(status.error_message());
  }
  return {httpStatus(status.error_code()), toJson(body)};
}

Reply invalid(const std::string& message) {
  return errorReply(
      errors::toGrpc(errors::withReason(absl::InvalidArgumentError(message), v1::INVALID_REQUEST)));
}

// One unary Coordinator call: the request's JSON in, the response's out.
using Call = std::function<Reply(const std::string& body, const std::string& authorization)>;

template <typename Request, typename Response>
Call unary(v1::Coordinator::Stub* stub,
           grpc::Status (v1::Coordinator::Stub::*method)(grpc::ClientContext*, const Request&,
                                                         Response*),
           std::chrono::milliseconds timeout) {
  return
      [stub, method, timeout](const std::string& body, const std::string& authorization) -> Reply {
        Request request;
        if (!body.empty()) {
          pbu::JsonParseOptions options;
          options.ignore_unknown_fields = false;
          const auto parsed = pbu::JsonStringToMessage(body, &request, options);
          if (!parsed.ok()) {
            return invalid(absl::StrCat("the body is not a ", Request::descriptor()->full_name(),
                                        " in JSON: ", parsed.ToString()));
          }
        }
        grpc::ClientContext context;
        context.set_deadline(std::chrono::system_clock::now() + timeout);
        if (!authorization.empty()) context.AddMetadata("authorization", authorization);
        Response response;
        const grpc::Status status = (stub->*method)(&context, request, &response);
        if (!status.ok()) return errorReply(status);
        return {200, toJson(response)};
      };
}

std::string gatewayJson(bool up, const std::string& why) {
  google::protobuf::Struct message;
  (*message.mutable_fields())["coordinator_up"].set_bool_value(up);
  (*message.mutable_fields())["message"].set_string_value(why);
  return toJson(message);
}

bool ended(v1::MissionState state) {
  return state == v1::MISSION_STATE_SUCCEEDED || state == v1::MISSION_STATE_FAILED ||
         state == v1::MISSION_STATE_ABORTED;
}

constexpr std::chrono::milliseconds kFirstRetry{100};
constexpr std::chrono::milliseconds kMaxRetry{2000};
// An idle event feed sends a comment this often, so a browser that went
// away is noticed.
constexpr std::chrono::milliseconds kKeepalive{5000};

}  // namespace

Gateway::Gateway(std::shared_ptr<grpc::Channel> coordinator, GatewayOptions options)
    : channel_(std::move(coordinator)),
      stub_(v1::Coordinator::NewStub(channel_)),
      options_(std::move(options)),
      hub_(options_.replay_capacity) {
  if (options_.data_channel) data_ = v1::DataChannel::NewStub(options_.data_channel);
}

Gateway::~Gateway() { shutdown(); }

absl::Status Gateway::start(const std::string& host, int port) {
  if (options_.tls_cert_file.empty() != options_.tls_key_file.empty()) {
    return absl::InvalidArgumentError("HTTPS needs both a certificate and a key");
  }
  if (!options_.tls_cert_file.empty()) {
    auto server = std::make_unique<httplib::SSLServer>(options_.tls_cert_file.c_str(),
                                                       options_.tls_key_file.c_str());
    if (!server->is_valid()) {
      return absl::InvalidArgumentError(absl::StrCat(
          "cannot serve HTTPS with ", options_.tls_cert_file, " and ", options_.tls_key_file));
    }
    server_ = std::move(server);
  } else {
    server_ = std::make_unique<httplib::Server>();
  }
  // One worker per event feed, and some for the calls.
  const size_t workers = static_cast<size_t>(options_.max_event_clients) + 8;
  server_->new_task_queue = [workers] { return new httplib::ThreadPool(workers); };
  server_->set_payload_max_length(options_.max_body_bytes);
  if (!options_.web_dir.empty() && !server_->set_mount_point("/", options_.web_dir)) {
    return absl::InvalidArgumentError(
        absl::StrCat("the console's web directory ", options_.web_dir, " does not exist"));
  }
  routes();
  if (port == 0) {
    port_ = server_->bind_to_any_port(host);
    if (port_ < 0) port_ = 0;
  } else if (server_->bind_to_port(host, port)) {
    port_ = port;
  }
  if (port_ == 0) {
    return absl::UnavailableError(absl::StrCat("cannot bind ", host, ":", port));
  }
  http_thread_ = std::thread([this] {
    server_->listen_after_bind();
    http_ended_ = true;
  });
  // Until it accepts: cpp-httplib's stop() does nothing to a server that has
  // not started listening, which would then never end.
  while (!server_->is_running() && !http_ended_) {
    std::this_thread::sleep_for(std::chrono::milliseconds(1));
  }
  if (http_ended_) return absl::UnavailableError("the console's HTTP server ended at once");
  events_thread_ = std::thread([this] { followEvents(); });
  missions_thread_ = std::thread([this] { followMissions(); });
  beliefs_thread_ = std::thread([this] { followBeliefs(); });
  return absl::OkStatus();
}

void Gateway::shutdown() {
  std::map<std::string, std::thread> watchers;
  {
    absl::MutexLock lock(&mutex_);
    if (stopping_) return;
    stopping_ = true;
    for (auto& [name, context] : streams_) context->TryCancel();
  }
  hub_.close();
  if (server_) server_->stop();
  if (http_thread_.joinable()) http_thread_.join();
  if (events_thread_.joinable()) events_thread_.join();
  if (missions_thread_.joinable()) missions_thread_.join();
  if (beliefs_thread_.joinable()) beliefs_thread_.join();
  std::vector<std::thread> topics;
  {
    absl::MutexLock lock(&mutex_);
    watchers.swap(mission_watchers_);
    topics.swap(topic_threads_);
  }
  for (auto& [id, thread] : watchers) {
    if (thread.joinable()) thread.join();
  }
  for (auto& thread : topics) thread.join();
}

bool Gateway::sleepFor(std::chrono::milliseconds wait, bool kickable) {
  absl::MutexLock lock(&mutex_);
  auto woken = [this, kickable]() ABSL_EXCLUSIVE_LOCKS_REQUIRED(mutex_) {
    return stopping_ || (kickable && kicked_);
  };
  mutex_.AwaitWithTimeout(absl::Condition(&woken), absl::FromChrono(wait));
  if (kickable) kicked_ = false;
  return !stopping_;
}

void Gateway::kick() {
  absl::MutexLock lock(&mutex_);
  kicked_ = true;
}

void Gateway::setCoordinatorUp(bool up, const std::string& why) {
  {
    absl::MutexLock lock(&mutex_);
    if (coordinator_known_ && coordinator_up_ == up) return;
    coordinator_known_ = true;
    coordinator_up_ = up;
  }
  hub_.publishLatest("gateway", "gateway", gatewayJson(up, why));
}

template <typename Response, typename Open, typename Handle, typename Ended>
void Gateway::followStream(const std::string& key, Open open, Handle handle, Ended ended) {
  auto retry = kFirstRetry;
  while (true) {
    grpc::ClientContext context;
    {
      absl::MutexLock lock(&mutex_);
      if (stopping_) return;
      streams_[key] = &context;
    }
    auto reader = open(&context);
    Response response;
    while (reader->Read(&response)) {
      retry = kFirstRetry;
      handle(response);
    }
    const grpc::Status status = reader->Finish();
    {
      absl::MutexLock lock(&mutex_);
      streams_.erase(key);
    }
    ended(status);
    if (!sleepFor(retry, false)) return;
    retry = std::min(retry * 2, kMaxRetry);
  }
}

void Gateway::followEvents() {
  EventCursor cursor;
  followStream<v1::WatchFleetEventsResponse>(
      "events",
      [&](grpc::ClientContext* context) { return stub_->WatchEvents(context, cursor.request()); },
      [&](const v1::WatchFleetEventsResponse& response) {
        setCoordinatorUp(true, "");
        for (const auto& event : cursor.accept(response)) hub_.publish("fleet", toJson(event));
      },
      [&](const grpc::Status& status) { setCoordinatorUp(false, status.error_message()); });
}

void Gateway::publishMission(const v1::MissionStatus& status) {
  std::string json = toJson(status);
  {
    absl::MutexLock lock(&mutex_);
    std::string& last = mission_json_[status.mission_id()];
    if (last == json) return;
    last = json;
  }
  hub_.publish("mission", std::move(json));
}

void Gateway::watchMission(const std::string& mission_id) {
  grpc::ClientContext context;
  const std::string key = "mission/" + mission_id;
  {
    absl::MutexLock lock(&mutex_);
    if (stopping_) return;
    streams_[key] = &context;
  }
  v1::WatchMissionRequest request;
  request.set_mission_id(mission_id);
  auto reader = stub_->WatchMission(&context, request);
  v1::WatchMissionResponse response;
  while (reader->Read(&response)) publishMission(response.status());
  reader->Finish();
  absl::MutexLock lock(&mutex_);
  streams_.erase(key);
  finished_watchers_.push_back(mission_id);
}

void Gateway::followMissions() {
  while (true) {
    grpc::ClientContext context;
    context.set_deadline(std::chrono::system_clock::now() + options_.call_timeout);
    v1::ListMissionsRequest request;
    request.set_page_size(100);
    v1::ListMissionsResponse response;
    std::vector<std::thread> done;
    if (stub_->ListMissions(&context, request, &response).ok()) {
      std::set<std::string> listed;
      for (const auto& status : response.missions()) {
        listed.insert(status.mission_id());
        publishMission(status);
        absl::MutexLock lock(&mutex_);
        if (!stopping_ && !ended(status.state()) &&
            mission_watchers_.count(status.mission_id()) == 0 &&
            mission_watchers_.size() < options_.max_watched_missions) {
          const std::string id = status.mission_id();
          mission_watchers_.emplace(id, std::thread([this, id] { watchMission(id); }));
        }
      }
      absl::MutexLock lock(&mutex_);
      // Missions the coordinator forgot are forgotten here too.
      for (auto it = mission_json_.begin(); it != mission_json_.end();) {
        it = listed.count(it->first) ? std::next(it) : mission_json_.erase(it);
      }
    }
    {
      absl::MutexLock lock(&mutex_);
      for (const auto& id : finished_watchers_) {
        auto it = mission_watchers_.find(id);
        if (it == mission_watchers_.end()) continue;
        done.push_back(std::move(it->second));
        mission_watchers_.erase(it);
      }
      finished_watchers_.clear();
    }
    for (auto& thread : done) thread.join();
    if (data_) followRobots();
    if (!sleepFor(options_.mission_poll, true)) return;
  }
}

// Every belief's latest value (a state per key), resumed after the last
// version seen; a coordinator without belief memory is asked again later.
void Gateway::followBeliefs() {
  uint64_t since_version = 0;
  followStream<v1::WatchBeliefsResponse>(
      "beliefs",
      [&](grpc::ClientContext* context) {
        v1::WatchBeliefsRequest request;
        request.set_since_version(since_version);
        return stub_->WatchBeliefs(context, request);
      },
      [&](const v1::WatchBeliefsResponse& response) {
        since_version = std::max(since_version, response.belief().version());
        hub_.publishLatest("belief/" + response.belief().key(), "belief",
                           toJson(response.belief()));
      },
      [](const grpc::Status&) {});
}

// Starts following the vehicle topics of robots that registered since.
void Gateway::followRobots() {
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + options_.call_timeout);
  v1::ListSystemsRequest request;
  request.set_page_size(100);
  v1::ListSystemsResponse response;
  if (!stub_->ListSystems(&context, request, &response).ok()) return;
  absl::MutexLock lock(&mutex_);
  for (const auto& system : response.systems()) {
    const std::string& robot = system.robot_id();
    if (stopping_ || robot.empty() || robots_.count(robot) > 0 ||
        robots_.size() >= options_.max_robots) {
      continue;
    }
    robots_.insert(robot);
    for (const auto& topic : options_.vehicle_topics) {
      const std::string name = "robots/" + robot + "/" + topic;
      topic_threads_.emplace_back([this, name] { followTopic(name); });
    }
  }
}

// One vehicle topic, its latest sample at most every vehicle_period, until
// shutdown; reconnects when the channel goes away.
void Gateway::followTopic(const std::string& topic) {
  auto last = std::chrono::steady_clock::time_point();
  followStream<v1::SubscribeResponse>(
      "topic/" + topic,
      [&](grpc::ClientContext* context) {
        v1::SubscribeRequest request;
        request.set_topic(topic);
        request.set_mode(v1::DELIVERY_MODE_LATEST);
        request.set_send_latest_first(true);
        return data_->Subscribe(context, request);
      },
      [&](const v1::SubscribeResponse& sample) {
        const auto now = std::chrono::steady_clock::now();
        if (now - last < options_.vehicle_period) return;
        last = now;
        hub_.publishLatest(topic, "vehicle", toJson(sample));
      },
      [](const grpc::Status&) {});
}

void Gateway::routes() {
  const auto timeout = options_.call_timeout;
  v1::Coordinator::Stub* stub = stub_.get();
  using S = v1::Coordinator::Stub;
  // The calls the console makes: reading the fleet and its missions, and an
  // operator's controls. Anything else is 404.
  auto calls = std::make_shared<std::map<std::string, Call>>(std::map<std::string, Call>{
      {"ListSystems", unary(stub, &S::ListSystems, timeout)},
      {"ListBehaviors", unary(stub, &S::ListBehaviors, timeout)},
      {"CheckBehaviorSituation", unary(stub, &S::CheckBehaviorSituation, timeout)},
      {"ListMissions", unary(stub, &S::ListMissions, timeout)},
      {"GetMission", unary(stub, &S::GetMission, timeout)},
      {"StartMission", unary(stub, &S::StartMission, timeout)},
      {"PauseMission", unary(stub, &S::PauseMission, timeout)},
      {"ResumeMission", unary(stub, &S::ResumeMission, timeout)},
      {"AbortMission", unary(stub, &S::AbortMission, timeout)},
      {"EmergencyLand", unary(stub, &S::EmergencyLand, timeout)},
      {"ReadBelief", unary(stub, &S::ReadBelief, timeout)},
      {"ListBeliefs", unary(stub, &S::ListBeliefs, timeout)},
  });
  server_->Post(R"(/api/coordinator/([A-Za-z]+))", [this, calls](const httplib::Request& request,
                                                                 httplib::Response& response) {
    const std::string name = request.matches[1];
    const auto call = calls->find(name);
    Reply reply;
    if (call == calls->end()) {
      reply = errorReply(errors::grpcError(grpc::StatusCode::NOT_FOUND, v1::INVALID_REQUEST,
                                           "the console does not call Coordinator." + name));
    } else {
      reply = call->second(request.body, request.get_header_value("Authorization"));
      if (reply.status == 200 && name.find("Mission") != std::string::npos) kick();
    }
    response.status = reply.status;
    response.set_content(reply.json, "application/json");
  });
  server_->Get("/api/events", [this](const httplib::Request& request, httplib::Response& response) {
    if (event_clients_.fetch_add(1) >= options_.max_event_clients) {
      event_clients_.fetch_sub(1);
      const Reply reply = errorReply(
          errors::grpcError(grpc::StatusCode::RESOURCE_EXHAUSTED, v1::LIMIT_EXCEEDED,
                            absl::StrCat("the console follows at most ", options_.max_event_clients,
                                         " event feeds at once"),
                            {{"limit", std::to_string(options_.max_event_clients)}}));
      response.status = reply.status;
      response.set_content(reply.json, "application/json");
      return;
    }
    // A browser that reconnects says what it saw last; a new one gets what
    // the hub kept.
    auto last = std::make_shared<uint64_t>(0);
    const std::string resume = request.get_header_value("Last-Event-ID");
    if (!resume.empty() && !absl::SimpleAtoi(resume, last.get())) *last = 0;
    response.set_header("Cache-Control", "no-cache");
    response.set_header("X-Accel-Buffering", "no");
    response.set_chunked_content_provider(
        "text/event-stream",
        [this, last](size_t, httplib::DataSink& sink) {
          const auto messages = hub_.after(*last, kKeepalive);
          if (hub_.closed()) {
            sink.done();
            return true;
          }
          std::string text = messages.empty() ? std::string(": keepalive\n\n") : std::string();
          for (const auto& message : messages) text += EventHub::format(message);
          if (!sink.write(text.data(), text.size())) return false;
          if (!messages.empty()) *last = messages.back().id;
          return true;
        },
        [this](bool) { event_clients_.fetch_sub(1); });
  });
  server_->Get("/api/world", [this](const httplib::Request&, httplib::Response& response) {
    // Without --world: an empty one (the page draws the vehicles alone).
    response.set_content(
        options_.world_json.empty() ? R"({"boxes":[],"markers":[]})" : options_.world_json,
        "application/json");
  });
  // Readiness of the console itself (the launcher waits for it).
  server_->Get("/healthz", [](const httplib::Request&, httplib::Response& response) {
    response.set_content("ok\n", "text/plain");
  });
  server_->set_post_routing_handler([](const httplib::Request&, httplib::Response& response) {
    response.set_header("X-Content-Type-Options", "nosniff");
  });
}

}  // namespace behaviorlib::console
