#pragma once

// The coordinator's own event log: every accepted behavior event of every
// system, plus system state changes, numbered 1, 2, 3... per coordinator run
// (with a random incarnation id per run), kept in a bounded buffer and served
// to resumable, filtered subscriptions (Coordinator.WatchEvents).
//
//   FleetEventLog log({.capacity = 10000});
//   auto sub = log.subscribe({.since_seq = 0, .robot_ids = {"drone1"}}, [&] { /* wake */ });
//   log.append(event);             // assigns seq, incarnation, wall_time
//   while (auto e = sub->pop()) { ... }
//
// It is the ResumableLog of the behavior systems' EventLog
// (behaviorlib/resumable_log.h, decision 2), with fleet filters and retention
// by count only: the oldest events are evicted first.

#include <algorithm>
#include <cstdint>
#include <functional>
#include <memory>
#include <string>
#include <vector>

#include "behaviorlib/resumable_log.h"
#include "behaviorlib/v1/coordinator.pb.h"

namespace behaviorlib::coordinator {

/// Whether `event` passes the robot and behavior filters.
bool matchesFilter(const v1::FleetEvent& event, const std::vector<std::string>& robot_ids,
                   const std::vector<std::string>& behaviors);

/// Fleet events of the listed robots and behaviors (all when empty); a
/// behavior filter leaves system events out.
struct FleetEventFilter {
  std::vector<std::string> robot_ids;
  std::vector<std::string> behaviors;
  bool matches(const v1::FleetEvent& event) const {
    return matchesFilter(event, robot_ids, behaviors);
  }
};

using FleetLog = ResumableLog<v1::FleetEvent, FleetEventFilter>;
using FleetEventPtr = FleetLog::EventPtr;
using FleetEventRecord = FleetLog::Record;
using FleetEventRecordPtr = FleetLog::RecordPtr;
using FleetSubscription = FleetLog::Subscription;
/// capacity (10000 by default), subscriber_queue_limit, incarnation.
using FleetEventLogOptions = ResumableLogOptions;

struct FleetSubscribeOptions {
  /// Replay retained events with seq > since_seq.
  uint64_t since_seq = 0;
  /// The incarnation since_seq refers to; empty means "the current one".
  std::string incarnation;
  /// Only events of these robots; empty means all.
  std::vector<std::string> robot_ids;
  /// Only behavior events of these behaviors (system events are left out);
  /// empty means all.
  std::vector<std::string> behaviors;
};

class FleetEventLog {
 public:
  /// Keeps at least the newest event.
  explicit FleetEventLog(FleetEventLogOptions options = {})
      : log_(withCapacityAtLeastOne(std::move(options))) {}

  const std::string& incarnation() const { return log_.incarnation(); }

  /// Appends: fills seq, incarnation and wall_time, retains the event and
  /// hands it to every matching subscriber. Never blocks on subscribers.
  FleetEventPtr append(v1::FleetEvent event) { return log_.append(std::move(event)); }
  /// append() for several events at once, in order: one lock, and each
  /// subscriber woken once.
  void appendAll(std::vector<v1::FleetEvent> events) { log_.appendAll(std::move(events)); }

  /// Subscribes (ResumableLog::subscribe). Drain once after subscribing: the
  /// replay is queued without a wake.
  std::unique_ptr<FleetSubscription> subscribe(const FleetSubscribeOptions& options,
                                               std::function<void()> wake) {
    return log_.subscribe(
        {.since_seq = options.since_seq,
         .incarnation = options.incarnation,
         .filter = {.robot_ids = options.robot_ids, .behaviors = options.behaviors}},
        std::move(wake));
  }

  /// Seq of the newest event (0 if none).
  uint64_t latestSeq() const { return log_.latestSeq(); }
  /// Number of retained events.
  size_t retainedCount() const { return log_.retainedCount(); }

 private:
  static FleetEventLogOptions withCapacityAtLeastOne(FleetEventLogOptions options) {
    options.capacity = std::max<size_t>(1, options.capacity);
    return options;
  }

  FleetLog log_;
};

}  // namespace behaviorlib::coordinator
