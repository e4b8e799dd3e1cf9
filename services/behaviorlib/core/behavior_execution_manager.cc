#include "behaviorlib/behavior_execution_manager.h"

#include <google/protobuf/util/time_util.h>
#include <time.h>

#include <cmath>
#include <future>
#include <optional>
#include <sstream>
#include <stdexcept>

#include "behaviorlib/config/v1/execution.pb.h"
#include "behaviorlib/configuration.h"
#include "behaviorlib/errors/status_details.h"
#include "behaviorlib/parameters.h"
#include "behaviorlib/v1/options.pb.h"

namespace behaviorlib {
namespace {

using google::protobuf::util::TimeUtil;
using SteadyTime = std::chrono::steady_clock::time_point;

int64_t steadyNs(SteadyTime t) {
  return std::chrono::duration_cast<std::chrono::nanoseconds>(t.time_since_epoch()).count();
}

google::protobuf::Timestamp toTimestamp(TimePoint t) {
  return TimeUtil::NanosecondsToTimestamp(t.time_since_epoch().count());
}

google::protobuf::Duration toProtoDuration(Duration d) {
  return TimeUtil::NanosecondsToDuration(d.count());
}

std::string secondsText(Duration d) {
  std::ostringstream out;
  out << std::chrono::duration<double>(d).count() << " s";
  return out.str();
}

std::string joinReasons(const std::vector<std::string>& reasons) {
  std::string out;
  for (const auto& r : reasons) {
    if (!out.empty()) out += "; ";
    out += r;
  }
  return out.empty() ? "no reason given" : out;
}

// The situation's codes, comma-separated (ErrorInfo metadata).
std::string codeNames(const Situation& situation) {
  std::string out;
  for (size_t i = 0; i < situation.reasons.size(); ++i) {
    if (!out.empty()) out += ",";
    out += v1::SituationReason_Name(situation.code(i));
  }
  return out;
}

// A parameter refusal of params:: (its field violations name the parameter
// inside the message): a reason, the behavior, and the request's field path.
absl::Status parameterError(absl::Status status, const std::string& behavior) {
  status = errors::prefixFieldViolations(std::move(status), "parameters.");
  return errors::withDefaultReason(std::move(status), v1::PARAMETER_INVALID,
                                   {{"behavior", behavior}});
}

// Every reason of `situation`, with its code, into a response or event.
template <class Message>
void addReasons(const Situation& situation, Message* out) {
  for (size_t i = 0; i < situation.reasons.size(); ++i) {
    out->add_reasons(situation.reasons[i]);
    out->add_reason_codes(situation.code(i));
  }
}

template <class T>
absl::StatusOr<T> waitFor(const std::function<void(Done<T>)>& start,
                          std::chrono::milliseconds timeout) {
  auto promise = std::make_shared<std::promise<absl::StatusOr<T>>>();
  auto future = promise->get_future();
  start([promise](absl::StatusOr<T> result) { promise->set_value(std::move(result)); });
  if (future.wait_for(timeout) != std::future_status::ready) {
    return errors::withReason(
        absl::DeadlineExceededError("the behavior did not answer in time (blocked user code?)"),
        v1::BEHAVIOR_UNRESPONSIVE);
  }
  return future.get();
}

// Moves a shared message's content into a new owned one.
std::unique_ptr<google::protobuf::Message> takeMessage(google::protobuf::Message& from) {
  std::unique_ptr<google::protobuf::Message> out(from.New());
  out->GetReflection()->Swap(out.get(), &from);
  return out;
}

// CPU time of the calling thread: the monitoring functions' own cost, which
// a preempted or waiting thread does not accrue (wall time does).
std::chrono::nanoseconds threadCpuTime() {
  timespec now{};
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &now);
  return std::chrono::seconds(now.tv_sec) + std::chrono::nanoseconds(now.tv_nsec);
}

}  // namespace

bool BehaviorExecutionManager::caughtUp(TimePoint t) const {
  absl::MutexLock lock(&mutex_);
  if (gated_) return true;  // the command waits for time to be granted
  if (!commands_.empty() || commanding_ || ticking_) return false;
  return state_ != State::kActive || next_tick_ > t;
}

bool BehaviorExecutionManager::idle() const {
  absl::MutexLock lock(&mutex_);
  return commands_.empty() && !gated_ && !commanding_ && !ticking_ && state_ != State::kActive;
}

std::string causeName(v1::TerminationCause cause) {
  std::string name = v1::TerminationCause_Name(cause);
  constexpr std::string_view kPrefix = "TERMINATION_CAUSE_";
  return name.rfind(kPrefix, 0) == 0 ? name.substr(kPrefix.size()) : name;
}

// Wakes the worker when simulated or fake time reaches the next tick.
class BehaviorExecutionManager::WakeOnClock final : public ClockListener {
 public:
  explicit WakeOnClock(BehaviorExecutionManager* owner) : owner_(owner) {}
  void onClockAdvanced() override {
    if (!owner_->wants_ticks_.load(std::memory_order_acquire)) return;
    absl::MutexLock lock(&owner_->mutex_);
    ++owner_->wakes_;
  }

 private:
  BehaviorExecutionManager* owner_;
};

// The background thread of inBackground(): runs queued tasks in order.
class BehaviorExecutionManager::Background {
 public:
  Background() : thread_([this] { run(); }) {}
  ~Background() { stop(); }
  void post(std::function<void()> task) {
    absl::MutexLock lock(&mutex_);
    if (stopping_) return;
    tasks_.push_back(std::move(task));
  }
  // Waits for the running task; drops the queued ones.
  void stop() {
    {
      absl::MutexLock lock(&mutex_);
      stopping_ = true;
    }
    if (thread_.joinable()) thread_.join();
  }

 private:
  void run() {
    while (true) {
      std::function<void()> task;
      {
        absl::MutexLock lock(&mutex_);
        mutex_.Await(absl::Condition(this, &Background::hasWorkLocked));
        if (stopping_) return;
        task = std::move(tasks_.front());
        tasks_.pop_front();
      }
      task();
    }
  }

  bool hasWorkLocked() const ABSL_EXCLUSIVE_LOCKS_REQUIRED(mutex_) {
    return stopping_ || !tasks_.empty();
  }

  absl::Mutex mutex_;
  std::deque<std::function<void()>> tasks_ ABSL_GUARDED_BY(mutex_);
  bool stopping_ ABSL_GUARDED_BY(mutex_) = false;
  std::thread thread_;
};

void BehaviorExecutionManager::runInBackground(std::function<void()> task) {
  Background* background;
  {
    absl::MutexLock lock(&mutex_);
    if (!background_) background_ = std::make_unique<Background>();
    background = background_.get();
  }
  background->post(std::move(task));
}

BehaviorBase::BehaviorBase(std::string name, const google::protobuf::Descriptor* parameters_type,
                           BehaviorOptions options)
    : name_(std::move(name)), parameters_type_(parameters_type), initial_options_(options) {}

namespace detail {
BehaviorExecutionManager& engineOf(BehaviorBase& behavior) { return behavior.engine(); }
}  // namespace detail

BehaviorExecutionManager::BehaviorExecutionManager(std::unique_ptr<BehaviorBase> behavior)
    : options_(behavior ? behavior->initial_options_ : BehaviorOptions{}),
      behavior_(std::move(behavior)) {
  if (!behavior_) throw std::logic_error("a BehaviorExecutionManager needs a behavior");
  if (behavior_->engine_ != nullptr) {
    throw std::logic_error("behavior " + name() + " is already held by an engine");
  }
  behavior_->engine_ = this;
}

BehaviorExecutionManager::~BehaviorExecutionManager() {
  if (worker_.joinable()) worker_.detach();  // stop() was not called: a host bug
}

absl::Status BehaviorExecutionManager::readExecutionConfig() {
  // The section's every key is the library's or the behavior's: decoded,
  // defaults applied and checked before the worker starts.
  config::v1::ExecutionConfig execution;
  const config::Source source{context_.config_file, "behaviors." + name()};
  if (absl::Status s = config::decode(context_.config, source, {&execution, configuration_.get()});
      !s.ok()) {
    return s;
  }
  if (execution.has_frequency_hz()) options_.frequency_hz = execution.frequency_hz();
  if (execution.has_maximum_execution_time_s()) {
    options_.maximum_execution_time = seconds(execution.maximum_execution_time_s());
  }
  if (execution.has_watchdog_timeout_s()) {
    options_.watchdog_timeout = std::chrono::milliseconds(
        static_cast<int64_t>(std::llround(execution.watchdog_timeout_s() * 1000.0)));
  }
  return absl::OkStatus();
}

absl::Status BehaviorExecutionManager::start(BehaviorContext context) {
  if (!context.clock || !context.events) {
    return absl::InvalidArgumentError("behavior " + name() + " needs a clock and an event log");
  }
  context_ = std::move(context);
  configuration_ = behavior_->newConfiguration();
  if (absl::Status s = readExecutionConfig(); !s.ok()) return s;
  if (!(options_.frequency_hz > 0.0 && options_.frequency_hz <= 10000.0)) {
    return absl::InvalidArgumentError("configuration of " + name() +
                                      ": frequency_hz must be in (0, 10000]");
  }
  if (options_.watchdog_timeout <= std::chrono::milliseconds(0)) {
    return absl::InvalidArgumentError("configuration of " + name() +
                                      ": watchdog_timeout_s must be positive");
  }
  period_ = Duration(static_cast<int64_t>(std::llround(1e9 / options_.frequency_hz)));
  clock_listener_ = std::make_unique<WakeOnClock>(this);
  context_.clock->addListener(clock_listener_.get());
  worker_ = std::thread([this] { run(); });

  auto configured = waitFor<bool>(
      [this](Done<bool> done) {
        post(
            [this, done] {
              absl::Status status;
              if (!guarded("onConfigure",
                           [&] { status = behavior_->configure(*configuration_); })) {
                status = absl::InternalError(failure_message_);
              }
              if (status.ok()) {
                done(true);
              } else {
                done(status);
              }
            },
            cancelWith(done, name()));
      },
      std::chrono::seconds(60));
  if (!configured.ok()) {
    stop();
    return configured.status();
  }
  return absl::OkStatus();
}

void BehaviorExecutionManager::stop(std::chrono::milliseconds timeout) {
  if (!worker_.joinable()) return;
  post(
      [this] {
        State state;
        {
          absl::ReleasableMutexLock lock(&mutex_);
          state = state_;
        }
        if (state == State::kActive || state == State::kPaused) {
          finish(v1::TERMINATION_CAUSE_INTERRUPTED, "process shutting down");
        }
        absl::MutexLock lock(&mutex_);
        stopping_ = true;
      },
      nullptr);
  bool exited;
  {
    absl::MutexLock lock(&mutex_);
    exited = mutex_.AwaitWithTimeout(absl::Condition(&exited_), absl::FromChrono(timeout));
  }
  if (exited) {
    worker_.join();
  } else {
    // Stuck in user code: the process is going away; do not hang it.
    worker_.detach();
  }
  // A running background job may use the behavior: it ends before the
  // behavior is destroyed.
  Background* background;
  {
    absl::MutexLock lock(&mutex_);
    background = background_.get();
  }
  if (background) background->stop();
  if (clock_listener_) context_.clock->removeListener(clock_listener_.get());
}

void BehaviorExecutionManager::post(std::function<void()> command, std::function<void()> cancel) {
  {
    absl::MutexLock lock(&mutex_);
    if (!exited_) {
      commands_.push_back({std::move(command), std::move(cancel)});
      return;
    }
  }
  if (cancel) cancel();
}

void BehaviorExecutionManager::schedule(std::shared_ptr<detail::Inbox> inbox) {
  absl::MutexLock lock(&mutex_);
  if (exited_ || stopping_) return;
  ready_.push_back(std::move(inbox));
}

uint64_t BehaviorExecutionManager::inboxGeneration() const {
  absl::MutexLock lock(&mutex_);
  return activation_id_.empty() ? 0 : generation_;
}

void BehaviorExecutionManager::deliver(const std::shared_ptr<detail::Inbox>& inbox) {
  bool stale;
  bool active;
  {
    absl::MutexLock lock(&mutex_);
    stale = inbox->generation() != 0 && inbox->generation() != generation_;
    active = state_ == State::kActive || state_ == State::kPaused;
  }
  if (stale) {
    inbox->discard();
    return;
  }
  if (guarded("a sample handler (onWorker)", [&] { inbox->drain(); })) return;
  if (active && !stopped_by_watchdog_) {
    finish(v1::TERMINATION_CAUSE_PROCESS_FAILURE, failure_message_);
  }
}

template <class T>
std::function<void()> BehaviorExecutionManager::cancelWith(const Done<T>& done,
                                                           const std::string& name) {
  return [done, name] {
    done(errors::withReason(absl::UnavailableError(name + " is shutting down"), v1::SHUTTING_DOWN,
                            {{"behavior", name}}));
  };
}

void BehaviorExecutionManager::run() {
  mutex_.Lock();
  while (true) {
    if (stopping_) break;
    if (!commands_.empty()) {
      auto command = std::move(commands_.front());
      commands_.pop_front();
      if (context_.before_command) {
        gated_ = true;
        mutex_.Unlock();
        context_.before_command();
        mutex_.Lock();
        gated_ = false;
      }
      commanding_ = true;
      mutex_.Unlock();
      command.run();
      mutex_.Lock();
      commanding_ = false;
      continue;
    }
    if (!ready_.empty()) {
      auto inbox = std::move(ready_.front());
      ready_.pop_front();
      mutex_.Unlock();
      deliver(inbox);
      mutex_.Lock();
      continue;
    }
    // Until there is work for the worker (a command, an inbox, the stop) or
    // the clock wakes it.
    const uint64_t seen = wakes_;
    const auto woken = [this, seen]() ABSL_EXCLUSIVE_LOCKS_REQUIRED(mutex_) {
      return stopping_ || !commands_.empty() || !ready_.empty() || wakes_ != seen;
    };
    if (state_ == State::kActive) {
      if (!context_.clock->valid()) {
        mutex_.AwaitWithTimeout(absl::Condition(&woken), absl::Milliseconds(50));
        continue;
      }
      const TimePoint now = context_.clock->now();
      if (now >= next_tick_) {
        next_tick_ += period_;
        // Never burst to catch up: a late tick moves the schedule.
        if (next_tick_ <= now) next_tick_ = now + period_;
        ticking_ = true;
        mutex_.Unlock();
        execute();
        mutex_.Lock();
        ticking_ = false;
        continue;
      }
      mutex_.AwaitWithTimeout(absl::Condition(&woken),
                              absl::FromChrono(context_.clock->wallWaitFor(next_tick_ - now)));
    } else {
      mutex_.Await(absl::Condition(&woken));  // inactive: no CPU until a command arrives
    }
  }
  exited_ = true;
  ready_.clear();
  std::deque<Command> left = std::move(commands_);
  commands_.clear();
  mutex_.Unlock();
  for (auto& command : left) {
    if (command.cancel) command.cancel();
  }
}

template <class F>
bool BehaviorExecutionManager::guarded(const char* function, F&& f) {
  stopped_by_watchdog_ = false;
  call_function_.store(function, std::memory_order_relaxed);
  call_started_ns_.store(steadyNs(std::chrono::steady_clock::now()), std::memory_order_release);
  bool ok = true;
  try {
    f();
  } catch (const std::exception& e) {
    ok = false;
    failure_message_ =
        std::string(call_function_.load(std::memory_order_relaxed)) + " threw: " + e.what();
  } catch (...) {
    ok = false;
    failure_message_ = std::string(call_function_.load(std::memory_order_relaxed)) +
                       " threw a non-standard exception";
  }
  // The exchange decides, without a lock, whether the watchdog claimed this
  // call (it swaps the start stamp for kWatchdogFired) before it returned.
  const bool fired = call_started_ns_.exchange(0, std::memory_order_acq_rel) == kWatchdogFired;
  if (fired) {
    // The watchdog already ended this activation while the call was stuck;
    // now that it returned, clean up and accept activations again.
    if (std::string_view(function) != "onDeactivate") {
      try {
        behavior_->onDeactivate();
      } catch (...) {
      }
    }
    {
      absl::MutexLock lock(&mutex_);
      state_ = State::kInactive;
      activation_id_.clear();
      parameters_.reset();
      ++generation_;
    }
    callOffBackgroundJobs();
    reportActive(false);
    if (context_.observer) context_.observer->onBlocked(false);
    failure_message_ = "stopped by the watchdog";
    stopped_by_watchdog_ = true;
    return false;
  }
  return ok;
}

template <class F>
bool BehaviorExecutionManager::hookOrAbort(const char* function, F&& hook,
                                           const std::function<void(absl::Status)>& reply) {
  if (guarded(function, std::forward<F>(hook))) return true;
  const std::string why = failure_message_;
  if (!stopped_by_watchdog_) finish(v1::TERMINATION_CAUSE_PROCESS_FAILURE, why);
  reply(absl::AbortedError(name() + ": " + why + "; the activation ended with PROCESS_FAILURE"));
  return false;
}

void BehaviorExecutionManager::watchdogCheck(std::chrono::steady_clock::time_point now) {
  const int64_t started = call_started_ns_.load(std::memory_order_acquire);
  if (started <= 0) return;  // no call running, or already claimed
  const auto limit =
      std::chrono::duration_cast<std::chrono::nanoseconds>(options_.watchdog_timeout);
  if (steadyNs(now) - started < limit.count()) return;
  absl::MutexLock lock(&mutex_);
  if (state_ != State::kActive && state_ != State::kPaused) return;
  int64_t expected = started;
  if (!call_started_ns_.compare_exchange_strong(expected, kWatchdogFired,
                                                std::memory_order_acq_rel)) {
    return;  // the call returned meanwhile
  }
  const char* function = call_function_.load(std::memory_order_relaxed);
  recordFinishedLocked(v1::TERMINATION_CAUSE_PROCESS_FAILURE,
                       std::string(function ? function : "user code") + " did not return within " +
                           secondsText(limit) + " (watchdog); " + name() +
                           " accepts activations again once it returns");
  state_ = State::kBlocked;
  if (context_.observer) context_.observer->onBlocked(true);
}

Duration BehaviorExecutionManager::activeTimeLocked(TimePoint now) const {
  if (state_ == State::kActive) return active_accumulated_ + (now - active_since_);
  return active_accumulated_;
}

Duration BehaviorExecutionManager::activeTime() const {
  // Locked: the watchdog thread writes state_ while user code, still
  // running past its limit, may ask this.
  const TimePoint now = context_.clock->now();
  absl::MutexLock lock(&mutex_);
  return activeTimeLocked(now);
}

void BehaviorExecutionManager::execute() {
  const auto t0 = std::chrono::steady_clock::now();
  const std::chrono::nanoseconds cpu0 = threadCpuTime();
  v1::TerminationCause cause = v1::TERMINATION_CAUSE_UNSPECIFIED;
  std::string message;
  Situation situation;
  const bool ok = guarded("monitoring", [&] {
    call_function_.store("checkProcesses", std::memory_order_relaxed);
    if (Verdict v = behavior_->checkProcesses(); v.finishes()) {
      cause = v1::TERMINATION_CAUSE_PROCESS_FAILURE;
      message = v.message();
      return;
    }
    call_function_.store("checkSituation", std::memory_order_relaxed);
    situation = behavior_->checkSituation();
    if (!situation.feasible) {
      cause = v1::TERMINATION_CAUSE_SITUATION_CHANGE;
      message = joinReasons(situation.reasons);
      return;
    }
    call_function_.store("checkGoal", std::memory_order_relaxed);
    if (Verdict v = behavior_->checkGoal(); v.finishes()) {
      cause = v1::TERMINATION_CAUSE_GOAL_ACHIEVED;
      message = v.message();
      return;
    }
    call_function_.store("checkProgress", std::memory_order_relaxed);
    if (Verdict v = behavior_->checkProgress(); v.finishes()) {
      cause = v1::TERMINATION_CAUSE_WRONG_PROGRESS;
      message = v.message();
      return;
    }
  });
  if (!ok) {
    if (!stopped_by_watchdog_) finish(v1::TERMINATION_CAUSE_PROCESS_FAILURE, failure_message_);
    return;
  }
  if (cause == v1::TERMINATION_CAUSE_UNSPECIFIED && maximum_execution_time_ > Duration::zero() &&
      activeTime() >= maximum_execution_time_) {
    cause = v1::TERMINATION_CAUSE_TIME_OUT;
    message = !time_out_reason_.empty()
                  ? time_out_reason_
                  : "not finished within maximum_execution_time " +
                        secondsText(maximum_execution_time_) + " of active time";
  }
  if (context_.observer) {
    context_.observer->onMonitoring(std::chrono::steady_clock::now() - t0, threadCpuTime() - cpu0);
  }
  if (cause != v1::TERMINATION_CAUSE_UNSPECIFIED) {
    finish(cause, message);
    return;
  }
  if (std::abs(situation.performance_ratio - reported_performance_) >=
          options_.situation_report_threshold ||
      situation.reasons != reported_reasons_ || situation.codes != reported_codes_) {
    absl::MutexLock lock(&mutex_);
    reported_performance_ = situation.performance_ratio;
    reported_reasons_ = situation.reasons;
    reported_codes_ = situation.codes;
    v1::BehaviorEvent event = newEventLocked();
    auto* changed = event.mutable_situation_changed();
    changed->set_feasible(true);
    changed->set_performance_ratio(situation.performance_ratio);
    addReasons(situation, changed);
    context_.events->append(std::move(event));
    if (context_.observer) context_.observer->onSituation(situation.performance_ratio);
  }
  const bool executed = guarded("onExecute", [&] { behavior_->onExecute(); });
  if (first_execute_pending_) {
    first_execute_pending_ = false;
    if (context_.observer) {
      context_.observer->onFirstExecute(std::chrono::steady_clock::now() - activate_received_);
    }
  }
  if (!executed && !stopped_by_watchdog_) {
    finish(v1::TERMINATION_CAUSE_PROCESS_FAILURE, failure_message_);
  }
}

void BehaviorExecutionManager::finish(v1::TerminationCause cause, const std::string& message) {
  std::string full_message = message;
  if (!guarded("onDeactivate", [&] { behavior_->onDeactivate(); })) {
    if (stopped_by_watchdog_) return;
    full_message += (full_message.empty() ? "" : "; ") + failure_message_;
  }
  {
    absl::MutexLock lock(&mutex_);
    if (state_ != State::kActive && state_ != State::kPaused) return;
    recordFinishedLocked(cause, full_message);
    state_ = State::kInactive;
    activation_id_.clear();
    parameters_.reset();
    ++generation_;
  }
  callOffBackgroundJobs();
  reportActive(false);
}

void BehaviorExecutionManager::callOffBackgroundJobs() {
  activation_jobs_.request_stop();
  activation_jobs_ = std::stop_source();
}

void BehaviorExecutionManager::recordFinishedLocked(v1::TerminationCause cause,
                                                    const std::string& message) {
  const TimePoint now = context_.clock->now();
  v1::BehaviorEvent event = newEventLocked();
  auto* finished = event.mutable_finished();
  finished->set_cause(cause);
  finished->set_message(message);
  *finished->mutable_active_duration() = toProtoDuration(activeTimeLocked(now));
  if (parameters_) *finished->mutable_parameters() = params::toStruct(*parameters_);
  wants_ticks_.store(false, std::memory_order_release);
  finished_.push_back({activation_id_, cause});
  if (finished_.size() > kFinishedRemembered) finished_.pop_front();
  // Metrics first, so that a client that sees the event reads updated counters.
  if (context_.observer) context_.observer->onFinished(cause);
  context_.events->append(std::move(event));
}

v1::BehaviorEvent BehaviorExecutionManager::newEventLocked() const {
  v1::BehaviorEvent event;
  event.set_behavior(name());
  event.set_activation_id(activation_id_);
  *event.mutable_time() = toTimestamp(context_.clock->now());
  return event;
}

void BehaviorExecutionManager::reportActive(bool active) {
  if (context_.on_active_changed) context_.on_active_changed(active);
}

absl::Status BehaviorExecutionManager::checkActivationIdLocked(const std::string& activation_id,
                                                               const char* verb) const {
  const bool running = state_ == State::kActive || state_ == State::kPaused;
  if (!activation_id.empty() && (!running || activation_id != activation_id_)) {
    const std::string current = running ? activation_id_ : std::string("none");
    return errors::withReason(
        absl::AbortedError("cannot " + std::string(verb) + " activation " + activation_id + " of " +
                           name() + ": it is not the current activation (current: " + current +
                           ")"),
        v1::ACTIVATION_MISMATCH,
        {{"behavior", name()},
         {"activation_id", activation_id},
         {"current_activation_id", current}});
  }
  if (!running) {
    return errors::withReason(absl::FailedPreconditionError("cannot " + std::string(verb) + " " +
                                                            name() + ": it is not active"),
                              v1::BEHAVIOR_NOT_ACTIVE, {{"behavior", name()}});
  }
  return absl::OkStatus();
}

// ---- Uniform interface -------------------------------------------------------

// While user code stuck past the watchdog still runs, the worker cannot take
// commands; answer at once instead of queueing behind it.
bool BehaviorExecutionManager::refuseWhileBlocked(const std::function<void(absl::Status)>& reply) {
  {
    absl::MutexLock lock(&mutex_);
    if (state_ != State::kBlocked) return false;
  }
  reply(errors::withReason(
      absl::FailedPreconditionError(
          name() +
          " is blocked: user code of its previous activation has not returned yet (stopped "
          "by the watchdog); try again later"),
      v1::BEHAVIOR_BLOCKED, {{"behavior", name()}}));
  return true;
}

void BehaviorExecutionManager::activate(std::unique_ptr<google::protobuf::Message> parameters,
                                        std::string request_id, Done<v1::ActivateResponse> done,
                                        SteadyTime received) {
  if (!parameters || parameters->GetDescriptor() != &parametersType()) {
    done(errors::withReason(absl::InvalidArgumentError(name() + " takes parameters of type " +
                                                       parametersType().full_name()),
                            v1::INVALID_REQUEST, {{"behavior", name()}}));
    return;
  }
  if (absl::Status s = params::applyDefaultsAndValidate(parameters.get()); !s.ok()) {
    done(parameterError(std::move(s), name()));
    return;
  }
  if (refuseWhileBlocked([&](absl::Status s) { done(s); })) return;
  // std::function needs a copyable callable: share the message until the
  // worker takes it.
  std::shared_ptr<google::protobuf::Message> holder(parameters.release());
  post([this, holder, request_id = std::move(request_id), received,
        done] { doActivate(takeMessage(*holder), request_id, received, done); },
       cancelWith(done, name()));
}

void BehaviorExecutionManager::doActivate(std::unique_ptr<google::protobuf::Message> parameters,
                                          const std::string& request_id, SteadyTime received,
                                          const Done<v1::ActivateResponse>& done) {
  // Answered after the lock is released: completions never run under it.
  auto early = [&]() -> std::optional<absl::StatusOr<v1::ActivateResponse>> {
    absl::MutexLock lock(&mutex_);
    const auto wall_now = std::chrono::steady_clock::now();
    while (!request_id_order_.empty() &&
           wall_now - request_id_order_.front().first > kRequestIdWindow) {
      request_ids_.erase(request_id_order_.front().second);
      request_id_order_.pop_front();
    }
    if (!request_id.empty()) {
      if (auto it = request_ids_.find(request_id); it != request_ids_.end()) {
        v1::ActivateResponse response = it->second.first;
        response.set_replayed(true);
        return response;
      }
    }
    if (state_ == State::kBlocked) {
      return errors::withReason(
          absl::FailedPreconditionError(
              name() + " is blocked: user code of its previous activation has not returned yet "
                       "(stopped by the watchdog); try again later"),
          v1::BEHAVIOR_BLOCKED, {{"behavior", name()}});
    }
    if (state_ != State::kInactive) {
      return errors::withReason(absl::FailedPreconditionError(
                                    name() + " is already active (activation " + activation_id_ +
                                    "); deactivate it first, or use Modify to change its "
                                    "parameters"),
                                v1::BEHAVIOR_ALREADY_ACTIVE,
                                {{"behavior", name()}, {"current_activation_id", activation_id_}});
    }
    if (!context_.clock->valid()) {
      return errors::withReason(
          absl::FailedPreconditionError(
              "the behavior clock has no time yet; is the simulator publishing on the 'clock' "
              "topic?"),
          v1::CLOCK_NOT_READY, {{"behavior", name()}});
    }
    return std::nullopt;
  }();
  if (early) {
    done(std::move(*early));
    return;
  }
  Situation situation;
  if (!guarded("checkSituation", [&] { situation = behavior_->checkSituation(); })) {
    done(errors::withReason(
        absl::FailedPreconditionError(name() + " cannot be activated: " + failure_message_),
        v1::BEHAVIOR_FAILED, {{"behavior", name()}}));
    return;
  }
  if (!situation.feasible) {
    done(errors::withReason(
        absl::FailedPreconditionError(name() + " cannot be activated in the current situation: " +
                                      joinReasons(situation.reasons)),
        v1::SITUATION_NOT_SUITABLE,
        {{"behavior", name()}, {"situation_reasons", codeNames(situation)}}));
    return;
  }
  const TimePoint now = context_.clock->now();
  {
    absl::MutexLock lock(&mutex_);
    parameters_ = std::move(parameters);
    activation_id_ = name() + "-" + context_.events->incarnation().substr(0, 8) + "-" +
                     std::to_string(++activation_counter_);
    ++generation_;
    maximum_execution_time_ = options_.maximum_execution_time;
    time_out_reason_.clear();
    activation_time_ = now;
    active_since_ = now;
    active_accumulated_ = Duration::zero();
  }
  absl::Status status;
  if (!guarded("onActivate", [&] { status = behavior_->onActivate(); })) {
    status = absl::InternalError(failure_message_);
  }
  if (!status.ok()) {
    {
      absl::MutexLock lock(&mutex_);
      parameters_.reset();
      activation_id_.clear();
      ++generation_;
    }
    callOffBackgroundJobs();
    done(absl::Status(status.code(),
                      name() + " refused activation: " + std::string(status.message())));
    return;
  }
  v1::ActivateResponse response;
  {
    absl::MutexLock lock(&mutex_);
    state_ = State::kActive;
    next_tick_ = now;
    first_execute_pending_ = true;
    activate_received_ = received;
    reported_performance_ = situation.performance_ratio;
    reported_reasons_ = situation.reasons;
    reported_codes_ = situation.codes;
    response.set_activation_id(activation_id_);
    *response.mutable_activation_time() = toTimestamp(now);
    *response.mutable_parameters() = params::toStruct(*parameters_);
    if (context_.observer)
      context_.observer->onActivated(std::chrono::steady_clock::now() - received);
    v1::BehaviorEvent event = newEventLocked();
    *event.mutable_activated()->mutable_parameters() = response.parameters();
    context_.events->append(std::move(event));
    if (!request_id.empty()) {
      request_ids_[request_id] = {response, std::chrono::steady_clock::now()};
      request_id_order_.emplace_back(std::chrono::steady_clock::now(), request_id);
    }
    wants_ticks_.store(true, std::memory_order_release);
  }
  reportActive(true);
  done(std::move(response));
}

void BehaviorExecutionManager::deactivate(std::string activation_id,
                                          Done<v1::DeactivateResponse> done) {
  {
    absl::ReleasableMutexLock lock(&mutex_);
    if (state_ == State::kBlocked) {
      for (const auto& f : finished_) {
        if (!activation_id.empty() && f.activation_id == activation_id) {
          v1::DeactivateResponse response;
          response.set_activation_id(activation_id);
          response.set_cause(f.cause);
          response.set_already_finished(true);
          lock.Release();
          done(std::move(response));
          return;
        }
      }
      lock.Release();
      refuseWhileBlocked([&](absl::Status s) { done(s); });
      return;
    }
  }
  post(
      [this, activation_id = std::move(activation_id), done] {
        std::string current;
        {
          absl::ReleasableMutexLock lock(&mutex_);
          const bool running = state_ == State::kActive || state_ == State::kPaused;
          if (!running && !activation_id.empty()) {
            for (const auto& f : finished_) {
              if (f.activation_id == activation_id) {
                v1::DeactivateResponse response;
                response.set_activation_id(activation_id);
                response.set_cause(f.cause);
                response.set_already_finished(true);
                lock.Release();
                done(std::move(response));
                return;
              }
            }
          }
          if (absl::Status s = checkActivationIdLocked(activation_id, "deactivate"); !s.ok()) {
            lock.Release();
            done(s);
            return;
          }
          current = activation_id_;
        }
        finish(v1::TERMINATION_CAUSE_INTERRUPTED, "deactivation requested");
        v1::DeactivateResponse response;
        response.set_activation_id(current);
        response.set_cause(v1::TERMINATION_CAUSE_INTERRUPTED);
        done(std::move(response));
      },
      cancelWith(done, name()));
}

void BehaviorExecutionManager::pause(std::string activation_id, Done<v1::PauseResponse> done) {
  if (refuseWhileBlocked([&](absl::Status s) { done(s); })) return;
  post(
      [this, activation_id = std::move(activation_id), done] {
        std::string current;
        {
          absl::ReleasableMutexLock lock(&mutex_);
          if (absl::Status s = checkActivationIdLocked(activation_id, "pause"); !s.ok()) {
            lock.Release();
            done(s);
            return;
          }
          if (state_ == State::kPaused) {
            lock.Release();
            done(errors::withReason(absl::FailedPreconditionError(name() + " is already paused"),
                                    v1::BEHAVIOR_ALREADY_PAUSED, {{"behavior", name()}}));
            return;
          }
          const TimePoint now = context_.clock->now();
          active_accumulated_ += now - active_since_;
          state_ = State::kPaused;
          wants_ticks_.store(false, std::memory_order_release);
          current = activation_id_;
        }
        if (!hookOrAbort(
                "onPause", [&] { behavior_->onPause(); }, [&](absl::Status s) { done(s); }))
          return;
        {
          absl::ReleasableMutexLock lock(&mutex_);
          v1::BehaviorEvent event = newEventLocked();
          event.mutable_paused();
          context_.events->append(std::move(event));
        }
        v1::PauseResponse response;
        response.set_activation_id(current);
        done(std::move(response));
      },
      cancelWith(done, name()));
}

void BehaviorExecutionManager::resume(std::string activation_id, Done<v1::ResumeResponse> done) {
  if (refuseWhileBlocked([&](absl::Status s) { done(s); })) return;
  post(
      [this, activation_id = std::move(activation_id), done] {
        std::string current;
        {
          absl::ReleasableMutexLock lock(&mutex_);
          if (absl::Status s = checkActivationIdLocked(activation_id, "resume"); !s.ok()) {
            lock.Release();
            done(s);
            return;
          }
          if (state_ != State::kPaused) {
            lock.Release();
            done(errors::withReason(absl::FailedPreconditionError(name() + " is not paused"),
                                    v1::BEHAVIOR_NOT_PAUSED, {{"behavior", name()}}));
            return;
          }
          current = activation_id_;
        }
        if (!hookOrAbort(
                "onResume", [&] { behavior_->onResume(); }, [&](absl::Status s) { done(s); }))
          return;
        {
          absl::ReleasableMutexLock lock(&mutex_);
          const TimePoint now = context_.clock->now();
          state_ = State::kActive;
          active_since_ = now;
          next_tick_ = now;
          v1::BehaviorEvent event = newEventLocked();
          event.mutable_resumed();
          context_.events->append(std::move(event));
          wants_ticks_.store(true, std::memory_order_release);
        }
        v1::ResumeResponse response;
        response.set_activation_id(current);
        done(std::move(response));
      },
      cancelWith(done, name()));
}

void BehaviorExecutionManager::modify(std::string activation_id,
                                      std::unique_ptr<google::protobuf::Message> update,
                                      Done<v1::ModifyResponse> done) {
  if (!update || update->GetDescriptor() != &parametersType()) {
    done(errors::withReason(absl::InvalidArgumentError(name() + " takes parameters of type " +
                                                       parametersType().full_name()),
                            v1::INVALID_REQUEST, {{"behavior", name()}}));
    return;
  }
  if (refuseWhileBlocked([&](absl::Status s) { done(s); })) return;
  std::shared_ptr<google::protobuf::Message> holder(update.release());
  post(
      [this, activation_id = std::move(activation_id), holder, done] {
        std::unique_ptr<google::protobuf::Message> update = takeMessage(*holder);
        std::unique_ptr<google::protobuf::Message> merged;
        std::string current;
        {
          absl::ReleasableMutexLock lock(&mutex_);
          if (absl::Status s = checkActivationIdLocked(activation_id, "modify"); !s.ok()) {
            lock.Release();
            done(s);
            return;
          }
          merged.reset(parameters_->New());
          merged->CopyFrom(*parameters_);
          current = activation_id_;
        }
        params::mergeUpdate(*update, merged.get());
        if (absl::Status s = params::applyDefaultsAndValidate(merged.get()); !s.ok()) {
          done(parameterError(std::move(s), name()));
          return;
        }
        absl::Status status;
        if (!hookOrAbort(
                "onModify", [&] { status = behavior_->modifyParameters(*merged); },
                [&](absl::Status s) { done(s); })) {
          return;
        }
        if (!status.ok()) {
          done(errors::rewrap(
              status, name() + " refused the new parameters: " + std::string(status.message())));
          return;
        }
        v1::ModifyResponse response;
        {
          absl::ReleasableMutexLock lock(&mutex_);
          parameters_ = std::move(merged);
          response.set_activation_id(current);
          *response.mutable_parameters() = params::toStruct(*parameters_);
          v1::BehaviorEvent event = newEventLocked();
          *event.mutable_modified()->mutable_parameters() = response.parameters();
          context_.events->append(std::move(event));
        }
        done(std::move(response));
      },
      cancelWith(done, name()));
}

void BehaviorExecutionManager::checkSituationNow(Done<v1::CheckSituationResponse> done) {
  if (refuseWhileBlocked([&](absl::Status s) {
        v1::CheckSituationResponse response;
        response.set_feasible(false);
        response.add_reasons(std::string(s.message()));
        done(std::move(response));
      })) {
    return;
  }
  post(
      [this, done] {
        Situation situation;
        v1::CheckSituationResponse response;
        if (!guarded("checkSituation", [&] { situation = behavior_->checkSituation(); })) {
          response.set_feasible(false);
          response.add_reasons(failure_message_);
          done(std::move(response));
          return;
        }
        response.set_feasible(situation.feasible);
        response.set_performance_ratio(situation.performance_ratio);
        addReasons(situation, &response);
        done(std::move(response));
      },
      cancelWith(done, name()));
}

v1::BehaviorState BehaviorExecutionManager::state() const {
  absl::MutexLock lock(&mutex_);
  switch (state_) {
    case State::kInactive:
      return v1::BEHAVIOR_STATE_INACTIVE;
    case State::kActive:
      return v1::BEHAVIOR_STATE_ACTIVE;
    case State::kPaused:
      return v1::BEHAVIOR_STATE_PAUSED;
    case State::kBlocked:
      return v1::BEHAVIOR_STATE_BLOCKED;
  }
  return v1::BEHAVIOR_STATE_UNSPECIFIED;
}

v1::CheckActivationResponse BehaviorExecutionManager::checkActivation() const {
  v1::CheckActivationResponse response;
  response.set_state(state());
  absl::MutexLock lock(&mutex_);
  const bool running = state_ == State::kActive || state_ == State::kPaused;
  response.set_active(running);
  if (running) {
    response.set_activation_id(activation_id_);
    if (parameters_) *response.mutable_parameters() = params::toStruct(*parameters_);
    *response.mutable_activation_time() = toTimestamp(activation_time_);
    *response.mutable_active_duration() = toProtoDuration(activeTimeLocked(context_.clock->now()));
  }
  return response;
}

absl::StatusOr<v1::ActivateResponse> BehaviorExecutionManager::activateAndWait(
    std::unique_ptr<google::protobuf::Message> parameters, std::string request_id,
    std::chrono::milliseconds timeout) {
  auto* raw = parameters.release();
  return waitFor<v1::ActivateResponse>(
      [&](Done<v1::ActivateResponse> done) {
        activate(std::unique_ptr<google::protobuf::Message>(raw), request_id, std::move(done));
      },
      timeout);
}

absl::StatusOr<v1::DeactivateResponse> BehaviorExecutionManager::deactivateAndWait(
    std::string activation_id, std::chrono::milliseconds timeout) {
  return waitFor<v1::DeactivateResponse>(
      [&](Done<v1::DeactivateResponse> done) { deactivate(activation_id, std::move(done)); },
      timeout);
}

absl::StatusOr<v1::PauseResponse> BehaviorExecutionManager::pauseAndWait(
    std::string activation_id) {
  return waitFor<v1::PauseResponse>(
      [&](Done<v1::PauseResponse> done) { pause(activation_id, std::move(done)); },
      std::chrono::seconds(5));
}

absl::StatusOr<v1::ResumeResponse> BehaviorExecutionManager::resumeAndWait(
    std::string activation_id) {
  return waitFor<v1::ResumeResponse>(
      [&](Done<v1::ResumeResponse> done) { resume(activation_id, std::move(done)); },
      std::chrono::seconds(5));
}

absl::StatusOr<v1::ModifyResponse> BehaviorExecutionManager::modifyAndWait(
    std::unique_ptr<google::protobuf::Message> update, std::string activation_id) {
  auto* raw = update.release();
  return waitFor<v1::ModifyResponse>(
      [&](Done<v1::ModifyResponse> done) {
        modify(activation_id, std::unique_ptr<google::protobuf::Message>(raw), std::move(done));
      },
      std::chrono::seconds(5));
}

absl::StatusOr<v1::CheckSituationResponse> BehaviorExecutionManager::checkSituationAndWait() {
  return waitFor<v1::CheckSituationResponse>(
      [&](Done<v1::CheckSituationResponse> done) { checkSituationNow(std::move(done)); },
      std::chrono::seconds(5));
}

std::string declaredBehaviorName(const google::protobuf::Descriptor* parameters) {
  if (parameters == nullptr || !parameters->options().HasExtension(v1::declare)) return {};
  return parameters->options().GetExtension(v1::declare).name();
}

namespace detail {

std::string requireDeclaredName(const google::protobuf::Descriptor* parameters) {
  std::string name = declaredBehaviorName(parameters);
  if (name.empty()) {
    throw std::logic_error(parameters->full_name() +
                           " declares no behavior: give it option (behaviorlib.v1.declare), or "
                           "name the behavior in its constructor");
  }
  return name;
}

}  // namespace detail

}  // namespace behaviorlib
