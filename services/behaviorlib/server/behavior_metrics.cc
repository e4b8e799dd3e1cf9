#include "behaviorlib/server/behavior_metrics.h"

#include <array>

namespace behaviorlib::server {

namespace {

const prometheus::Histogram::BucketBoundaries& monitoringBuckets() {
  // The paper's t1 is 0.1-3.9 us; cover 100 ns .. 10 ms.
  static const prometheus::Histogram::BucketBoundaries kBuckets = {
      1e-7, 2.5e-7, 5e-7, 1e-6, 2.5e-6, 5e-6, 1e-5, 2.5e-5, 5e-5, 1e-4, 1e-3, 1e-2};
  return kBuckets;
}

const prometheus::Histogram::BucketBoundaries& activationBuckets() {
  // The paper's t3 is 0.6-51.5 ms; ours is ~0.1 ms. Cover 10 us .. 1 s.
  static const prometheus::Histogram::BucketBoundaries kBuckets = {
      1e-5, 2.5e-5, 5e-5, 1e-4, 2.5e-4, 5e-4, 1e-3, 2.5e-3, 1e-2, 5e-2, 0.25, 1.0};
  return kBuckets;
}

constexpr std::array<v1::TerminationCause, 6> kCauses = {
    v1::TERMINATION_CAUSE_GOAL_ACHIEVED,   v1::TERMINATION_CAUSE_TIME_OUT,
    v1::TERMINATION_CAUSE_WRONG_PROGRESS,  v1::TERMINATION_CAUSE_SITUATION_CHANGE,
    v1::TERMINATION_CAUSE_PROCESS_FAILURE, v1::TERMINATION_CAUSE_INTERRUPTED};

}  // namespace

class PrometheusObserver final : public BehaviorObserver {
 public:
  PrometheusObserver(BehaviorMetrics& m, const std::string& behavior,
                     BehaviorMetrics::BlockedCallback on_blocked)
      : behavior_(behavior), on_blocked_(std::move(on_blocked)) {
    const prometheus::Labels labels = {
        {"robot", m.robot_id_}, {"system", m.system_}, {"behavior", behavior}};
    activations_ = &m.activations_.Add(labels);
    for (auto cause : kCauses) {
      auto with_cause = labels;
      with_cause["cause"] = causeName(cause);
      terminations_[cause] = &m.terminations_.Add(with_cause);
    }
    active_ = &m.active_.Add(labels);
    monitoring_ = &m.monitoring_.Add(labels, monitoringBuckets());
    monitoring_cpu_ = &m.monitoring_cpu_.Add(labels, monitoringBuckets());
    activation_ = &m.activation_.Add(labels, activationBuckets());
    activate_call_ = &m.activate_call_.Add(labels, activationBuckets());
    performance_ = &m.performance_.Add(labels);
    performance_->Set(1.0);
  }

  void onActivated(std::chrono::nanoseconds activate_call) override {
    activate_call_->Observe(std::chrono::duration<double>(activate_call).count());
    activations_->Increment();
    active_->Set(1);
  }
  void onFirstExecute(std::chrono::nanoseconds latency) override {
    activation_->Observe(std::chrono::duration<double>(latency).count());
  }
  void onFinished(v1::TerminationCause cause) override {
    if (cause >= 0 && static_cast<size_t>(cause) < terminations_.size() && terminations_[cause]) {
      terminations_[cause]->Increment();
    }
    active_->Set(0);
  }
  void onMonitoring(std::chrono::nanoseconds wall, std::chrono::nanoseconds cpu) override {
    monitoring_->Observe(std::chrono::duration<double>(wall).count());
    monitoring_cpu_->Observe(std::chrono::duration<double>(cpu).count());
  }
  void onSituation(double performance_ratio) override { performance_->Set(performance_ratio); }
  void onBlocked(bool blocked) override {
    if (on_blocked_) on_blocked_(behavior_, blocked);
  }

 private:
  std::string behavior_;
  BehaviorMetrics::BlockedCallback on_blocked_;
  prometheus::Counter* activations_ = nullptr;
  std::array<prometheus::Counter*, 7> terminations_{};
  prometheus::Gauge* active_ = nullptr;
  prometheus::Histogram* monitoring_ = nullptr;
  prometheus::Histogram* monitoring_cpu_ = nullptr;
  prometheus::Histogram* activation_ = nullptr;
  prometheus::Histogram* activate_call_ = nullptr;
  prometheus::Gauge* performance_ = nullptr;
};

BehaviorMetrics::BehaviorMetrics(prometheus::Registry& registry, std::string robot_id,
                                 std::string system)
    : robot_id_(std::move(robot_id)),
      system_(std::move(system)),
      activations_(prometheus::BuildCounter()
                       .Name("behaviorlib_activations_total")
                       .Help("Activations started")
                       .Register(registry)),
      terminations_(prometheus::BuildCounter()
                        .Name("behaviorlib_terminations_total")
                        .Help("Activations finished, by termination cause")
                        .Register(registry)),
      active_(prometheus::BuildGauge()
                  .Name("behaviorlib_active_behaviors")
                  .Help("1 while the behavior is active (or paused)")
                  .Register(registry)),
      monitoring_(prometheus::BuildHistogram()
                      .Name("behaviorlib_monitoring_seconds")
                      .Help("Wall time of the four monitoring functions of one tick (the "
                            "paper's t1)")
                      .Register(registry)),
      monitoring_cpu_(prometheus::BuildHistogram()
                          .Name("behaviorlib_monitoring_cpu_seconds")
                          .Help("CPU time of the thread running the four monitoring functions of "
                                "one tick (the paper's t1, without preemption)")
                          .Register(registry)),
      activation_(prometheus::BuildHistogram()
                      .Name("behaviorlib_activation_seconds")
                      .Help("Activate request received until the first onExecute (the paper's t3)")
                      .Register(registry)),
      activate_call_(prometheus::BuildHistogram()
                         .Name("behaviorlib_activate_call_seconds")
                         .Help("Activate request received until the activation was decided "
                               "(checkSituation and onActivate included): the part of t3 before "
                               "the first tick")
                         .Register(registry)),
      performance_(prometheus::BuildGauge()
                       .Name("behaviorlib_situation_performance_ratio")
                       .Help("Latest performance estimate of checkSituation, in [0, 1]")
                       .Register(registry)) {}

BehaviorHost::ObserverFactory BehaviorMetrics::observerFactory(BlockedCallback on_blocked) {
  return [this, on_blocked](
             const BehaviorExecutionManager& behavior) -> std::unique_ptr<BehaviorObserver> {
    return std::make_unique<PrometheusObserver>(*this, behavior.name(), on_blocked);
  };
}

}  // namespace behaviorlib::server
