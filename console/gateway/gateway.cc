#include "behaviorlib/console/gateway.h"

#include <google/protobuf/struct.pb.h>
#include <google/protobuf/util/json_util.h>
#include <google/protobuf/util/type_resolver.h>
#include <google/protobuf/util/type_resolver_util.h>
#include <httplib.h>

#include <algorithm>
#include <cstdio>
#include <filesystem>
#include <functional>
#include <map>
#include <regex>
#include <set>
#include <utility>

#include "absl/strings/match.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/time/time.h"
#include "behaviorlib/embedded_descriptor_pool.h"
#include "behaviorlib/error_details.h"
#include "behaviorlib/recorder/recorder.h"
#include "formats/mcap/mcap.h"
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
  JsonPrinter() {
    resolver_.reset(
        pbu::NewTypeResolverForDescriptorPool(kTypeUrlPrefix, &embedded::descriptorPool()));
    options_.preserve_proto_field_names = true;
    options_.always_print_primitive_fields = true;
  }

  std::string print(const google::protobuf::Message& message) const {
    return printBinary(message.GetDescriptor()->full_name(), message.SerializeAsString());
  }

  // A message of the type `type` (a full name of the embedded descriptors)
  // from its binary encoding.
  std::string printBinary(const std::string& type, const std::string& bytes) const {
    std::string out;
    const auto status = pbu::BinaryToJsonString(
        resolver_.get(), absl::StrCat(kTypeUrlPrefix, "/", type), bytes, &out, options_);
    if (!status.ok()) {
      google::protobuf::Struct error;
      (*error.mutable_fields())["json_error"].set_string_value(status.ToString());
      pbu::MessageToJsonString(error, &out);
    }
    return out;
  }

 private:
  std::unique_ptr<pbu::TypeResolver> resolver_;
  pbu::JsonPrintOptions options_;
};

const JsonPrinter& printer() {
  static const JsonPrinter* const instance = new JsonPrinter();
  return *instance;
}

std::string toJson(const google::protobuf::Message& message) { return printer().print(message); }

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

// One recording as the feed's messages (the page applies them as it does
// the live ones): the coordinator's events, missions and beliefs, and the
// vehicle samples thinned to one per `period` per topic.
absl::StatusOr<std::string> recordingJson(const std::string& path, const std::string& name,
                                          const GatewayOptions& options) {
  recorder::mcap::ReadLimits limits;
  limits.max_file_bytes = options.max_recording_bytes;
  std::string messages;
  size_t count = 0;
  bool truncated = false;
  uint64_t first_ns = 0;
  uint64_t last_ns = 0;
  std::map<uint16_t, uint64_t> last_sample_ns;
  const uint64_t period_ns =
      static_cast<uint64_t>(std::chrono::nanoseconds(options.recording_sample_period).count());
  const auto summary = recorder::mcap::scan(
      path, limits,
      [&](const recorder::mcap::ScanSummary& known, const recorder::mcap::Message& message) {
        const auto& channel = known.channels.at(message.channel_id);
        const auto schema = known.schemas.find(channel.schema_id);
        if (schema == known.schemas.end() || schema->second.encoding != "protobuf") return true;
        const std::string& type = schema->second.name;
        std::string event;
        std::string data;
        if (channel.topic == recorder::kEventsTopic) {
          event = "fleet";
        } else if (channel.topic == recorder::kMissionsTopic) {
          event = "mission";
        } else if (channel.topic == recorder::kBeliefsTopic) {
          event = "belief";
        } else if (absl::StartsWith(channel.topic, "robots/")) {
          auto last = last_sample_ns.find(message.channel_id);
          if (last != last_sample_ns.end() && message.log_time_ns < last->second + period_ns) {
            return true;
          }
          last_sample_ns[message.channel_id] = message.log_time_ns;
          v1::SubscribeResponse sample;
          sample.set_topic(channel.topic);
          sample.mutable_sample()->set_type_url(absl::StrCat(kTypeUrlPrefix, "/", type));
          sample.mutable_sample()->set_value(message.data);
          event = "vehicle";
          data = toJson(sample);
        } else {
          return true;
        }
        if (data.empty()) data = printer().printBinary(type, message.data);
        if (count == 0) first_ns = message.log_time_ns;
        last_ns = std::max(last_ns, message.log_time_ns);
        if (count >= options.max_recording_messages) {
          truncated = true;
          return false;
        }
        const double t_ms =
            (static_cast<double>(message.log_time_ns) - static_cast<double>(first_ns)) / 1e6;
        absl::StrAppend(&messages, count == 0 ? "" : ",", "{\"t_ms\":", t_ms, ",\"event\":\"",
                        event, "\",\"data\":", data, "}");
        ++count;
        return true;
      });
  if (!summary.ok()) return summary.status();
  return absl::StrCat(
      "{\"name\":\"", name, "\",\"complete\":", summary->complete ? "true" : "false",
      ",\"truncated\":", truncated ? "true" : "false",
      ",\"duration_ms\":", (static_cast<double>(last_ns) - static_cast<double>(first_ns)) / 1e6,
      ",\"messages\":[", messages, "]}");
}

follower::FollowerOptions followerOptions(const GatewayOptions& options) {
  follower::FollowerOptions follower;
  follower.call_timeout = options.call_timeout;
  follower.mission_poll = options.mission_poll;
  follower.max_watched_missions = options.max_watched_missions;
  follower.data_channel = options.data_channel;
  // The console draws a vehicle at most once a vehicle_period: the broker
  // and the simulator are asked for no more than that (decision 17).
  const double rate_hz =
      options.vehicle_period.count() > 0 ? 1000.0 / options.vehicle_period.count() : 0.0;
  for (const auto& topic : options.vehicle_topics) {
    follower.vehicle_topics.push_back({topic, rate_hz});
  }
  follower.vehicle_period = options.vehicle_period;
  follower.max_robots = options.max_robots;
  return follower;
}
// An idle event feed sends a comment this often, so a browser that went
// away is noticed.
constexpr std::chrono::milliseconds kKeepalive{5000};

// The API's JSON goes out uncompressed. cpp-httplib compresses a reply whose
// type is exactly "application/json" when the request accepts it, and with
// brotli at its default quality (11) when a browser says br: the lists of a
// 20-vehicle fleet then cost tens of milliseconds of CPU a reply, which the
// page asked for at every fleet event (two thirds of the console's CPU in
// a 20-vehicle run with one page open). The library compresses by exact
// type, so the same type with its charset parameter is sent as it is. The
// static files (the page, its script) are still compressed, once a load.
constexpr char kJson[] = "application/json; charset=utf-8";
// Recordings listed at most.
constexpr size_t kMaxListedRecordings = 1000;

const std::regex& recordingName() {
  static const std::regex* const pattern = new std::regex(R"([A-Za-z0-9._-]{1,200}\.mcap)");
  return *pattern;
}

}  // namespace

Gateway::Gateway(std::shared_ptr<grpc::Channel> coordinator, GatewayOptions options)
    : channel_(std::move(coordinator)),
      stub_(v1::Coordinator::NewStub(channel_)),
      options_(std::move(options)),
      hub_(options_.replay_capacity),
      follower_(channel_, followerOptions(options_), this) {}

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
  if (!options_.recordings_dir.empty()) {
    auto recordings = server_kit::ConfinedDirectory::open("recordings", options_.recordings_dir,
                                                          options_.max_recording_bytes);
    if (!recordings.ok()) return recordings.status();
    recordings_ = std::move(*recordings);
  }
  routes();
  recordingRoutes();
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
  follower_.start();
  return absl::OkStatus();
}

void Gateway::shutdown() {
  if (stopped_.exchange(true)) return;
  follower_.shutdown();
  hub_.close();
  if (server_) server_->stop();
  if (http_thread_.joinable()) http_thread_.join();
}

void Gateway::onEvent(const v1::FleetEvent& event) { hub_.publish("fleet", toJson(event)); }

void Gateway::onMission(const v1::MissionStatus& status) {
  hub_.publish("mission", toJson(status));
}

// Each belief's latest value is a state of its own.
void Gateway::onBelief(const v1::Belief& belief) {
  hub_.publishLatest("belief/" + belief.key(), "belief", toJson(belief));
}

void Gateway::onSample(const v1::SubscribeResponse& sample) {
  hub_.publishLatest(sample.topic(), "vehicle", toJson(sample));
}

void Gateway::onCoordinator(bool up, const std::string& why) {
  hub_.publishLatest("gateway", "gateway", gatewayJson(up, why));
}

void Gateway::recordingRoutes() {
  server_->Get("/api/recordings", [this](const httplib::Request&, httplib::Response& response) {
    std::vector<std::pair<std::string, uintmax_t>> found;
    std::error_code error;
    if (recordings_.enabled()) {
      for (std::filesystem::directory_iterator it(recordings_.root(), error), end;
           !error && it != end && found.size() < kMaxListedRecordings; it.increment(error)) {
        const std::string name = it->path().filename().string();
        if (it->symlink_status().type() != std::filesystem::file_type::regular ||
            !std::regex_match(name, recordingName())) {
          continue;
        }
        found.emplace_back(name, it->file_size(error));
      }
    }
    std::sort(found.begin(), found.end());
    std::string list;
    for (const auto& [name, bytes] : found) {
      absl::StrAppend(&list, list.empty() ? "" : ",", "{\"name\":\"", name, "\",\"bytes\":", bytes,
                      "}");
    }
    response.set_content(absl::StrCat("{\"recordings\":[", list, "]}"), kJson);
  });
  server_->Get(R"(/api/recordings/([^/]+))", [this](const httplib::Request& request,
                                                    httplib::Response& response) {
    const std::string name = request.matches[1];
    absl::StatusOr<std::string> json;
    if (!std::regex_match(name, recordingName())) {
      json = absl::InvalidArgumentError(absl::StrCat(
          "a recording's name is letters, digits, '.', '_' and '-' ending .mcap, not '", name,
          "'"));
    } else {
      absl::StatusOr<std::string> path = recordings_.resolveExisting(name);
      json = path.ok() ? recordingJson(*path, name, options_) : path.status();
    }
    if (json.ok()) {
      response.set_content(*json, kJson);
      return;
    }
    const Reply reply = errorReply(errors::toGrpc(json.status()));
    response.status = reply.status;
    response.set_content(reply.json, kJson);
  });
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
      {"CheckMission", unary(stub, &S::CheckMission, timeout)},
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
      if (reply.status == 200 && name.find("Mission") != std::string::npos) follower_.kick();
    }
    response.status = reply.status;
    response.set_content(reply.json, kJson);
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
      response.set_content(reply.json, kJson);
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
        options_.world_json.empty() ? R"({"boxes":[],"markers":[]})" : options_.world_json, kJson);
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
