#include "coordinator/events/fleet_event_log.h"

#include <algorithm>

namespace behaviorlib::coordinator {

namespace {

bool contains(const std::vector<std::string>& list, const std::string& value) {
  return std::find(list.begin(), list.end(), value) != list.end();
}

}  // namespace

bool matchesFilter(const v1::FleetEvent& event, const std::vector<std::string>& robot_ids,
                   const std::vector<std::string>& behaviors) {
  if (event.has_behavior_event()) {
    const auto& e = event.behavior_event();
    return (robot_ids.empty() || contains(robot_ids, e.robot_id())) &&
           (behaviors.empty() || contains(behaviors, e.behavior()));
  }
  if (event.has_system_state_changed()) {
    return behaviors.empty() &&
           (robot_ids.empty() ||
            contains(robot_ids, event.system_state_changed().system().robot_id()));
  }
  return robot_ids.empty() && behaviors.empty();
}

}  // namespace behaviorlib::coordinator
