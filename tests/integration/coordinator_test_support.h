#pragma once

// Helpers of the coordinator's integration tests: clients of the real
// coordinator and behavior-system processes with bounded waits, and a TCP
// proxy that can cut the network between them (a fault injector, not a
// stand-in: both ends are the real processes).

#include <arpa/inet.h>
#include <google/protobuf/struct.pb.h>
#include <google/protobuf/util/json_util.h>
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>
#include <netinet/in.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <condition_variable>
#include <deque>
#include <functional>
#include <memory>
#include <mutex>
#include <optional>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "behaviorlib/v1/behavior.grpc.pb.h"
#include "behaviorlib/v1/coordinator.grpc.pb.h"
#include "support/prometheus_text.h"
#include "support/server_process.h"

namespace coordinator_test {

namespace v1 = behaviorlib::v1;
using std::chrono::milliseconds;
using std::chrono::seconds;
using SteadyClock = std::chrono::steady_clock;

// Every RPC and every wait is bounded.
constexpr milliseconds kCallTimeout = seconds(5);
constexpr milliseconds kEventTimeout = seconds(5);

inline std::string describe(const grpc::Status& s) {
  return std::to_string(static_cast<int>(s.error_code())) + " " + s.error_message();
}

inline google::protobuf::Struct structFromJson(const std::string& json) {
  google::protobuf::Struct s;
  auto status = google::protobuf::util::JsonStringToMessage(json, &s);
  EXPECT_TRUE(status.ok()) << json << ": " << status.ToString();
  return s;
}

template <class Response>
struct Reply {
  grpc::Status status;
  Response response;
};

template <class Stub, class Request, class Response>
Reply<Response> unary(Stub& stub,
                      grpc::Status (Stub::*method)(grpc::ClientContext*, const Request&, Response*),
                      const Request& request) {
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + kCallTimeout);
  Reply<Response> reply;
  reply.status = (stub.*method)(&context, request, &reply.response);
  return reply;
}

/// Polls `condition` every 20 ms until it holds or `timeout` passes.
inline bool waitUntil(const std::function<bool()>& condition, milliseconds timeout) {
  const auto deadline = SteadyClock::now() + timeout;
  while (true) {
    if (condition()) return true;
    if (SteadyClock::now() >= deadline) return false;
    std::this_thread::sleep_for(milliseconds(20));
  }
}

/// Client of behaviorlib.v1.Coordinator.
class CoordinatorClient {
 public:
  explicit CoordinatorClient(const std::string& address)
      : stub_(v1::Coordinator::NewStub(
            grpc::CreateChannel(address, grpc::InsecureChannelCredentials()))) {}

  Reply<v1::ListSystemsResponse> listSystems(const std::string& robot = "") {
    v1::ListSystemsRequest request;
    request.set_robot_id(robot);
    return unary(*stub_, &v1::Coordinator::Stub::ListSystems, request);
  }
  Reply<v1::ListFleetBehaviorsResponse> listBehaviors(const std::string& robot = "",
                                                      const std::string& behavior = "") {
    v1::ListFleetBehaviorsRequest request;
    request.set_robot_id(robot);
    request.set_behavior(behavior);
    return unary(*stub_, &v1::Coordinator::Stub::ListBehaviors, request);
  }
  Reply<v1::ActivateFleetBehaviorResponse> activate(const std::string& robot,
                                                    const std::string& behavior,
                                                    const std::string& parameters_json,
                                                    const std::string& request_id = "") {
    v1::ActivateFleetBehaviorRequest request;
    request.set_robot_id(robot);
    request.set_behavior(behavior);
    *request.mutable_parameters() = structFromJson(parameters_json);
    request.set_request_id(request_id);
    return unary(*stub_, &v1::Coordinator::Stub::ActivateBehavior, request);
  }
  Reply<v1::DeactivateFleetBehaviorResponse> deactivate(const std::string& robot,
                                                        const std::string& behavior,
                                                        const std::string& activation_id = "") {
    v1::DeactivateFleetBehaviorRequest request;
    request.set_robot_id(robot);
    request.set_behavior(behavior);
    request.set_activation_id(activation_id);
    return unary(*stub_, &v1::Coordinator::Stub::DeactivateBehavior, request);
  }
  Reply<v1::CheckFleetBehaviorSituationResponse> situation(const std::string& robot,
                                                           const std::string& behavior) {
    v1::CheckFleetBehaviorSituationRequest request;
    request.set_robot_id(robot);
    request.set_behavior(behavior);
    return unary(*stub_, &v1::Coordinator::Stub::CheckBehaviorSituation, request);
  }
  /// Any other call: unary(client.stub(), &v1::Coordinator::Stub::..., request).
  v1::Coordinator::Stub& stub() { return *stub_; }
  Reply<v1::RegisterSystemResponse> registerSystem(const v1::RegisterSystemRequest& request) {
    return unary(*stub_, &v1::Coordinator::Stub::RegisterSystem, request);
  }
  Reply<v1::HeartbeatResponse> heartbeat(const v1::HeartbeatRequest& request) {
    return unary(*stub_, &v1::Coordinator::Stub::Heartbeat, request);
  }

  /// The system of `robot` (first one), if listed.
  std::optional<v1::SystemInfo> system(const std::string& robot) {
    auto reply = listSystems(robot);
    if (!reply.status.ok() || reply.response.systems().empty()) return std::nullopt;
    return reply.response.systems(0);
  }

  /// Waits until `robot`'s system is listed in `state` (and, if given, with
  /// `incarnation`).
  bool waitForSystem(const std::string& robot, v1::SystemState state,
                     milliseconds timeout = seconds(10), const std::string& incarnation = "") {
    return waitUntil(
        [&] {
          auto s = system(robot);
          return s && s->state() == state &&
                 (incarnation.empty() || s->incarnation() == incarnation);
        },
        timeout);
  }

 private:
  std::unique_ptr<v1::Coordinator::Stub> stub_;
};

/// Generic client of one behavior system (behaviorlib.v1.BehaviorSystem).
class SystemClient {
 public:
  explicit SystemClient(const std::string& address)
      : stub_(v1::BehaviorSystem::NewStub(
            grpc::CreateChannel(address, grpc::InsecureChannelCredentials()))) {}

  Reply<v1::ActivateResponse> activate(const std::string& behavior, const std::string& json) {
    v1::ActivateBehaviorRequest request;
    request.set_behavior(behavior);
    *request.mutable_parameters() = structFromJson(json);
    return unary(*stub_, &v1::BehaviorSystem::Stub::ActivateBehavior, request);
  }
  Reply<v1::CheckActivationResponse> checkActivation(const std::string& behavior) {
    v1::CheckBehaviorActivationRequest request;
    request.set_behavior(behavior);
    return unary(*stub_, &v1::BehaviorSystem::Stub::CheckBehaviorActivation, request);
  }
  Reply<v1::ListBehaviorsResponse> listBehaviors() {
    return unary(*stub_, &v1::BehaviorSystem::Stub::ListBehaviors, v1::ListBehaviorsRequest());
  }

 private:
  std::unique_ptr<v1::BehaviorSystem::Stub> stub_;
};

/// A Coordinator.WatchEvents subscriber: a reader thread queues every
/// message; the test pops them with bounded waits.
class FleetWatcher {
 public:
  FleetWatcher(const std::string& address, const v1::WatchFleetEventsRequest& request)
      : stub_(v1::Coordinator::NewStub(
            grpc::CreateChannel(address, grpc::InsecureChannelCredentials()))) {
    context_.set_deadline(std::chrono::system_clock::now() + seconds(90));
    reader_ = stub_->WatchEvents(&context_, request);
    thread_ = std::thread([this] { run(); });
  }
  explicit FleetWatcher(const std::string& address)
      : FleetWatcher(address, v1::WatchFleetEventsRequest()) {}
  ~FleetWatcher() { disconnect(); }
  FleetWatcher(const FleetWatcher&) = delete;
  FleetWatcher& operator=(const FleetWatcher&) = delete;

  static v1::WatchFleetEventsRequest request(uint64_t since_seq, const std::string& incarnation,
                                             std::vector<std::string> robots = {},
                                             std::vector<std::string> behaviors = {}) {
    v1::WatchFleetEventsRequest r;
    r.set_since_seq(since_seq);
    r.set_incarnation(incarnation);
    for (auto& robot : robots) r.add_robot_ids(robot);
    for (auto& behavior : behaviors) r.add_behaviors(behavior);
    return r;
  }

  void disconnect() {
    context_.TryCancel();
    if (thread_.joinable()) thread_.join();
  }

  std::optional<v1::WatchFleetEventsResponse> next(milliseconds timeout = kEventTimeout) {
    std::unique_lock lock(mutex_);
    cv_.wait_for(lock, timeout, [this] { return !queue_.empty() || ended_; });
    if (queue_.empty()) return std::nullopt;
    auto message = std::move(queue_.front());
    queue_.pop_front();
    return message;
  }

  std::optional<v1::WatchEventsStart> start(milliseconds timeout = kEventTimeout) {
    auto message = next(timeout);
    if (!message || !message->has_start()) {
      ADD_FAILURE() << "no WatchEventsStart received"
                    << (message ? ": " + message->ShortDebugString() : std::string());
      return std::nullopt;
    }
    return message->start();
  }

  std::optional<v1::FleetEvent> nextEvent(milliseconds timeout = kEventTimeout) {
    auto message = next(timeout);
    if (!message) return std::nullopt;
    if (!message->has_event()) {
      ADD_FAILURE() << "expected an event, got " << message->ShortDebugString();
      return std::nullopt;
    }
    return message->event();
  }

  /// Pops events until one matches (the others are appended to `skipped`).
  std::optional<v1::FleetEvent> waitFor(const std::function<bool(const v1::FleetEvent&)>& predicate,
                                        milliseconds timeout = kEventTimeout,
                                        std::vector<v1::FleetEvent>* skipped = nullptr) {
    const auto deadline = SteadyClock::now() + timeout;
    while (true) {
      const auto left = std::chrono::duration_cast<milliseconds>(deadline - SteadyClock::now());
      if (left <= milliseconds(0)) return std::nullopt;
      auto event = nextEvent(left);
      if (!event) return std::nullopt;
      if (predicate(*event)) return event;
      if (skipped) skipped->push_back(*event);
    }
  }

  std::optional<v1::FleetEvent> waitFinished(const std::string& activation_id,
                                             milliseconds timeout = kEventTimeout) {
    return waitFor(
        [&](const v1::FleetEvent& e) {
          return e.has_behavior_event() && e.behavior_event().has_finished() &&
                 e.behavior_event().activation_id() == activation_id;
        },
        timeout);
  }

  std::optional<v1::FleetEvent> waitActivated(const std::string& activation_id,
                                              milliseconds timeout = kEventTimeout) {
    return waitFor(
        [&](const v1::FleetEvent& e) {
          return e.has_behavior_event() && e.behavior_event().has_activated() &&
                 e.behavior_event().activation_id() == activation_id;
        },
        timeout);
  }

  std::optional<v1::FleetEvent> waitSystemState(const std::string& robot, v1::SystemState state,
                                                milliseconds timeout = kEventTimeout) {
    return waitFor(
        [&](const v1::FleetEvent& e) {
          return e.has_system_state_changed() &&
                 e.system_state_changed().system().robot_id() == robot &&
                 e.system_state_changed().system().state() == state;
        },
        timeout);
  }

  /// Every event that arrives within `quiet` of the previous one.
  std::vector<v1::FleetEvent> drain(milliseconds quiet = milliseconds(300)) {
    std::vector<v1::FleetEvent> events;
    while (auto e = nextEvent(quiet)) events.push_back(*e);
    return events;
  }

  std::optional<grpc::Status> waitEnded(milliseconds timeout) {
    std::unique_lock lock(mutex_);
    cv_.wait_for(lock, timeout, [this] { return ended_; });
    if (!ended_) return std::nullopt;
    return status_;
  }

 private:
  void run() {
    v1::WatchFleetEventsResponse message;
    while (reader_->Read(&message)) {
      std::lock_guard lock(mutex_);
      queue_.push_back(message);
      cv_.notify_all();
    }
    grpc::Status status = reader_->Finish();
    std::lock_guard lock(mutex_);
    status_ = status;
    ended_ = true;
    cv_.notify_all();
  }

  std::unique_ptr<v1::Coordinator::Stub> stub_;
  grpc::ClientContext context_;
  std::unique_ptr<grpc::ClientReader<v1::WatchFleetEventsResponse>> reader_;
  std::thread thread_;
  std::mutex mutex_;
  std::condition_variable cv_;
  std::deque<v1::WatchFleetEventsResponse> queue_;
  bool ended_ = false;
  grpc::Status status_;
};

/// Behavior events of `events` (in order), optionally only of `robot`.
inline std::vector<v1::BehaviorEvent> behaviorEvents(const std::vector<v1::FleetEvent>& events,
                                                     const std::string& robot = "") {
  std::vector<v1::BehaviorEvent> out;
  for (const auto& e : events) {
    if (e.has_behavior_event() && (robot.empty() || e.behavior_event().robot_id() == robot)) {
      out.push_back(e.behavior_event());
    }
  }
  return out;
}

/// Counts the finished events of `activation_id` in `events`.
inline int finishedCount(const std::vector<v1::FleetEvent>& events,
                         const std::string& activation_id) {
  int n = 0;
  for (const auto& e : events) {
    n += e.has_behavior_event() && e.behavior_event().has_finished() &&
         e.behavior_event().activation_id() == activation_id;
  }
  return n;
}

/// A TCP proxy on 127.0.0.1 (free port) to `target_port` that can cut every
/// connection and refuse new ones, then let them through again.
class TcpProxy {
 public:
  explicit TcpProxy(int target_port) : target_port_(target_port) {
    listener_ = socket(AF_INET, SOCK_STREAM, 0);
    int one = 1;
    setsockopt(listener_, SOL_SOCKET, SO_REUSEADDR, &one, sizeof(one));
    sockaddr_in addr{};
    addr.sin_family = AF_INET;
    addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    addr.sin_port = 0;
    if (bind(listener_, reinterpret_cast<sockaddr*>(&addr), sizeof(addr)) != 0 ||
        listen(listener_, 64) != 0) {
      ADD_FAILURE() << "proxy cannot listen";
      return;
    }
    socklen_t len = sizeof(addr);
    getsockname(listener_, reinterpret_cast<sockaddr*>(&addr), &len);
    port_ = ntohs(addr.sin_port);
    accept_thread_ = std::thread([this] { acceptLoop(); });
  }

  ~TcpProxy() {
    stopping_ = true;
    ::shutdown(listener_, SHUT_RDWR);
    close(listener_);
    if (accept_thread_.joinable()) accept_thread_.join();
    cut();
    std::vector<std::thread> pumps;
    {
      // Joined without the lock: a pump takes it to close its sockets.
      std::lock_guard lock(mutex_);
      pumps = std::move(pumps_);
    }
    for (auto& t : pumps) t.join();
  }

  int port() const { return port_; }
  std::string address() const { return "127.0.0.1:" + std::to_string(port_); }

  /// Closes every connection and refuses new ones until restore().
  void cut() {
    refusing_ = true;
    std::lock_guard lock(mutex_);
    for (int fd : open_) ::shutdown(fd, SHUT_RDWR);
  }
  void restore() { refusing_ = false; }

 private:
  void acceptLoop() {
    while (!stopping_) {
      const int client = accept(listener_, nullptr, nullptr);
      if (client < 0) {
        if (stopping_) return;
        continue;
      }
      if (refusing_) {
        close(client);
        continue;
      }
      const int upstream = socket(AF_INET, SOCK_STREAM, 0);
      sockaddr_in addr{};
      addr.sin_family = AF_INET;
      addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
      addr.sin_port = htons(static_cast<uint16_t>(target_port_));
      if (connect(upstream, reinterpret_cast<sockaddr*>(&addr), sizeof(addr)) != 0) {
        close(upstream);
        close(client);
        continue;
      }
      std::lock_guard lock(mutex_);
      open_.push_back(client);
      open_.push_back(upstream);
      pumps_.emplace_back([this, client, upstream] { pump(client, upstream); });
    }
  }

  void pump(int a, int b) {
    pollfd fds[2] = {{a, POLLIN, 0}, {b, POLLIN, 0}};
    char buffer[16384];
    while (!stopping_) {
      if (poll(fds, 2, 100) < 0) break;
      bool done = false;
      for (int i = 0; i < 2 && !done; ++i) {
        if (fds[i].revents & (POLLIN | POLLHUP | POLLERR)) {
          const ssize_t n = read(fds[i].fd, buffer, sizeof(buffer));
          if (n <= 0 || refusing_) {
            done = true;
            break;
          }
          const int to = fds[1 - i].fd;
          for (ssize_t sent = 0; sent < n;) {
            const ssize_t w = send(to, buffer + sent, static_cast<size_t>(n - sent), MSG_NOSIGNAL);
            if (w <= 0) {
              done = true;
              break;
            }
            sent += w;
          }
        }
      }
      if (done) break;
    }
    std::lock_guard lock(mutex_);
    for (int fd : {a, b}) {
      ::shutdown(fd, SHUT_RDWR);
      close(fd);
      open_.erase(std::remove(open_.begin(), open_.end(), fd), open_.end());
    }
  }

  const int target_port_;
  int listener_ = -1;
  int port_ = 0;
  std::atomic<bool> stopping_{false};
  std::atomic<bool> refusing_{false};
  std::thread accept_thread_;
  std::mutex mutex_;
  std::vector<int> open_;
  std::vector<std::thread> pumps_;
};

using support::metricSum;
using support::metricValue;

}  // namespace coordinator_test
