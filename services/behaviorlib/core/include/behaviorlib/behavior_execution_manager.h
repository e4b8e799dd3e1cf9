#pragma once

// A robot behavior that controls itself and manages its own execution (Molina
// et al., "Programming Robot Behaviors with Execution Management Functions").
// The behavior's author derives from Behavior<Params> (a BehaviorBase),
// overrides the paper's functions, and registers the class in a behavior
// system, which wraps it in its engine, the BehaviorExecutionManager:
//
//   class WaitBehavior final : public behaviorlib::Behavior<v1::WaitParameters> {
//    protected:
//     behaviorlib::Verdict checkGoal() override {
//       return activeTime() >= behaviorlib::seconds(parameters().duration_s())
//                  ? behaviorlib::Verdict::finish("waited")
//                  : behaviorlib::Verdict::keepGoing();
//     }
//   };
//
// Threading: every user function of one behavior is called on that behavior's
// own worker thread, one at a time, so user code needs no locking of its own
// state. Lifecycle calls (activate, deactivate, ...) may come from any thread;
// they are queued to the worker and complete through a callback. Data from
// other threads (channel samples, belief updates, a helper thread's result)
// reaches the behavior through onWorker(): the sample is handed over and the
// handler runs on the worker, between ticks.
//
// The tick (execute(), not overridable) runs, in this order:
//   1. checkProcesses()  -> PROCESS_FAILURE   (other checks rely on the processes)
//   2. checkSituation()  -> SITUATION_CHANGE  (the assumptions must hold before
//                                              a goal or progress verdict can be trusted)
//   3. checkGoal()       -> GOAL_ACHIEVED
//   4. checkProgress()   -> WRONG_PROGRESS
//   5. maximum_execution_time (active time only) -> TIME_OUT
//   6. onExecute()
// The first check that reports ends the activation with its cause: onDeactivate()
// runs and then the finished event is emitted. An exception from any user
// function ends the activation with PROCESS_FAILURE. Activation wakes the worker
// at once: the first tick (and onExecute) follows onActivate immediately.

#include <google/protobuf/empty.pb.h>
#include <google/protobuf/message.h>
#include <yaml-cpp/yaml.h>

#include <atomic>
#include <chrono>
#include <deque>
#include <functional>
#include <map>
#include <memory>
#include <optional>
#include <stdexcept>
#include <stop_token>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "absl/base/thread_annotations.h"
#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/synchronization/mutex.h"
#include "behaviorlib/clock.h"
#include "behaviorlib/event_log.h"
#include "behaviorlib/v1/behavior.pb.h"
#include "behaviorlib/v1/errors.pb.h"

namespace behaviorlib {

/// checkSituation()'s answer: do the behavior's assumptions hold, and how well
/// would it perform.
struct Situation {
  bool feasible = true;
  /// Estimated performance in [0, 1]; 1 is optimal.
  double performance_ratio = 1.0;
  /// Why, in words (mostly why the situation is not feasible).
  std::vector<std::string> reasons;
  /// The same reasons as codes (errors.proto), in the same order; a reason
  /// without a code reads as SITUATION_REASON_UNSPECIFIED.
  std::vector<v1::SituationReason> codes;

  static Situation ok(double performance_ratio = 1.0) { return {true, performance_ratio, {}, {}}; }
  static Situation infeasible(v1::SituationReason code, std::string reason) {
    return {false, 0.0, {std::move(reason)}, {code}};
  }
  [[deprecated(
      "give the reason a code: Situation::infeasible(v1::SITUATION_REASON_..., "
      "text)")]] static Situation
  infeasible(std::string reason) {
    return infeasible(v1::SITUATION_REASON_UNSPECIFIED, std::move(reason));
  }
  /// Adds a reason with its code (feasibility and ratio are left alone).
  void add(v1::SituationReason code, std::string reason) {
    codes.resize(reasons.size(), v1::SITUATION_REASON_UNSPECIFIED);
    reasons.push_back(std::move(reason));
    codes.push_back(code);
  }
  /// The code of reasons[i].
  v1::SituationReason code(size_t i) const {
    return i < codes.size() ? codes[i] : v1::SITUATION_REASON_UNSPECIFIED;
  }
};

/// The answer of checkGoal(), checkProgress() and checkProcesses(): keep going,
/// or finish the activation (with that function's termination cause) and say
/// why.
class Verdict {
 public:
  static Verdict keepGoing() { return Verdict(false, {}); }
  static Verdict finish(std::string message) { return Verdict(true, std::move(message)); }
  bool finishes() const { return finishes_; }
  const std::string& message() const { return message_; }

 private:
  Verdict(bool finishes, std::string message) : finishes_(finishes), message_(std::move(message)) {}
  bool finishes_;
  std::string message_;
};

/// Execution settings; the system's --config file may override them per
/// behavior (keys frequency_hz, maximum_execution_time_s, watchdog_timeout_s).
struct BehaviorOptions {
  /// Ticks per second of the behavior's clock while active.
  double frequency_hz = 100.0;
  /// Maximum active time before TIME_OUT; zero means none.
  Duration maximum_execution_time{0};
  /// Wall time a user function may run before the activation is ended with
  /// PROCESS_FAILURE.
  std::chrono::milliseconds watchdog_timeout{1000};
  /// A change of the performance ratio at least this large, while active,
  /// emits a situation-changed event.
  double situation_report_threshold = 0.1;
};

/// Receives the measurements the library makes (Prometheus in servers).
/// Called on the behavior's worker thread; must be cheap and non-blocking.
class BehaviorObserver {
 public:
  virtual ~BehaviorObserver() = default;
  /// An activation succeeded: `activate_call` is the wall time from the
  /// request's arrival until the activation was decided (checkSituation and
  /// onActivate included), the part of t3 before the first tick.
  virtual void onActivated(std::chrono::nanoseconds /*activate_call*/) {}
  /// Wall time from the activate request's arrival to the first onExecute
  /// (the paper's t3).
  virtual void onFirstExecute(std::chrono::nanoseconds /*activation_latency*/) {}
  virtual void onFinished(v1::TerminationCause /*cause*/) {}
  /// Time of the four monitoring functions of one tick (the paper's t1):
  /// wall time, and the CPU time of the thread that ran them (without the
  /// time it was preempted or waited).
  virtual void onMonitoring(std::chrono::nanoseconds /*wall*/, std::chrono::nanoseconds /*cpu*/) {}
  virtual void onSituation(double /*performance_ratio*/) {}
  /// The watchdog stopped a stuck user function (true); it returned (false).
  /// May be called from the watchdog thread.
  virtual void onBlocked(bool /*blocked*/) {}
};

/// What the hosting system gives a behavior when it starts.
struct BehaviorContext {
  const Clock* clock = nullptr;
  EventLog* events = nullptr;
  BehaviorObserver* observer = nullptr;  // optional
  std::string robot_id;
  /// This behavior's section of the --config file (may be null).
  YAML::Node config;
  /// The file it came from, for messages ("" when none).
  std::string config_file;
  /// Called (on the worker) when the behavior becomes active or inactive; the
  /// system's watchdog uses it to poll only while something runs.
  std::function<void(bool active)> on_active_changed;
  /// Optional: called on the worker before each command (activate,
  /// deactivate, ...) runs, and may block until the command may run at the
  /// current time (the deterministic mode's TimeFollower: a system that was
  /// idle is not waited for, so its clock may lag the simulation; the gate
  /// makes the simulator wait for it and brings its clock up to date first).
  /// While a command waits there the behavior counts as caught up but not
  /// idle.
  std::function<void()> before_command;
};

template <class T>
using Done = std::function<void(absl::StatusOr<T>)>;

/// How samples handed to a behavior's worker wait (onWorker()).
enum class Delivery {
  /// Only the newest undelivered sample waits (a pose, an image): a busy
  /// worker skips stale ones.
  kLatest,
  /// Every sample, in order (an IMU stream, messages), up to a capacity;
  /// beyond it the oldest waiting sample is dropped and counted.
  kEvery,
};

class BehaviorExecutionManager;

namespace detail {
/// Samples waiting for one onWorker() handler: any thread pushes, the
/// behavior's worker drains.
class Inbox {
 public:
  virtual ~Inbox() = default;
  /// Worker: calls the handler with every waiting sample.
  virtual void drain() = 0;
  /// Worker: drops what waits (its activation has ended).
  virtual void discard() = 0;
  /// The activation generation it belongs to; 0 for none (it outlives
  /// activations).
  virtual uint64_t generation() const = 0;
  /// Samples dropped because the inbox was full (Delivery::kEvery).
  virtual uint64_t dropped() const = 0;
};
}  // namespace detail

class BehaviorBase;
namespace detail {
/// The engine that holds `behavior` (tests, hosts; never behavior code).
/// Throws std::logic_error when no engine holds it yet.
BehaviorExecutionManager& engineOf(BehaviorBase& behavior);
}  // namespace detail

/// What a behavior's author derives from (through Behavior<Params>): the
/// paper's functions to override, and the helpers they may call on the
/// behavior's worker. The engine (BehaviorExecutionManager) that runs it,
/// with its threads, queues and locks, is the library's own.
class BehaviorBase {
 public:
  virtual ~BehaviorBase() = default;
  BehaviorBase(const BehaviorBase&) = delete;
  BehaviorBase& operator=(const BehaviorBase&) = delete;

  const std::string& name() const { return name_; }
  const google::protobuf::Descriptor& parametersType() const { return *parameters_type_; }

 protected:
  BehaviorBase(std::string name, const google::protobuf::Descriptor* parameters_type,
               BehaviorOptions options);

  // ---- Activation management (the paper's table) ---------------------------
  /// Prepares an activation; parameters() are set. An error refuses it.
  virtual absl::Status onActivate() { return absl::OkStatus(); }
  /// One step of the behavior's control.
  virtual void onExecute() {}
  /// Leaves a safe, stable state; releases what onActivate acquired.
  virtual void onDeactivate() {}

  // ---- Execution monitoring (the paper's table) ----------------------------
  virtual Situation checkSituation() { return Situation::ok(); }
  virtual Verdict checkGoal() { return Verdict::keepGoing(); }
  virtual Verdict checkProgress() { return Verdict::keepGoing(); }
  virtual Verdict checkProcesses() { return Verdict::keepGoing(); }

  // ---- Beyond the paper ----------------------------------------------------
  /// Paused: a motion behavior should hold position here.
  virtual void onPause() {}
  virtual void onResume() {}
  // (onModify is typed: Behavior<Params>::onModify(const Params&).)

  // ---- For subclasses (worker thread) --------------------------------------
  const Clock& clock() const;
  TimePoint now() const;
  /// Active (not paused) time of the current activation.
  Duration activeTime() const;
  const google::protobuf::Message& parametersMessage() const;
  const std::string& activationId() const;
  const std::string& robotId() const;
  /// Options after configuration.
  const BehaviorOptions& options() const;

  /// A callback that any thread may call (a channel subscription's reader, a
  /// belief watch, a helper thread): it copies the sample, and `handler` runs
  /// with it on this behavior's worker, between ticks, like every other user
  /// function. Behavior state therefore needs no lock. Made during an
  /// activation (onActivate, a tick), its samples that are still waiting when
  /// that activation ends are dropped; made outside one (onConfigure), it
  /// delivers whenever. An exception from `handler` ends an activation with
  /// PROCESS_FAILURE; the watchdog watches it as any user function.
  /// `capacity` bounds the waiting samples of Delivery::kEvery.
  template <class T>
  std::function<void(const T&)> onWorker(std::function<void(const T&)> handler,
                                         Delivery delivery = Delivery::kEvery,
                                         size_t capacity = 1024);

  /// Runs `job` on this behavior's background thread (one per behavior,
  /// started on first use; jobs run one at a time, in order), then `done`
  /// with its result on the worker, as onWorker() delivers. For work too
  /// long for a tick: decoding an image, planning, a slow remote call. The
  /// job gets copies (or sole ownership) of what it reads and writes, and
  /// leaves the behavior's state alone. The result of an ended activation is
  /// dropped; an exception from the job ends the activation with
  /// PROCESS_FAILURE. stop() waits for the running job. Worker thread.
  template <class R>
  void inBackground(std::function<R()> job, std::function<void(const R&)> done);
  /// inBackground() for a job that may be called off: it gets a
  /// std::stop_token and looks at it where stopping is worth it (before a
  /// long step, before writing an output). The returned std::stop_source
  /// calls it off (a newer job superseding it, say); the end of the
  /// activation calls off every job it started. A called-off job's result
  /// is dropped: `done` does not see it. Worker thread.
  template <class R>
  std::stop_source inBackground(std::function<R(std::stop_token)> job,
                                std::function<void(const R&)> done);
  /// Overrides maximum_execution_time for the current activation (e.g. from
  /// its parameters, in onActivate()); zero means none. `reason`, when not
  /// empty, is the TIME_OUT's message instead of the library's (e.g. a
  /// behavior that ends itself through the time-out says why).
  void setMaximumExecutionTime(Duration d, std::string reason = {});

 private:
  friend class BehaviorExecutionManager;
  friend BehaviorExecutionManager& detail::engineOf(BehaviorBase& behavior);
  // The engine that holds it; throws std::logic_error before one does (a
  // helper called from a constructor).
  BehaviorExecutionManager& engine() const;

  /// New parameters are about to take effect; an error refuses them.
  /// Behavior<Params> overrides it with the typed onModify(const Params&).
  virtual absl::Status modifyParameters(const google::protobuf::Message& new_parameters) = 0;
  /// An empty message of the behavior's configuration type.
  virtual std::unique_ptr<google::protobuf::Message> newConfiguration() const = 0;
  /// The decoded, checked configuration; Behavior<Params, Config> overrides
  /// it with the typed onConfigure(const Config&).
  virtual absl::Status configure(const google::protobuf::Message& configuration) = 0;

  const std::string name_;
  const google::protobuf::Descriptor* const parameters_type_;
  const BehaviorOptions initial_options_;
  BehaviorExecutionManager* engine_ = nullptr;
};

/// The engine of one behavior: it holds the behavior (a BehaviorBase), runs
/// its functions on the behavior's own worker thread, and serves the uniform
/// interface to the host. Behavior authors never see it: their class derives
/// from Behavior<Params>, and a host (BehaviorHost, a behavior system) wraps
/// it in an engine.
class BehaviorExecutionManager final {
 public:
  /// Holds `behavior` (not null).
  explicit BehaviorExecutionManager(std::unique_ptr<BehaviorBase> behavior);
  BehaviorExecutionManager(const BehaviorExecutionManager&) = delete;
  BehaviorExecutionManager& operator=(const BehaviorExecutionManager&) = delete;
  /// The host must call stop() before destroying a started behavior.
  ~BehaviorExecutionManager();

  /// The behavior it holds.
  BehaviorBase& behavior() { return *behavior_; }
  const BehaviorBase& behavior() const { return *behavior_; }

  const std::string& name() const { return behavior_->name(); }
  const google::protobuf::Descriptor& parametersType() const { return behavior_->parametersType(); }
  /// Options after configuration.
  const BehaviorOptions& options() const { return options_; }
  /// The behavior's configuration message (its keys beside the library's
  /// ExecutionConfig; decision 45).
  const google::protobuf::Descriptor& configurationType() const {
    return *behavior_->newConfiguration()->GetDescriptor();
  }

  // ---- Host interface ------------------------------------------------------

  /// Applies the config overrides, starts the worker and runs onConfigure() on
  /// it; an error from onConfigure is returned and the behavior stays stopped.
  absl::Status start(BehaviorContext context);
  /// Ends an active activation with INTERRUPTED ("process shutting down"),
  /// emits its event and joins the worker (waits at most `timeout` for a
  /// worker stuck in user code, then leaves it).
  void stop(std::chrono::milliseconds timeout = std::chrono::seconds(3));

  /// Called by the system watchdog (any thread): ends the activation with
  /// PROCESS_FAILURE if a user function has run longer than the watchdog
  /// timeout at `now`.
  void watchdogCheck(std::chrono::steady_clock::time_point now);

  // ---- Uniform interface (thread-safe; completions run on the worker) ------

  /// Validates `parameters` (defaults, ranges; INVALID_ARGUMENT naming the
  /// field), then on the worker: replays a known `request_id`; refuses when
  /// already active or the situation is infeasible (FAILED_PRECONDITION);
  /// runs onActivate(); emits the activated event; replies; and runs the
  /// first tick at once. `received` is when the request arrived (for t3).
  void activate(std::unique_ptr<google::protobuf::Message> parameters, std::string request_id,
                Done<v1::ActivateResponse> done,
                std::chrono::steady_clock::time_point received = std::chrono::steady_clock::now());
  /// Ends the activation with INTERRUPTED. ABORTED when `activation_id` is
  /// set but is not the current activation (except a finished one while
  /// nothing else runs: success with already_finished).
  void deactivate(std::string activation_id, Done<v1::DeactivateResponse> done);
  void pause(std::string activation_id, Done<v1::PauseResponse> done);
  void resume(std::string activation_id, Done<v1::ResumeResponse> done);
  /// Applies the set fields of `update` over the current parameters
  /// (params::mergeUpdate), validates, and calls onModify().
  void modify(std::string activation_id, std::unique_ptr<google::protobuf::Message> update,
              Done<v1::ModifyResponse> done);
  /// Runs checkSituation() on the worker.
  void checkSituationNow(Done<v1::CheckSituationResponse> done);
  /// Whether everything due up to `t` on the behavior's clock has run: no
  /// command waits or runs, and an active behavior is not ticking and has its
  /// next tick after `t` (the deterministic mode's catch-up report). A
  /// command held at the time gate (BehaviorContext::before_command) waits
  /// for time, so it counts as caught up.
  bool caughtUp(TimePoint t) const;
  /// Whether nothing runs until a call from outside: no command waits or
  /// runs (at the time gate or beyond), no tick runs, and the behavior is not
  /// active (the deterministic mode does
  /// not wait for an idle system).
  bool idle() const;
  /// Reads the current activation state (no user code; immediate).
  v1::CheckActivationResponse checkActivation() const;
  v1::BehaviorState state() const;

  // Blocking conveniences (tests, tools); wait at most `timeout` wall time.
  absl::StatusOr<v1::ActivateResponse> activateAndWait(
      std::unique_ptr<google::protobuf::Message> parameters, std::string request_id = {},
      std::chrono::milliseconds timeout = std::chrono::seconds(5));
  absl::StatusOr<v1::DeactivateResponse> deactivateAndWait(
      std::string activation_id = {}, std::chrono::milliseconds timeout = std::chrono::seconds(5));
  absl::StatusOr<v1::PauseResponse> pauseAndWait(std::string activation_id = {});
  absl::StatusOr<v1::ResumeResponse> resumeAndWait(std::string activation_id = {});
  absl::StatusOr<v1::ModifyResponse> modifyAndWait(
      std::unique_ptr<google::protobuf::Message> update, std::string activation_id = {});
  absl::StatusOr<v1::CheckSituationResponse> checkSituationAndWait();

  /// One monitoring tick: the four checks, the time-out, then onExecute().
  /// Driven by the worker; not overridable (the paper's execute()).
  void execute();

  /// How long request_ids are remembered for idempotent Activate.
  static constexpr std::chrono::minutes kRequestIdWindow{10};
  /// How many finished activation ids are remembered (for Deactivate replies).
  static constexpr size_t kFinishedRemembered = 64;

 private:
  friend class BehaviorBase;
  // ---- What BehaviorBase's helpers read (the behavior's worker) ------------
  const Clock& clock() const { return *context_.clock; }
  TimePoint now() const { return context_.clock->now(); }
  Duration activeTime() const;
  const google::protobuf::Message& parametersMessage() const { return *parameters_; }
  const std::string& activationId() const { return activation_id_; }
  template <class T>
  std::function<void(const T&)> onWorker(std::function<void(const T&)> handler,
                                         Delivery delivery = Delivery::kEvery,
                                         size_t capacity = 1024);
  template <class R>
  void inBackground(std::function<R()> job, std::function<void(const R&)> done);
  template <class R>
  std::stop_source inBackground(std::function<R(std::stop_token)> job,
                                std::function<void(const R&)> done);
  const std::string& robotId() const { return context_.robot_id; }
  void setMaximumExecutionTime(Duration d, std::string reason) {
    maximum_execution_time_ = d;
    time_out_reason_ = std::move(reason);
  }

  enum class State { kInactive, kActive, kPaused, kBlocked };
  struct Finished {
    std::string activation_id;
    v1::TerminationCause cause;
  };

  class WakeOnClock;
  class Background;
  template <class T>
  class SampleInbox;
  // Queues `task` for the background thread (started on first use).
  void runInBackground(std::function<void()> task);
  void run();
  // Decodes the section's keys (the library's, and the behavior's when it
  // declares a configuration message) and applies the library's to options_.
  absl::Status readExecutionConfig();
  // Any thread: queues `inbox` for the worker to drain (once per push
  // burst; the inbox keeps its own scheduled flag).
  void schedule(std::shared_ptr<detail::Inbox> inbox);
  // The generation an inbox made now belongs to (0 outside activations).
  uint64_t inboxGeneration() const;
  // Worker: drains one ready inbox (lock not held).
  void deliver(const std::shared_ptr<detail::Inbox>& inbox);
  // Queues `command` for the worker; if the worker has stopped (or stops
  // before running it), `cancel` runs instead so that every caller gets an
  // answer.
  void post(std::function<void()> command, std::function<void()> cancel);
  template <class T>
  static std::function<void()> cancelWith(const Done<T>& done, const std::string& name);
  // Ends the current activation (worker thread, lock not held).
  void finish(v1::TerminationCause cause, const std::string& message);
  // Emits the finished event and bookkeeping (lock held).
  void recordFinishedLocked(v1::TerminationCause cause, const std::string& message);
  v1::BehaviorEvent newEventLocked() const;
  Duration activeTimeLocked(TimePoint now) const;
  template <class F>
  bool guarded(const char* function, F&& f);  // runs user code; false if it threw
  // Runs a lifecycle hook; if it fails, ends the activation with
  // PROCESS_FAILURE and replies ABORTED. False then.
  template <class F>
  bool hookOrAbort(const char* function, F&& hook, const std::function<void(absl::Status)>& reply);
  void doActivate(std::unique_ptr<google::protobuf::Message> parameters,
                  const std::string& request_id, std::chrono::steady_clock::time_point received,
                  const Done<v1::ActivateResponse>& done);
  void reportActive(bool active);
  // True (after calling `reply` with FAILED_PRECONDITION) while blocked.
  bool refuseWhileBlocked(const std::function<void(absl::Status)>& reply);
  absl::Status checkActivationIdLocked(const std::string& activation_id, const char* verb) const;

  BehaviorOptions options_;
  BehaviorContext context_;
  // The behavior's decoded configuration (null when it declares no message);
  // set by start() before the worker exists, read only by it afterwards.
  std::unique_ptr<google::protobuf::Message> configuration_;
  std::unique_ptr<WakeOnClock> clock_listener_;
  // The worker waits on mutex_ (Mutex::Await) for a command, an inbox,
  // stopping_, or a wake from the clock (wakes_ counts them).
  mutable absl::Mutex mutex_;
  std::unique_ptr<Background> background_ ABSL_GUARDED_BY(mutex_);  // created on first use
  struct Command {
    std::function<void()> run;
    std::function<void()> cancel;
  };
  std::deque<Command> commands_ ABSL_GUARDED_BY(mutex_);
  // Inboxes with samples for the worker.
  std::deque<std::shared_ptr<detail::Inbox>> ready_ ABSL_GUARDED_BY(mutex_);
  // Changes when an activation starts or ends; onWorker() inboxes of an
  // ended activation are discarded.
  uint64_t generation_ ABSL_GUARDED_BY(mutex_) = 1;
  bool stopping_ ABSL_GUARDED_BY(mutex_) = false;
  bool exited_ ABSL_GUARDED_BY(mutex_) = false;
  uint64_t wakes_ ABSL_GUARDED_BY(mutex_) = 0;
  std::thread worker_;

  // Activation state: written on the worker under mutex_ (state_ also by the
  // watchdog, which marks a stuck call kBlocked); the worker's own code reads
  // it without the lock, user code through activeTime() with it.
  State state_ = State::kInactive;
  std::string activation_id_;
  std::unique_ptr<google::protobuf::Message> parameters_;
  TimePoint activation_time_{};
  TimePoint active_since_{};
  Duration active_accumulated_{0};
  Duration maximum_execution_time_{0};
  std::string time_out_reason_;
  TimePoint next_tick_{};
  bool ticking_ ABSL_GUARDED_BY(mutex_) = false;  // the worker runs a tick
  // The worker holds a command at the time gate (before_command), or runs
  // one.
  bool gated_ ABSL_GUARDED_BY(mutex_) = false;
  bool commanding_ ABSL_GUARDED_BY(mutex_) = false;
  Duration period_{0};
  bool first_execute_pending_ = false;
  std::chrono::steady_clock::time_point activate_received_{};
  double reported_performance_ = 1.0;
  std::vector<std::string> reported_reasons_;
  std::vector<v1::SituationReason> reported_codes_;
  uint64_t activation_counter_ = 0;
  std::atomic<bool> wants_ticks_{false};
  // Calls off the cancellable background jobs of the activation when it
  // ends (worker thread only).
  std::stop_source activation_jobs_;
  void callOffBackgroundJobs();

  // Failure reported from user code (exception) during the current call, and
  // whether the watchdog had stopped it (worker thread only).
  std::string failure_message_;
  bool stopped_by_watchdog_ = false;

  // Watchdog: steady-clock ns when the current user call started (0: none;
  // kWatchdogFired: the watchdog ended the activation while the call ran).
  static constexpr int64_t kWatchdogFired = -1;
  std::atomic<int64_t> call_started_ns_{0};
  std::atomic<const char*> call_function_{nullptr};

  std::map<std::string, std::pair<v1::ActivateResponse, std::chrono::steady_clock::time_point>>
      request_ids_;
  std::deque<std::pair<std::chrono::steady_clock::time_point, std::string>> request_id_order_;
  std::deque<Finished> finished_;
  // Last: the behavior's own state goes first, before the engine's.
  std::unique_ptr<BehaviorBase> behavior_;
};

template <class T>
class BehaviorExecutionManager::SampleInbox final
    : public detail::Inbox,
      public std::enable_shared_from_this<SampleInbox<T>> {
 public:
  SampleInbox(BehaviorExecutionManager* owner, std::function<void(const T&)> handler,
              Delivery delivery, size_t capacity, uint64_t generation)
      : owner_(owner),
        handler_(std::move(handler)),
        delivery_(delivery),
        capacity_(capacity == 0 ? 1 : capacity),
        generation_(generation) {}

  void push(const T& sample) {
    bool schedule = false;
    {
      absl::MutexLock lock(&mutex_);
      if (delivery_ == Delivery::kLatest) {
        waiting_.clear();
      } else if (waiting_.size() >= capacity_) {
        waiting_.pop_front();
        ++dropped_;
      }
      waiting_.push_back(sample);
      schedule = !scheduled_;
      scheduled_ = true;
    }
    if (schedule) owner_->schedule(this->shared_from_this());
  }
  void drain() override {
    for (const T& sample : take()) handler_(sample);
  }
  void discard() override { take(); }
  uint64_t generation() const override { return generation_; }
  uint64_t dropped() const override {
    absl::MutexLock lock(&mutex_);
    return dropped_;
  }

 private:
  std::deque<T> take() {
    absl::MutexLock lock(&mutex_);
    scheduled_ = false;
    return std::exchange(waiting_, {});
  }

  BehaviorExecutionManager* const owner_;
  const std::function<void(const T&)> handler_;
  const Delivery delivery_;
  const size_t capacity_;
  const uint64_t generation_;
  mutable absl::Mutex mutex_;
  std::deque<T> waiting_ ABSL_GUARDED_BY(mutex_);
  bool scheduled_ ABSL_GUARDED_BY(mutex_) = false;
  uint64_t dropped_ ABSL_GUARDED_BY(mutex_) = 0;
};

template <class T>
std::function<void(const T&)> BehaviorExecutionManager::onWorker(
    std::function<void(const T&)> handler, Delivery delivery, size_t capacity) {
  auto inbox = std::make_shared<SampleInbox<T>>(this, std::move(handler), delivery, capacity,
                                                inboxGeneration());
  return [inbox](const T& sample) { inbox->push(sample); };
}

template <class R>
void BehaviorExecutionManager::inBackground(std::function<R()> job,
                                            std::function<void(const R&)> done) {
  auto deliver = onWorker<R>(std::move(done));
  auto fail =
      onWorker<std::string>([](const std::string& what) { throw std::runtime_error(what); });
  runInBackground([job = std::move(job), deliver = std::move(deliver), fail = std::move(fail)] {
    std::optional<R> result;
    try {
      result.emplace(job());
    } catch (const std::exception& e) {
      fail(std::string("a background job threw: ") + e.what());
      return;
    } catch (...) {
      fail("a background job threw a non-standard exception");
      return;
    }
    deliver(*result);
  });
}

template <class R>
std::stop_source BehaviorExecutionManager::inBackground(std::function<R(std::stop_token)> job,
                                                        std::function<void(const R&)> done) {
  std::stop_source stop;
  // The job's own source, stopped too when the activation's is: the link
  // lives as long as the job (it is part of the job's closure).
  auto call_off = [stop]() mutable { stop.request_stop(); };
  auto link = std::make_shared<std::stop_callback<decltype(call_off)>>(activation_jobs_.get_token(),
                                                                       std::move(call_off));
  inBackground<R>([job = std::move(job), token = stop.get_token(), link] { return job(token); },
                  [done = std::move(done), token = stop.get_token()](const R& result) {
                    if (!token.stop_requested()) done(result);
                  });
  return stop;
}

inline BehaviorExecutionManager& BehaviorBase::engine() const {
  if (engine_ == nullptr) {
    throw std::logic_error("behavior " + name_ +
                           ": no engine holds it yet (a helper was called from its constructor; "
                           "use onConfigure)");
  }
  return *engine_;
}
inline const Clock& BehaviorBase::clock() const { return engine().clock(); }
inline TimePoint BehaviorBase::now() const { return engine().now(); }
inline Duration BehaviorBase::activeTime() const { return engine().activeTime(); }
inline const google::protobuf::Message& BehaviorBase::parametersMessage() const {
  return engine().parametersMessage();
}
inline const std::string& BehaviorBase::activationId() const { return engine().activationId(); }
inline const std::string& BehaviorBase::robotId() const { return engine().robotId(); }
inline const BehaviorOptions& BehaviorBase::options() const { return engine().options(); }
inline void BehaviorBase::setMaximumExecutionTime(Duration d, std::string reason) {
  engine().setMaximumExecutionTime(d, std::move(reason));
}
template <class T>
std::function<void(const T&)> BehaviorBase::onWorker(std::function<void(const T&)> handler,
                                                     Delivery delivery, size_t capacity) {
  return engine().template onWorker<T>(std::move(handler), delivery, capacity);
}
template <class R>
void BehaviorBase::inBackground(std::function<R()> job, std::function<void(const R&)> done) {
  engine().template inBackground<R>(std::move(job), std::move(done));
}
template <class R>
std::stop_source BehaviorBase::inBackground(std::function<R(std::stop_token)> job,
                                            std::function<void(const R&)> done) {
  return engine().template inBackground<R>(std::move(job), std::move(done));
}

/// The name of the behavior that `parameters` declares with the
/// (behaviorlib.v1.declare) option, or "" when it declares none.
std::string declaredBehaviorName(const google::protobuf::Descriptor* parameters);

namespace detail {
// The declared name; throws std::logic_error when there is none.
std::string requireDeclaredName(const google::protobuf::Descriptor* parameters);
}  // namespace detail

/// A behavior with a typed parameter message and a typed configuration
/// message (decision 45): the keys of its section of --config beside the
/// library's. A behavior without keys of its own keeps the default, Empty,
/// and any other key in its section is refused.
template <class Params, class Config = google::protobuf::Empty>
class Behavior : public BehaviorBase {
 public:
  using Parameters = Params;
  /// The behavior that Params declares (its name comes from the proto).
  /// Throws std::logic_error when Params declares none.
  explicit Behavior(BehaviorOptions options = {})
      : BehaviorBase(detail::requireDeclaredName(Params::descriptor()), Params::descriptor(),
                     options) {}
  /// A behavior named here, served only through the generic BehaviorSystem
  /// service (tests, tools: a test behavior may borrow WAIT's parameters).
  /// BehaviorSystemBuilder::add<> refuses a typed service of another name.
  explicit Behavior(std::string name, BehaviorOptions options = {})
      : BehaviorBase(std::move(name), Params::descriptor(), options) {}

 protected:
  /// The current activation's parameters (defaults applied, validated).
  const Params& parameters() const { return static_cast<const Params&>(parametersMessage()); }
  /// Modify: `new_parameters` (the current ones with the update's set
  /// fields, defaults applied, validated) are about to take effect; an error
  /// refuses them and the current ones stay.
  virtual absl::Status onModify(const Params& /*new_parameters*/) { return absl::OkStatus(); }
  /// Reads the behavior's configuration: its section of --config, decoded
  /// into Config, defaults applied and checked (an unknown key, a value of
  /// the wrong type or out of range stops the system at start, naming the
  /// file and line). Runs once, on the worker, before any activation; an
  /// error stops the system at start.
  virtual absl::Status onConfigure(const Config& /*config*/) { return absl::OkStatus(); }

 private:
  absl::Status modifyParameters(const google::protobuf::Message& new_parameters) final {
    return onModify(static_cast<const Params&>(new_parameters));
  }
  std::unique_ptr<google::protobuf::Message> newConfiguration() const final {
    return std::make_unique<Config>();
  }
  absl::Status configure(const google::protobuf::Message& configuration) final {
    return onConfigure(static_cast<const Config&>(configuration));
  }
};

/// A TerminationCause's short name ("GOAL_ACHIEVED").
std::string causeName(v1::TerminationCause cause);

}  // namespace behaviorlib
