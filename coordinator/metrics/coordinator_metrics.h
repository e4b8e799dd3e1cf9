#pragma once

// Prometheus metrics of the coordinator (names behaviorlib_coordinator_*).
// Every series is created once here; updates are plain counter and gauge
// operations.

#include <prometheus/counter.h>
#include <prometheus/gauge.h>
#include <prometheus/registry.h>

#include <string>

#include "behaviorlib/v1/mission.pb.h"

namespace behaviorlib::coordinator {

struct CoordinatorMetrics {
  explicit CoordinatorMetrics(prometheus::Registry& registry);

  /// Behavior events received from systems and forwarded to the stream.
  prometheus::Counter& events_received;
  /// Events received again after a resume (or of an activation already
  /// finished by the coordinator) and dropped.
  prometheus::Counter& events_dropped_duplicate;
  /// Events a system no longer retained when the coordinator resumed.
  prometheus::Counter& events_lost;
  /// Finished events the coordinator made for activations of systems that
  /// went down, restarted or left.
  prometheus::Counter& events_synthesized;
  /// Systems the coordinator knows (registered or configured).
  prometheus::Gauge& systems_registered;
  /// Systems whose event stream is established.
  prometheus::Gauge& systems_up;
  /// Times a system was declared down by supervision.
  prometheus::Counter& systems_down;
  /// Event streams to systems re-opened after a break.
  prometheus::Counter& stream_reconnects;
  /// Open Coordinator.WatchEvents streams.
  prometheus::Gauge& subscribers;
  /// Missions started, by robot.
  prometheus::Family<prometheus::Counter>& missions_started;
  /// Missions ended, by robot, outcome and cause (missionEnded).
  prometheus::Family<prometheus::Counter>& missions_finished;
  /// Safety actions, by robot, action and trigger.
  prometheus::Family<prometheus::Counter>& safety_actions;
  /// Missions the coordinator holds: running, and ended ones retained
  /// (--max-ended-missions, --max-ended-mission-age-s).
  prometheus::Gauge& missions_retained;
  /// Mission runners alive (each with its thread and parsed mission): the
  /// running missions, plus those that ended since the last start.
  prometheus::Gauge& mission_runners;
  /// Open WatchVehicle streams, each a data-channel subscription (counted
  /// until the subscription has ended).
  prometheus::Gauge& vehicle_watches;

  /// Counts an ended mission in missions_finished.
  void missionEnded(const v1::MissionStatus& status);
};

/// What ended a mission, for missions_finished's `cause` label: the
/// termination cause of its last step without the TERMINATION_CAUSE_ prefix
/// (GOAL_ACHIEVED for a success, TIME_OUT, INTERRUPTED for an abort during a
/// step, ...), REFUSED when that step's activation was refused, NONE when no
/// step ended it (a failed recurrent behavior, an abort between steps, a
/// resume that failed).
std::string missionEndCause(const v1::MissionStatus& status);

}  // namespace behaviorlib::coordinator
