#pragma once

// Prometheus metrics of a behavior system, labelled robot, system, behavior
// (and cause). Label sets are resolved once per behavior at start, never per
// tick.
//
//   BehaviorMetrics metrics(registry, "drone1", "basic_quadrotor_behaviors");
//   host.setObserverFactory(metrics.observerFactory());

#include <prometheus/counter.h>
#include <prometheus/family.h>
#include <prometheus/gauge.h>
#include <prometheus/histogram.h>
#include <prometheus/registry.h>

#include <functional>
#include <memory>
#include <string>

#include "behaviorlib/behavior_host.h"

namespace behaviorlib::server {

class BehaviorMetrics {
 public:
  BehaviorMetrics(prometheus::Registry& registry, std::string robot_id, std::string system);
  /// Called when a behavior is blocked by the watchdog (true) and when it
  /// recovers (false); e.g. to report it NOT_SERVING through gRPC health.
  using BlockedCallback = std::function<void(const std::string& behavior, bool blocked)>;
  /// Creates one observer per behavior (for BehaviorHost::setObserverFactory).
  BehaviorHost::ObserverFactory observerFactory(BlockedCallback on_blocked = nullptr);

 private:
  friend class PrometheusObserver;
  std::string robot_id_;
  std::string system_;
  prometheus::Family<prometheus::Counter>& activations_;
  prometheus::Family<prometheus::Counter>& terminations_;
  prometheus::Family<prometheus::Gauge>& active_;
  prometheus::Family<prometheus::Histogram>& monitoring_;
  prometheus::Family<prometheus::Histogram>& monitoring_cpu_;
  prometheus::Family<prometheus::Histogram>& activation_;
  prometheus::Family<prometheus::Histogram>& activate_call_;
  prometheus::Family<prometheus::Gauge>& performance_;
};

}  // namespace behaviorlib::server
