#pragma once

// ReplayedState: what the coordinator keeps from its journal at start-up.
// Journal::open (or decodeJournal) hands every record to apply(); the
// coordinator then copies the result into its live stores:
//   - beliefs: every belief record restored in order into a store with no
//     journal attached (the last record of a key wins; a deletion stays as
//     the store's tombstone);
//   - missions: every mission status in journal order (MissionManager::restore
//     keeps the last one of each id);
//   - systems: the last record of each (robot, system) pair; an unregistration
//     removes the pair.
//
//   ReplayedState replayed;
//   auto journal = Journal::open(path, [&](const durable::v1::JournalRecord& r) {
//   replayed.apply(r); });
//
// Not thread-safe: it is filled and read by the one thread that starts the
// coordinator.

#include <map>
#include <string>
#include <utility>
#include <vector>

#include "behaviorlib/durable/v1/journal.pb.h"
#include "behaviorlib/v1/mission.pb.h"
#include "coordinator/belief/belief_store.h"

namespace behaviorlib::coordinator {

struct ReplayedState {
  BeliefStore beliefs;
  std::vector<v1::MissionStatus> missions;
  std::map<std::pair<std::string, std::string>, durable::v1::SystemRecord> systems;

  void apply(const durable::v1::JournalRecord& record);
};

}  // namespace behaviorlib::coordinator
