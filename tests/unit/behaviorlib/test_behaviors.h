#pragma once

// A behavior whose every function is scriptable from a test, recording the
// calls it receives; and helpers to wait for asynchronous outcomes.

#include <atomic>
#include <chrono>
#include <functional>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "behaviorlib/behavior_execution_manager.h"
#include "behaviorlib/behavior_host.h"
#include "behaviorlib/event_log.h"
#include "behaviorlib/v1/behaviors/basic_quadrotor_behaviors.pb.h"

namespace behaviorlib::testing {

class ScriptedBehavior final : public Behavior<v1::WaitParameters> {
 public:
  explicit ScriptedBehavior(std::string name = "SCRIPTED", BehaviorOptions options = {})
      : Behavior(std::move(name), options) {}

  std::function<absl::Status()> on_activate = [] { return absl::OkStatus(); };
  std::function<void()> on_execute = [] {};
  std::function<void()> on_pause = [] {};
  std::function<Situation()> situation = [] { return Situation::ok(); };
  std::function<Verdict()> goal = [] { return Verdict::keepGoing(); };
  std::function<Verdict()> progress = [] { return Verdict::keepGoing(); };
  std::function<Verdict()> processes = [] { return Verdict::keepGoing(); };
  std::function<absl::Status(const v1::WaitParameters&)> on_modify = [](const v1::WaitParameters&) {
    return absl::OkStatus();
  };
  /// Not empty: checkProgress ends the activation through the time-out with
  /// this reason as its message.
  std::function<std::string()> time_out_reason = [] { return std::string(); };

  std::vector<std::string> calls() const {
    std::lock_guard lock(mutex_);
    return calls_;
  }
  void clearCalls() {
    std::lock_guard lock(mutex_);
    calls_.clear();
  }
  int count(const std::string& call) const {
    std::lock_guard lock(mutex_);
    int n = 0;
    for (const auto& c : calls_) n += c == call;
    return n;
  }
  Duration lastActiveTime() const { return Duration(last_active_ns_.load()); }
  double durationParameter() const { return duration_parameter_.load(); }
  /// The current activation's duration_s (on the worker only: from a hook).
  double durationParameterNow() const { return parameters().duration_s(); }

 protected:
  absl::Status onActivate() override {
    record("onActivate");
    return on_activate();
  }
  void onExecute() override {
    record("onExecute");
    last_active_ns_.store(activeTime().count());
    duration_parameter_.store(parameters().duration_s());
    on_execute();
  }
  void onDeactivate() override { record("onDeactivate"); }
  void onPause() override {
    record("onPause");
    on_pause();
  }
  void onResume() override { record("onResume"); }
  absl::Status onModify(const v1::WaitParameters& p) override {
    record("onModify");
    return on_modify(p);
  }
  Situation checkSituation() override {
    record("checkSituation");
    return situation();
  }
  Verdict checkGoal() override {
    record("checkGoal");
    return goal();
  }
  Verdict checkProgress() override {
    record("checkProgress");
    if (std::string reason = time_out_reason(); !reason.empty()) {
      setMaximumExecutionTime(std::max(activeTime(), Duration(1)), std::move(reason));
    }
    return progress();
  }
  Verdict checkProcesses() override {
    record("checkProcesses");
    return processes();
  }

 private:
  void record(const std::string& call) {
    std::lock_guard lock(mutex_);
    calls_.push_back(call);
  }
  mutable std::mutex mutex_;
  std::vector<std::string> calls_;
  std::atomic<int64_t> last_active_ns_{0};
  std::atomic<double> duration_parameter_{0};
};

/// Polls `predicate` until it holds or `timeout` (wall time) passes.
inline bool eventually(const std::function<bool()>& predicate,
                       std::chrono::milliseconds timeout = std::chrono::seconds(5)) {
  const auto deadline = std::chrono::steady_clock::now() + timeout;
  while (std::chrono::steady_clock::now() < deadline) {
    if (predicate()) return true;
    std::this_thread::sleep_for(std::chrono::milliseconds(1));
  }
  return predicate();
}

/// Collects every event of an EventLog from subscription time on.
class EventCollector {
 public:
  explicit EventCollector(EventLog& log) {
    subscription_ = log.subscribe({}, [] {});
  }
  std::vector<v1::BehaviorEvent> events() {
    drain();
    std::lock_guard lock(mutex_);
    return events_;
  }
  /// Waits for the first finished event (after `skip` earlier ones) and
  /// returns it; an empty event on timeout.
  v1::BehaviorEvent waitFinished(size_t skip = 0,
                                 std::chrono::milliseconds timeout = std::chrono::seconds(5)) {
    v1::BehaviorEvent found;
    eventually(
        [&] {
          size_t seen = 0;
          for (const auto& e : events()) {
            if (e.has_finished() && seen++ == skip) {
              found = e;
              return true;
            }
          }
          return false;
        },
        timeout);
    return found;
  }
  int countKind(v1::BehaviorEvent::KindCase kind) {
    int n = 0;
    for (const auto& e : events()) n += e.kind_case() == kind;
    return n;
  }

 private:
  void drain() {
    std::lock_guard lock(mutex_);
    while (auto e = subscription_->pop()) events_.push_back(*e);
  }
  std::unique_ptr<EventSubscription> subscription_;
  std::mutex mutex_;
  std::vector<v1::BehaviorEvent> events_;
};

inline BehaviorHostOptions hostOptions(std::string robot_id, std::string system) {
  BehaviorHostOptions options;
  options.robot_id = std::move(robot_id);
  options.system = std::move(system);
  return options;
}

inline std::unique_ptr<v1::WaitParameters> waitParams(double duration_s) {
  auto p = std::make_unique<v1::WaitParameters>();
  p->set_duration_s(duration_s);
  return p;
}

}  // namespace behaviorlib::testing
