#pragma once

// Registration of a behavior-system process with the coordinator
// (behaviorlib.v1.Coordinator): RegisterSystem at start, retried with backoff
// (100 ms doubling to 2 s) while the coordinator is not up; Heartbeat at the
// interval the coordinator asks for; registering again when the coordinator
// restarted (Heartbeat answers NOT_FOUND, or its incarnation changed) or was
// unreachable; UnregisterSystem on a clean shutdown. Runs on a thread of its
// own and never blocks the behaviors.
//
//   auto registration = startCoordinatorRegistration(
//       "127.0.0.1:50060", "127.0.0.1:0", runtime.grpcPort(), host, "basic_quadrotor_behaviors");
//   ...                      // on SIGTERM, after host.stop():
//   registration->stop();    // UnregisterSystem with the last event's seq

#include <grpcpp/grpcpp.h>

#include <chrono>
#include <cstdint>
#include <functional>
#include <memory>
#include <string>
#include <thread>

#include "absl/base/thread_annotations.h"
#include "absl/synchronization/mutex.h"
#include "behaviorlib/v1/coordinator.grpc.pb.h"

namespace behaviorlib {
class BehaviorHost;
}  // namespace behaviorlib

namespace behaviorlib::server {

struct CoordinatorRegistrationOptions {
  /// The coordinator's address, "host:port".
  std::string coordinator;
  /// What is registered.
  std::string robot_id;
  std::string system;
  /// Where this process serves BehaviorSystem, as the coordinator can reach
  /// it (see advertisedAddress).
  std::string address;
  std::string incarnation;
  /// The seq of the last event emitted, read when unregistering.
  std::function<uint64_t()> final_seq;
  /// Prefix of the lines logged to stderr (the program name).
  std::string log_prefix = "behavior system";
};

class CoordinatorRegistration {
 public:
  explicit CoordinatorRegistration(CoordinatorRegistrationOptions options);
  /// Stops (and unregisters if registered), with a short deadline.
  ~CoordinatorRegistration();
  CoordinatorRegistration(const CoordinatorRegistration&) = delete;
  CoordinatorRegistration& operator=(const CoordinatorRegistration&) = delete;

  void start();
  /// Stops heartbeating and, if registered, calls UnregisterSystem (waiting
  /// at most `timeout`). Idempotent.
  void stop(std::chrono::milliseconds timeout = std::chrono::seconds(1));

  /// True while the coordinator has accepted the registration.
  bool registered() const;
  /// Successful RegisterSystem calls so far.
  uint64_t registrationCount() const;

 private:
  void run();
  // Waits up to `duration` unless stopped.
  void waitFor(std::chrono::milliseconds duration);
  // Runs one unary call with `deadline`; cancellable by stop().
  template <class Request, class Response>
  grpc::Status call(grpc::Status (v1::Coordinator::Stub::*method)(grpc::ClientContext*,
                                                                  const Request&, Response*),
                    const Request& request, Response* response, std::chrono::milliseconds deadline);
  void log(const std::string& line) const;

  const CoordinatorRegistrationOptions options_;
  std::shared_ptr<grpc::Channel> channel_;
  std::unique_ptr<v1::Coordinator::Stub> stub_;
  std::thread thread_;

  // The heartbeat thread sleeps on mutex_ (Mutex::AwaitWithTimeout) until
  // its next beat or the stop.
  mutable absl::Mutex mutex_;
  bool stopping_ ABSL_GUARDED_BY(mutex_) = false;
  bool stopped_ ABSL_GUARDED_BY(mutex_) = false;
  grpc::ClientContext* in_flight_ ABSL_GUARDED_BY(mutex_) = nullptr;
  bool registered_ ABSL_GUARDED_BY(mutex_) = false;
  uint64_t registrations_ ABSL_GUARDED_BY(mutex_) = 0;
};

/// The "host:port" under which a server started with `--listen listen` and
/// bound to `port` is reachable: the listen host with the bound port, or this
/// machine's host name when it listens on every interface (0.0.0.0, [::]).
std::string advertisedAddress(const std::string& listen, int port);

/// Starts registering `host`'s system with `coordinator`; nullptr when
/// `coordinator` is empty (no registration). The coordinator is told to dial
/// `advertise` when it is set (a relay or a NAT in front of the system),
/// advertisedAddress(listen, bound_port) otherwise.
std::unique_ptr<CoordinatorRegistration> startCoordinatorRegistration(
    const std::string& coordinator, const std::string& listen, int bound_port, BehaviorHost& host,
    const std::string& program, const std::string& advertise = "");

}  // namespace behaviorlib::server
