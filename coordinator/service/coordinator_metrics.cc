#include "coordinator/service/coordinator_metrics.h"

#include <string>

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
                        "Open Coordinator.WatchEvents streams")) {}

}  // namespace behaviorlib::coordinator
