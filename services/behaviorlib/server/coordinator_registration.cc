#include "behaviorlib/server/coordinator_registration.h"

#include <google/protobuf/util/time_util.h>
#include <unistd.h>

#include <algorithm>
#include <cstdio>

#include "absl/time/time.h"
#include "behaviorlib/behavior_host.h"
#include "behaviorlib/server_kit/transport_security.h"

namespace behaviorlib::server {

namespace {

constexpr std::chrono::milliseconds kInitialBackoff(100);
constexpr std::chrono::milliseconds kMaxBackoff(2000);
constexpr std::chrono::milliseconds kDefaultHeartbeat(1000);
// The coordinator reads our ListBehaviors before answering RegisterSystem.
constexpr std::chrono::milliseconds kRegisterDeadline(5000);

grpc::ChannelArguments channelArguments() {
  // gRPC's default reconnect backoff grows to 120 s; a restarted coordinator
  // must be found again within our own 2 s retry period.
  grpc::ChannelArguments args;
  args.SetInt(GRPC_ARG_INITIAL_RECONNECT_BACKOFF_MS, static_cast<int>(kInitialBackoff.count()));
  // gRPC gives each connection attempt at least this long (its "minimum
  // connect timeout"); a refused attempt is still retried after the initial
  // backoff. At 100 ms, a server slow to send its HTTP/2 settings on a loaded
  // machine failed the call.
  args.SetInt(GRPC_ARG_MIN_RECONNECT_BACKOFF_MS, 5000);
  args.SetInt(GRPC_ARG_MAX_RECONNECT_BACKOFF_MS, static_cast<int>(kMaxBackoff.count()));
  return args;
}

std::string describe(const grpc::Status& status) {
  return status.error_message() + " (code " +
         std::to_string(static_cast<int>(status.error_code())) + ")";
}

}  // namespace

CoordinatorRegistration::CoordinatorRegistration(CoordinatorRegistrationOptions options)
    : options_(std::move(options)),
      channel_(behaviorlib::server_kit::makeChannel(options_.coordinator, channelArguments())),
      stub_(v1::Coordinator::NewStub(channel_)) {}

CoordinatorRegistration::~CoordinatorRegistration() { stop(std::chrono::milliseconds(500)); }

void CoordinatorRegistration::start() {
  thread_ = std::thread([this] { run(); });
}

bool CoordinatorRegistration::registered() const {
  absl::MutexLock lock(&mutex_);
  return registered_;
}

uint64_t CoordinatorRegistration::registrationCount() const {
  absl::MutexLock lock(&mutex_);
  return registrations_;
}

void CoordinatorRegistration::log(const std::string& line) const {
  std::fprintf(stderr, "%s: %s\n", options_.log_prefix.c_str(), line.c_str());
}

void CoordinatorRegistration::waitFor(std::chrono::milliseconds duration) {
  absl::MutexLock lock(&mutex_);
  // Until stopped, at most duration.
  mutex_.AwaitWithTimeout(absl::Condition(&stopping_), absl::FromChrono(duration));
}

template <class Request, class Response>
grpc::Status CoordinatorRegistration::call(
    grpc::Status (v1::Coordinator::Stub::*method)(grpc::ClientContext*, const Request&, Response*),
    const Request& request, Response* response, std::chrono::milliseconds deadline) {
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + deadline);
  {
    absl::MutexLock lock(&mutex_);
    if (stopping_) return grpc::Status(grpc::StatusCode::CANCELLED, "stopping");
    in_flight_ = &context;
  }
  const grpc::Status status = (stub_.get()->*method)(&context, request, response);
  absl::MutexLock lock(&mutex_);
  in_flight_ = nullptr;
  return status;
}

void CoordinatorRegistration::run() {
  std::chrono::milliseconds backoff = kInitialBackoff;
  std::chrono::milliseconds interval = kDefaultHeartbeat;
  std::string coordinator_incarnation;
  std::string last_complaint;
  const std::string where = "the coordinator at " + options_.coordinator;
  while (true) {
    bool registered = false;
    {
      absl::MutexLock lock(&mutex_);
      if (stopping_) return;
      registered = registered_;
    }
    if (!registered) {
      v1::RegisterSystemRequest request;
      request.set_robot_id(options_.robot_id);
      request.set_system(options_.system);
      request.set_address(options_.address);
      request.set_incarnation(options_.incarnation);
      v1::RegisterSystemResponse response;
      const grpc::Status status =
          call(&v1::Coordinator::Stub::RegisterSystem, request, &response, kRegisterDeadline);
      if (status.ok()) {
        {
          absl::MutexLock lock(&mutex_);
          registered_ = true;
          ++registrations_;
        }
        coordinator_incarnation = response.coordinator_incarnation();
        const auto ms =
            google::protobuf::util::TimeUtil::DurationToMilliseconds(response.heartbeat_interval());
        interval = ms > 0 ? std::clamp(std::chrono::milliseconds(ms), std::chrono::milliseconds(50),
                                       std::chrono::milliseconds(std::chrono::minutes(1)))
                          : kDefaultHeartbeat;
        backoff = kInitialBackoff;
        last_complaint.clear();
        log("registered with " + where + " as " + options_.address + " (" +
            std::to_string(response.behaviors_size()) + " behaviors)");
        continue;
      }
      if (status.error_code() == grpc::StatusCode::CANCELLED) continue;  // stopping
      // Say it once per kind of failure, not at every retry.
      const std::string complaint = "cannot register with " + where + ": " + describe(status);
      if (complaint != last_complaint) log(complaint + "; retrying");
      last_complaint = complaint;
      waitFor(backoff);
      backoff = std::min(backoff * 2, kMaxBackoff);
      continue;
    }

    waitFor(interval);
    v1::HeartbeatRequest request;
    request.set_robot_id(options_.robot_id);
    request.set_system(options_.system);
    request.set_incarnation(options_.incarnation);
    v1::HeartbeatResponse response;
    const grpc::Status status = call(&v1::Coordinator::Stub::Heartbeat, request, &response,
                                     std::max(interval, std::chrono::milliseconds(1000)));
    if (status.error_code() == grpc::StatusCode::CANCELLED) continue;  // stopping
    std::string again;
    if (status.ok()) {
      if (response.coordinator_incarnation() != coordinator_incarnation) {
        again = where + " restarted";
      }
    } else if (status.error_code() == grpc::StatusCode::FAILED_PRECONDITION) {
      const std::string complaint = where + " refuses this process: " + describe(status);
      if (complaint != last_complaint) log(complaint);
      last_complaint = complaint;
    } else if (status.error_code() == grpc::StatusCode::NOT_FOUND) {
      again = where + " no longer knows this process (" + status.error_message() + ")";
    } else {
      again = "lost " + where + " (" + describe(status) + ")";
    }
    if (!again.empty()) {
      log(again + "; registering again");
      absl::MutexLock lock(&mutex_);
      registered_ = false;
      backoff = kInitialBackoff;
    }
  }
}

void CoordinatorRegistration::stop(std::chrono::milliseconds timeout) {
  bool registered = false;
  {
    absl::MutexLock lock(&mutex_);
    if (stopped_) return;
    stopped_ = true;
    stopping_ = true;
    if (in_flight_ != nullptr) in_flight_->TryCancel();
  }
  if (thread_.joinable()) thread_.join();
  {
    absl::MutexLock lock(&mutex_);
    registered = registered_;
    registered_ = false;
  }
  if (!registered) return;
  v1::UnregisterSystemRequest request;
  request.set_robot_id(options_.robot_id);
  request.set_system(options_.system);
  request.set_incarnation(options_.incarnation);
  if (options_.final_seq) request.set_final_seq(options_.final_seq());
  v1::UnregisterSystemResponse response;
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + timeout);
  const grpc::Status status = stub_->UnregisterSystem(&context, request, &response);
  if (status.ok()) {
    log("unregistered from the coordinator at " + options_.coordinator + " (last event seq " +
        std::to_string(request.final_seq()) + ")");
  } else {
    log("could not unregister from the coordinator at " + options_.coordinator + ": " +
        describe(status));
  }
}

std::string advertisedAddress(const std::string& listen, int port) {
  const auto colon = listen.rfind(':');
  std::string host = colon == std::string::npos ? listen : listen.substr(0, colon);
  if (host.empty() || host == "0.0.0.0" || host == "[::]" || host == "::" || host == "*") {
    char name[256] = {};
    host = gethostname(name, sizeof(name) - 1) == 0 && name[0] != '\0' ? name : "localhost";
  }
  return host + ":" + std::to_string(port);
}

std::unique_ptr<CoordinatorRegistration> startCoordinatorRegistration(
    const std::string& coordinator, const std::string& listen, int bound_port, BehaviorHost& host,
    const std::string& program, const std::string& advertise) {
  if (coordinator.empty()) return nullptr;
  CoordinatorRegistrationOptions options;
  options.coordinator = coordinator;
  options.robot_id = host.robotId();
  options.system = host.system();
  options.address = advertise.empty() ? advertisedAddress(listen, bound_port) : advertise;
  options.incarnation = host.events().incarnation();
  options.final_seq = [&host] { return host.events().latestSeq(); };
  options.log_prefix = program;
  auto registration = std::make_unique<CoordinatorRegistration>(std::move(options));
  registration->start();
  return registration;
}

}  // namespace behaviorlib::server
