#pragma once

// The coordinator's connection to one behavior-system process: its event
// intake and its supervision, on one thread per system.
//
// The thread reads the system's ListBehaviors (whenever a new incarnation
// appears) and follows its WatchEvents stream, resuming with since_seq and the
// incarnation after every break so that no event is lost or doubled
// (ActivationTracker). When the stream breaks it checks the system's gRPC
// health every probe interval; once the check has failed for the grace period
// (Supervision) the system is DOWN and every activation in progress there gets
// a synthesized PROCESS_FAILURE. It keeps contacting the system: a new
// incarnation (a restart, or a registration naming a new address) makes it UP
// again, and the old incarnation's activations still in progress end with
// PROCESS_FAILURE first. A second thread (the watchdog) probes health while
// the stream is up but silent, or the system's heartbeats stopped: a frozen
// process (SIGSTOP, deadlock) keeps its connection open and its stream never
// breaks, so when those probes fail for the grace period the watchdog cancels
// the stream and the intake thread declares the system down at once (it comes
// back, same incarnation, as after a network cut). Every event of the
// system's, and every state change, is appended to the FleetEventLog by the
// intake thread only, so they appear in the order they happened.
//
//   SystemLink link({.robot_id = "drone1", .address = "127.0.0.1:50061",
//                    .source = v1::SYSTEM_SOURCE_CONFIG}, log, metrics, options, on_retired);
//   link.start();
//   ...
//   link.stop();   // cancels the stream, joins the thread

#include <grpcpp/grpcpp.h>

#include <chrono>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include "absl/base/thread_annotations.h"
#include "absl/synchronization/mutex.h"
#include "behaviorlib/v1/behavior.grpc.pb.h"
#include "behaviorlib/v1/coordinator.pb.h"
#include "coordinator/events/activation_tracker.h"
#include "coordinator/events/fleet_event_log.h"
#include "coordinator/metrics/coordinator_metrics.h"
#include "coordinator/registry/supervision.h"

namespace behaviorlib::coordinator {

/// The most behaviors a coordinator registers per system: it reads a
/// system's description as one ListBehaviors page of this size, and refuses
/// a system whose description has a next page.
inline constexpr int32_t kMaxBehaviorsPerSystem = 1000;

struct LinkOptions {
  /// How long the health check must keep failing (after the stream broke)
  /// before the system is declared down. Wall time.
  std::chrono::nanoseconds grace = std::chrono::seconds(1);
  /// Deadline of one health check.
  std::chrono::milliseconds health_timeout{250};
  /// Health checks while reconnecting.
  std::chrono::milliseconds probe_interval{100};
  /// Health checks while down or unregistered.
  std::chrono::milliseconds idle_probe_interval{500};
  /// Deadline of ListBehaviors and of the calls the link makes itself.
  std::chrono::milliseconds call_timeout{3000};
  /// The heartbeat interval registered systems are given; heartbeats missed
  /// for more than two intervals make the watchdog probe health.
  std::chrono::milliseconds heartbeat_interval{1000};
  /// Watchdog of a system whose stream is up (a frozen process keeps it
  /// open): when the stream has been silent this long, or heartbeats stopped,
  /// health is probed every stall_probe_interval with a stall_probe_timeout
  /// deadline; failing for the grace period breaks the stream and the system
  /// is declared down.
  std::chrono::milliseconds silence{500};
  std::chrono::milliseconds stall_probe_interval{250};
  std::chrono::milliseconds stall_probe_timeout{300};
};

struct LinkIdentity {
  std::string robot_id;
  /// Empty for a --systems entry until the system is reached.
  std::string system;
  std::string address;
  v1::SystemSource source = v1::SYSTEM_SOURCE_UNSPECIFIED;
};

/// gRPC channel arguments for connections to behavior systems and to the
/// coordinator: reconnect within 100 ms .. 2 s (gRPC's default backoff grows
/// to 120 s, far longer than a restart takes).
grpc::ChannelArguments fastReconnectArguments();

class SystemLink {
 public:
  /// `on_retired` is called (on the link's thread) when a registered system
  /// unregistered and the link ended for good.
  SystemLink(LinkIdentity identity, FleetEventLog& log, CoordinatorMetrics& metrics,
             LinkOptions options, std::function<void(SystemLink*)> on_retired);
  /// Stops the thread.
  ~SystemLink();
  SystemLink(const SystemLink&) = delete;
  SystemLink& operator=(const SystemLink&) = delete;

  void start();
  /// Cancels whatever the thread waits for and joins it. Idempotent.
  void stop();

  /// A (re)registration: the system at `address` described itself with
  /// `description` (already checked against the request). A new address or
  /// incarnation makes the link reconnect at once.
  void registered(const std::string& address, const v1::ListBehaviorsResponse& description);
  /// Records a heartbeat of `incarnation`; false if it is not the registered
  /// incarnation.
  bool heartbeat(const std::string& incarnation);
  /// The system shuts down cleanly: read its events up to `final_seq`, then
  /// leave (registered systems are removed; configured ones stay listed and
  /// are contacted again). False if `incarnation` is not the registered one.
  bool unregister(const std::string& incarnation, uint64_t final_seq);

  const std::string& robotId() const { return robot_id_; }
  v1::SystemSource source() const { return source_; }
  std::string system() const;
  std::string address() const;
  std::string registeredIncarnation() const;
  v1::SystemState state() const;
  /// Unregistered and ended (registered systems only).
  bool retired() const;
  /// Unregistering: waiting for the last events.
  bool leaving() const;

  v1::SystemInfo info() const;
  /// Names of the hosted behaviors (empty before the first contact).
  std::vector<std::string> behaviorNames() const;
  bool hosts(const std::string& behavior) const;
  /// One hosted behavior as plans see it (no schema copied).
  struct BehaviorView {
    std::string name;
    /// The system is UP.
    bool system_up = false;
    /// ACTIVE, PAUSED or INACTIVE while tracked, UNSPECIFIED otherwise.
    v1::BehaviorState state = v1::BEHAVIOR_STATE_UNSPECIFIED;
    std::string activation_id;
  };
  /// Appends every hosted behavior's view.
  void viewBehaviors(std::vector<BehaviorView>* out) const;
  /// Appends the hosted behaviors matching `behavior` ("" for all).
  void describeBehaviors(const std::string& behavior,
                         google::protobuf::RepeatedPtrField<v1::FleetBehavior>* out) const;

  /// For routing a call: the stub, or nullptr with `status` UNAVAILABLE
  /// saying why the system cannot be used now.
  std::shared_ptr<v1::BehaviorSystem::Stub> stubForCall(grpc::Status* status) const;

 private:
  struct StreamEnd {
    /// Why the stream ended (or could not be used), for messages.
    std::string reason;
    bool got_start = false;
  };

  void run();
  // The watchdog thread.
  void watch();
  StreamEnd readStream(v1::BehaviorSystem::Stub& stub, const v1::WatchEventsRequest& request);
  bool onStart(const v1::WatchEventsStart& start, v1::BehaviorSystem::Stub& stub);
  // Events of the system's stream, in order (one message's worth).
  void onEvents(const std::vector<const v1::BehaviorEvent*>& events, grpc::ClientContext& context);
  // Returns true when the watchdog broke the stream (the system stopped
  // answering); `detail` then says why.
  bool onBroken(const std::string& reason, std::string* detail);
  void declareDown(const std::string& health_detail, bool stopped_answering = false);
  // Returns false when the link retired (the thread must end).
  bool finishLeaving();
  void deactivateFenced();

  // Register the context of the event stream, and of the other blocking call
  // in progress (nullptr when none), so that stop() and pokes can cancel them.
  void setStreamCall(grpc::ClientContext* context);
  void setCall(grpc::ClientContext* context);
  void setWatchCall(grpc::ClientContext* context);
  // Wakes the thread and cancels its call: something changed.
  void pokeLocked() ABSL_EXCLUSIVE_LOCKS_REQUIRED(mutex_);
  // Waits up to `duration` unless stopped or poked.
  void waitFor(std::chrono::milliseconds duration);
  void rebuildChannelLocked() ABSL_EXCLUSIVE_LOCKS_REQUIRED(mutex_);
  // Changes the state; returns the SystemStateChangedEvent to append (after
  // unlocking), if it changed.
  std::optional<v1::FleetEvent> setStateLocked(v1::SystemState state, std::string message)
      ABSL_EXCLUSIVE_LOCKS_REQUIRED(mutex_);
  v1::SystemInfo infoLocked() const ABSL_EXCLUSIVE_LOCKS_REQUIRED(mutex_);
  void append(std::vector<v1::FleetEvent> events);
  std::string nameLocked() const ABSL_EXCLUSIVE_LOCKS_REQUIRED(mutex_);

  mutable absl::Mutex mutex_;
  // system and address change at (re)registration and first contact.
  LinkIdentity identity_ ABSL_GUARDED_BY(mutex_);
  // identity_'s robot_id and source, which never change (read without the lock).
  const std::string robot_id_;
  const v1::SystemSource source_;
  FleetEventLog& log_;
  CoordinatorMetrics& metrics_;
  const LinkOptions options_;
  std::function<void(SystemLink*)> on_retired_;
  std::thread thread_;
  std::thread watch_thread_;
  bool stopping_ ABSL_GUARDED_BY(mutex_) = false;
  bool poked_ ABSL_GUARDED_BY(mutex_) = false;
  grpc::ClientContext* stream_call_ ABSL_GUARDED_BY(mutex_) = nullptr;
  grpc::ClientContext* call_ ABSL_GUARDED_BY(mutex_) = nullptr;
  grpc::ClientContext* watch_call_ ABSL_GUARDED_BY(mutex_) = nullptr;
  std::shared_ptr<grpc::Channel> channel_ ABSL_GUARDED_BY(mutex_);
  std::shared_ptr<v1::BehaviorSystem::Stub> stub_ ABSL_GUARDED_BY(mutex_);
  v1::ListBehaviorsResponse description_ ABSL_GUARDED_BY(mutex_);
  std::string registered_incarnation_ ABSL_GUARDED_BY(mutex_);
  v1::SystemState state_ ABSL_GUARDED_BY(mutex_) = v1::SYSTEM_STATE_UNSPECIFIED;
  std::string state_message_ ABSL_GUARDED_BY(mutex_);
  std::chrono::system_clock::time_point state_time_ ABSL_GUARDED_BY(mutex_);
  std::optional<std::chrono::system_clock::time_point> last_heartbeat_ ABSL_GUARDED_BY(mutex_);
  ActivationTracker tracker_ ABSL_GUARDED_BY(mutex_);
  // When the watchdog last probed an idle system for a silent stream.
  std::chrono::steady_clock::time_point last_silence_probe_ ABSL_GUARDED_BY(mutex_) = {};
  Supervision supervision_ ABSL_GUARDED_BY(mutex_);
  // Why the stream last ended, for messages.
  std::string last_break_ ABSL_GUARDED_BY(mutex_);
  // Why onStart refused the stream.
  std::string start_failure_ ABSL_GUARDED_BY(mutex_);
  // A stream was established before.
  bool had_stream_ ABSL_GUARDED_BY(mutex_) = false;
  // Counts established streams.
  uint64_t stream_generation_ ABSL_GUARDED_BY(mutex_) = 0;
  // Last message on the stream.
  std::chrono::steady_clock::time_point last_activity_ ABSL_GUARDED_BY(mutex_);
  // The watchdog broke the stream: no answer.
  bool stalled_ ABSL_GUARDED_BY(mutex_) = false;
  // Why, for messages.
  std::string stall_detail_ ABSL_GUARDED_BY(mutex_);
  // The fence check runs once the replay is through.
  uint64_t replay_end_seq_ ABSL_GUARDED_BY(mutex_) = 0;
  bool fence_check_pending_ ABSL_GUARDED_BY(mutex_) = false;
  bool leaving_ ABSL_GUARDED_BY(mutex_) = false;
  uint64_t final_seq_ ABSL_GUARDED_BY(mutex_) = 0;
  bool retired_ ABSL_GUARDED_BY(mutex_) = false;
};

}  // namespace behaviorlib::coordinator
