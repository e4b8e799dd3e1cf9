#include "behaviorlib/event_log.h"

#include <algorithm>
#include <utility>

namespace behaviorlib {

bool BehaviorEventFilter::matches(const v1::BehaviorEvent& event) const {
  return behaviors.empty() ||
         std::find(behaviors.begin(), behaviors.end(), event.behavior()) != behaviors.end();
}

EventLog::EventLog(EventLogOptions options)
    : robot_id_(std::move(options.robot_id)),
      system_(std::move(options.system)),
      log_(ResumableLogOptions{.capacity = options.capacity,
                               .subscriber_queue_limit = options.subscriber_queue_limit,
                               .incarnation = std::move(options.incarnation)},
           ActivationRetention{options.retention}) {}

EventPtr EventLog::append(v1::BehaviorEvent event) {
  event.set_robot_id(robot_id_);
  event.set_system(system_);
  return log_.append(std::move(event));
}

std::unique_ptr<EventSubscription> EventLog::subscribe(const SubscribeOptions& options,
                                                       std::function<void()> wake) {
  return log_.subscribe({.since_seq = options.since_seq,
                         .incarnation = options.incarnation,
                         .filter = {.behaviors = options.behaviors}},
                        std::move(wake));
}

}  // namespace behaviorlib
