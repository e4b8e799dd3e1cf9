#pragma once

// BehaviorHost: the transport-free heart of a behavior system. It owns the
// behaviors of one process, their shared event log and clock, and the
// watchdog that ends an activation whose user code is stuck.
//
//   behaviorlib::SteadyClock clock;
//   behaviorlib::BehaviorHost host({.robot_id = "drone1", .system = "basic"}, clock);
//   host.add(std::make_unique<WaitBehavior>());
//   if (auto s = host.start(config); !s.ok()) ...
//   host.find("WAIT")->activateAndWait(...);
//   host.stop();   // active behaviors finish INTERRUPTED

#include <yaml-cpp/yaml.h>

#include <functional>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include "absl/base/thread_annotations.h"
#include "absl/status/status.h"
#include "absl/synchronization/mutex.h"
#include "behaviorlib/behavior_execution_manager.h"
#include "behaviorlib/clock.h"
#include "behaviorlib/event_log.h"

namespace behaviorlib {

struct BehaviorHostOptions {
  std::string robot_id = "drone1";
  std::string system = "behavior_system";
  EventLogOptions events;  // robot_id and system are filled from above
  /// Given to every behavior (BehaviorContext::before_command); must stay
  /// callable until stop() returns.
  std::function<void()> before_command;
};

class BehaviorHost {
 public:
  BehaviorHost(BehaviorHostOptions options, const Clock& clock);
  BehaviorHost(const BehaviorHost&) = delete;
  BehaviorHost& operator=(const BehaviorHost&) = delete;
  ~BehaviorHost();  // stops if still running

  /// Adds a behavior before start(); names must be unique.
  void add(std::unique_ptr<BehaviorExecutionManager> behavior);
  /// The same, wrapped in its engine here.
  void add(std::unique_ptr<BehaviorBase> behavior) {
    add(std::make_unique<BehaviorExecutionManager>(std::move(behavior)));
  }
  /// Factory for metrics: called once per behavior at start(); may return
  /// nullptr. The host keeps the observers alive.
  using ObserverFactory =
      std::function<std::unique_ptr<BehaviorObserver>(const BehaviorExecutionManager&)>;
  void setObserverFactory(ObserverFactory factory) { observer_factory_ = std::move(factory); }

  /// Configures and starts every behavior. `config` is the whole --config
  /// document (read from `config_file`, named in messages); each behavior
  /// gets `config["behaviors"][<NAME>]`. A section of a behavior the host
  /// does not hold is an error with its file:line (a misspelled name).
  absl::Status start(const YAML::Node& config = YAML::Node(), const std::string& config_file = "");
  /// Ends every active activation with INTERRUPTED (events emitted), joins
  /// the workers and the watchdog.
  void stop();

  /// The behavior with this name, or nullptr.
  BehaviorExecutionManager* find(const std::string& name) const;
  const std::vector<std::unique_ptr<BehaviorExecutionManager>>& behaviors() const {
    return behaviors_;
  }
  /// Whether every behavior ran everything due up to `t` (caughtUp).
  bool caughtUp(TimePoint t) const;
  /// Whether every behavior is idle (BehaviorExecutionManager::idle).
  bool idle() const;
  EventLog& events() { return events_; }
  const Clock& clock() const { return clock_; }
  const std::string& robotId() const { return options_.robot_id; }
  const std::string& system() const { return options_.system; }
  /// Number of currently active (or paused) behaviors.
  int activeCount() const;

 private:
  void watchdogLoop();
  void onActiveChanged(bool active);

  BehaviorHostOptions options_;
  const Clock& clock_;
  EventLog events_;
  std::vector<std::unique_ptr<BehaviorExecutionManager>> behaviors_;
  std::vector<std::unique_ptr<BehaviorObserver>> observers_;
  ObserverFactory observer_factory_;
  bool started_ = false;

  // The watchdog thread waits on mutex_ (Mutex::Await) for an active
  // behavior or the stop.
  mutable absl::Mutex mutex_;
  int active_count_ ABSL_GUARDED_BY(mutex_) = 0;
  bool stopping_ ABSL_GUARDED_BY(mutex_) = false;
  std::thread watchdog_;
};

}  // namespace behaviorlib
