#include "behaviorlib/behavior_host.h"

#include <algorithm>

#include "behaviorlib/configuration.h"

namespace behaviorlib {
namespace {

EventLogOptions eventOptions(const BehaviorHostOptions& options) {
  EventLogOptions events = options.events;
  events.robot_id = options.robot_id;
  events.system = options.system;
  return events;
}

}  // namespace

BehaviorHost::BehaviorHost(BehaviorHostOptions options, const Clock& clock)
    : options_(std::move(options)), clock_(clock), events_(eventOptions(options_)) {}

BehaviorHost::~BehaviorHost() { stop(); }

void BehaviorHost::add(std::unique_ptr<BehaviorExecutionManager> behavior) {
  behaviors_.push_back(std::move(behavior));
}

absl::Status BehaviorHost::start(const YAML::Node& config, const std::string& config_file) {
  for (size_t i = 0; i < behaviors_.size(); ++i) {
    for (size_t j = i + 1; j < behaviors_.size(); ++j) {
      if (behaviors_[i]->name() == behaviors_[j]->name()) {
        return absl::InvalidArgumentError("behavior " + behaviors_[i]->name() +
                                          " is registered twice");
      }
    }
  }
  YAML::Node section;
  if (config && config.IsMap() && config["behaviors"]) section = config["behaviors"];
  if (section && !section.IsNull()) {
    if (!section.IsMap()) {
      return absl::InvalidArgumentError(config::position(section, config_file) +
                                        ": behaviors: must be a map from behavior names to keys");
    }
    for (const auto& item : section) {
      const std::string name = item.first.IsScalar() ? item.first.Scalar() : std::string();
      if (find(name) != nullptr) continue;
      std::string hosted;
      for (const auto& behavior : behaviors_) {
        hosted += (hosted.empty() ? "" : ", ") + behavior->name();
      }
      return absl::InvalidArgumentError(config::position(item.first, config_file) +
                                        ": behaviors: no behavior '" + name +
                                        "' in this system (it hosts " + hosted + ")");
    }
  }
  for (auto& behavior : behaviors_) {
    BehaviorContext context;
    context.clock = &clock_;
    context.events = &events_;
    context.robot_id = options_.robot_id;
    if (section && section.IsMap() && section[behavior->name()]) {
      context.config = section[behavior->name()];
    }
    context.config_file = config_file;
    if (observer_factory_) {
      if (auto observer = observer_factory_(*behavior)) {
        context.observer = observer.get();
        observers_.push_back(std::move(observer));
      }
    }
    context.on_active_changed = [this](bool active) { onActiveChanged(active); };
    context.before_command = options_.before_command;
    if (absl::Status s = behavior->start(std::move(context)); !s.ok()) {
      stop();
      return s;
    }
  }
  started_ = true;
  watchdog_ = std::thread([this] { watchdogLoop(); });
  return absl::OkStatus();
}

void BehaviorHost::stop() {
  for (auto& behavior : behaviors_) behavior->stop();
  {
    absl::MutexLock lock(&mutex_);
    stopping_ = true;  // the watchdog's Await sees it at the unlock
  }
  if (watchdog_.joinable()) watchdog_.join();
  started_ = false;
}

BehaviorExecutionManager* BehaviorHost::find(const std::string& name) const {
  for (const auto& behavior : behaviors_) {
    if (behavior->name() == name) return behavior.get();
  }
  return nullptr;
}

int BehaviorHost::activeCount() const {
  absl::MutexLock lock(&mutex_);
  return active_count_;
}

void BehaviorHost::onActiveChanged(bool active) {
  absl::MutexLock lock(&mutex_);
  active_count_ += active ? 1 : -1;
}

void BehaviorHost::watchdogLoop() {
  // Poll only while something is active, at a quarter of the shortest
  // timeout: idle systems stay idle.
  std::chrono::milliseconds period(1000);
  for (const auto& behavior : behaviors_) {
    period = std::min(period, behavior->options().watchdog_timeout / 4);
  }
  period = std::max(period, std::chrono::milliseconds(5));
  const auto active_or_stop = [this]() ABSL_EXCLUSIVE_LOCKS_REQUIRED(mutex_) {
    return stopping_ || active_count_ > 0;
  };
  absl::MutexLock lock(&mutex_);
  while (!stopping_) {
    // Idle: no CPU until a behavior becomes active or the host stops.
    mutex_.Await(absl::Condition(&active_or_stop));
    if (stopping_) break;
    // Waits out the period unless stopped meanwhile.
    if (mutex_.AwaitWithTimeout(absl::Condition(&stopping_), absl::FromChrono(period))) break;
    mutex_.Unlock();
    const auto now = std::chrono::steady_clock::now();
    for (auto& behavior : behaviors_) behavior->watchdogCheck(now);
    mutex_.Lock();
  }
}

bool BehaviorHost::caughtUp(TimePoint t) const {
  for (const auto& behavior : behaviors_) {
    if (!behavior->caughtUp(t)) return false;
  }
  return true;
}

bool BehaviorHost::idle() const {
  for (const auto& behavior : behaviors_) {
    if (!behavior->idle()) return false;
  }
  return true;
}

}  // namespace behaviorlib
