#pragma once

// Where a coordinator WatchEvents stream is, so that a client that
// reconnects resumes without a gap or a duplicate (as the Python client's
// EventCursor):
//
// - within one coordinator incarnation, the stream resumes after the last
//   coordinator seq delivered;
// - a restarted coordinator has a new incarnation and replays every event it
//   retained, which it read again from the systems; their behavior events
//   keep the system's own (incarnation, seq), so the ones already delivered
//   are recognised and dropped. Synthesized events (seq 0) are recognised by
//   their activation.

#include <cstdint>
#include <deque>
#include <set>
#include <string>
#include <tuple>
#include <vector>

#include "behaviorlib/v1/coordinator.pb.h"

namespace behaviorlib::follower {

class EventCursor {
 public:
  /// Behavior events remembered to recognise a replayed one.
  static constexpr size_t kRemembered = 4096;

  /// The request that resumes the stream where it is.
  v1::WatchFleetEventsRequest request() const;

  /// The new events of one WatchEvents message, in order (none for the
  /// start message).
  std::vector<v1::FleetEvent> accept(const v1::WatchFleetEventsResponse& response);

  uint64_t sinceSeq() const { return since_seq_; }
  const std::string& incarnation() const { return incarnation_; }
  /// Coordinator restarts seen, and events it said were no longer retained.
  uint64_t restartsSeen() const { return restarts_seen_; }
  uint64_t droppedCount() const { return dropped_count_; }

 private:
  using Identity = std::tuple<bool, std::string, std::string, uint64_t>;
  bool remember(const v1::FleetEvent& event);

  uint64_t since_seq_ = 0;
  std::string incarnation_;
  uint64_t restarts_seen_ = 0;
  uint64_t dropped_count_ = 0;
  std::set<Identity> seen_;
  std::deque<Identity> order_;
};

}  // namespace behaviorlib::follower
