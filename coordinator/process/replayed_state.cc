#include "coordinator/process/replayed_state.h"

namespace behaviorlib::coordinator {

void ReplayedState::apply(const durable::v1::JournalRecord& record) {
  if (record.has_belief()) beliefs.restore(record.belief());
  if (record.has_mission()) missions.push_back(record.mission());
  if (record.has_system()) {
    const auto& r = record.system();
    auto key = std::make_pair(r.robot_id(), r.system());
    if (r.unregistered()) {
      systems.erase(key);
    } else {
      systems[std::move(key)] = r;
    }
  }
}

}  // namespace behaviorlib::coordinator
