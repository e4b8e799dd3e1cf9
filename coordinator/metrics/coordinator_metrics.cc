#include "coordinator/metrics/coordinator_metrics.h"

#include <string>
#include <string_view>

namespace behaviorlib::coordinator {

namespace {

prometheus::Counter& counter(prometheus::Registry& registry, const std::string& name,
                             const std::string& help) {
  return prometheus::BuildCounter().Name(name).Help(help).Register(registry).Add({});
}

prometheus::Gauge& gauge(prometheus::Registry& registry, const std::string& name,
                         const std::string& help) {
  return prometheus::BuildGauge().Name(name).Help(help).Register(registry).Add({});
}

}  // namespace

CoordinatorMetrics::CoordinatorMetrics(prometheus::Registry& registry)
    : events_received(counter(registry, "behaviorlib_coordinator_events_received_total",
                              "Behavior events received from systems and forwarded")),
      events_dropped_duplicate(
          counter(registry, "behaviorlib_coordinator_events_duplicate_total",
                  "Events dropped as already seen (resume overlap) or of an activation the "
                  "coordinator had already finished")),
      events_lost(counter(registry, "behaviorlib_coordinator_events_lost_total",
                          "Events a system no longer retained when the coordinator resumed")),
      events_synthesized(counter(registry, "behaviorlib_coordinator_events_synthesized_total",
                                 "Finished events made by the coordinator for activations of "
                                 "systems that went down, restarted or left")),
      systems_registered(gauge(registry, "behaviorlib_coordinator_systems_registered",
                               "Behavior systems known to the coordinator")),
      systems_up(gauge(registry, "behaviorlib_coordinator_systems_up",
                       "Behavior systems whose event stream is established")),
      systems_down(counter(registry, "behaviorlib_coordinator_systems_down_total",
                           "Times supervision declared a behavior system down")),
      stream_reconnects(counter(registry, "behaviorlib_coordinator_stream_reconnects_total",
                                "Event streams to behavior systems re-opened after a break")),
      subscribers(gauge(registry, "behaviorlib_coordinator_subscribers",
                        "Open Coordinator.WatchEvents streams")),
      missions_started(prometheus::BuildCounter()
                           .Name("behaviorlib_coordinator_missions_started_total")
                           .Help("Missions started, by robot")
                           .Register(registry)),
      missions_finished(
          prometheus::BuildCounter()
              .Name("behaviorlib_coordinator_missions_finished_total")
              .Help("Missions ended, by robot, outcome (succeeded, failed, aborted) and cause "
                    "(the termination cause of the step that ended it, REFUSED for a refused "
                    "activation, NONE when no step did)")
              .Register(registry)),
      safety_actions(prometheus::BuildCounter()
                         .Name("behaviorlib_coordinator_safety_actions_total")
                         .Help("Safety actions taken, by robot, action (emergency_land, kill, "
                               "land, hover_then_land, hover_and_abort) and trigger (operator, "
                               "battery, geofence, lease_failsafe, controller_failure)")
                         .Register(registry)),
      missions_retained(gauge(registry, "behaviorlib_coordinator_missions_retained",
                              "Missions held: running, and ended ones retained")),
      mission_runners(gauge(registry, "behaviorlib_coordinator_mission_runners",
                            "Mission runners alive (thread and parsed mission): running "
                            "missions and those ended since the last start")),
      vehicle_watches(gauge(registry, "behaviorlib_coordinator_vehicle_watches",
                            "Open WatchVehicle streams (each a data-channel subscription)")) {}

void CoordinatorMetrics::missionEnded(const v1::MissionStatus& status) {
  std::string outcome = "failed";
  if (status.state() == v1::MISSION_STATE_SUCCEEDED) outcome = "succeeded";
  if (status.state() == v1::MISSION_STATE_ABORTED) outcome = "aborted";
  missions_finished
      .Add({{"robot", status.robot_id()}, {"outcome", outcome}, {"cause", missionEndCause(status)}})
      .Increment();
}

std::string missionEndCause(const v1::MissionStatus& status) {
  if (status.steps().empty()) return "NONE";
  // The last step record is the one the mission ended on (safety steps are
  // not recorded as steps).
  const v1::MissionStepRecord& last = status.steps(status.steps_size() - 1);
  if (last.state() == v1::MISSION_STEP_STATE_REFUSED) return "REFUSED";
  if (last.state() != v1::MISSION_STEP_STATE_FINISHED) return "NONE";
  if (status.state() != v1::MISSION_STATE_SUCCEEDED &&
      last.cause() == v1::TERMINATION_CAUSE_GOAL_ACHIEVED) {
    return "NONE";  // ended after its last step succeeded (a recurrent behavior, an abort)
  }
  const std::string name = v1::TerminationCause_Name(last.cause());
  constexpr std::string_view kPrefix = "TERMINATION_CAUSE_";
  return name.rfind(kPrefix, 0) == 0 ? name.substr(kPrefix.size()) : name;
}

}  // namespace behaviorlib::coordinator
