#include "simulator/service/simulator_metrics.h"

#include <algorithm>
#include <string_view>

#include "simulator/service/channel_publisher.h"
#include "simulator/service/sensor_publisher.h"

namespace behaviorlib::sim {
namespace {

const prometheus::Histogram::BucketBoundaries& stepBuckets() {
  // A step of one vehicle's dynamics is ~0.4 us; with sensors a few us; a
  // lock-step that waits for a frame, milliseconds.
  static const prometheus::Histogram::BucketBoundaries kBuckets = {
      5e-7, 1e-6, 2.5e-6, 5e-6, 1e-5, 2.5e-5, 5e-5, 1e-4, 2.5e-4, 1e-3, 1e-2};
  return kBuckets;
}

const prometheus::Histogram::BucketBoundaries& frameBuckets() {
  // A 2-D lidar scan ~0.04 ms, 16 channels ~0.6 ms; a 640x480 frame ~4 ms.
  static const prometheus::Histogram::BucketBoundaries kBuckets = {
      2.5e-5, 5e-5, 1e-4, 2.5e-4, 5e-4, 1e-3, 2.5e-3, 5e-3, 1e-2, 2.5e-2, 5e-2, 0.1};
  return kBuckets;
}

prometheus::Gauge& gauge(prometheus::Registry& registry, const std::string& name,
                         const std::string& help) {
  return prometheus::BuildGauge().Name(name).Help(help).Register(registry).Add({});
}

/// Adds what a monotonic source counted since `seen` to `counter`.
void advance(prometheus::Counter& counter, uint64_t now, uint64_t& seen) {
  if (now > seen) counter.Increment(static_cast<double>(now - seen));
  seen = std::max(seen, now);
}

}  // namespace

SimulatorMetrics::SimulatorMetrics(prometheus::Registry& registry, Simulation& simulation,
                                   const TimeControl& time)
    : simulation_(simulation),
      time_(time),
      real_time_factor_(gauge(registry, "behaviorlib_simulator_real_time_factor",
                              "Simulated seconds per wall second achieved while free-running")),
      time_scale_(gauge(registry, "behaviorlib_simulator_time_scale",
                        "Simulated seconds per wall second asked for (SetTimeScale)")),
      lock_step_(gauge(registry, "behaviorlib_simulator_lock_step",
                       "1 while time advances only through Simulator.Step")),
      time_seconds_(
          gauge(registry, "behaviorlib_simulator_time_seconds", "Simulated time since Reset")),
      step_seconds_(prometheus::BuildHistogram()
                        .Name("behaviorlib_simulator_step_seconds")
                        .Help("Wall time of one physics step with its listeners (sensors, "
                              "publishers): the mean of each batch of steps")
                        .Register(registry)
                        .Add({}, stepBuckets())),
      position_(prometheus::BuildGauge()
                    .Name("behaviorlib_simulator_vehicle_position_meters")
                    .Help("Ground-truth position of a vehicle, world ENU")
                    .Register(registry)),
      battery_(prometheus::BuildGauge()
                   .Name("behaviorlib_simulator_vehicle_battery_ratio")
                   .Help("Battery state of charge of a vehicle, 0..1")
                   .Register(registry)),
      flight_state_(prometheus::BuildGauge()
                        .Name("behaviorlib_simulator_vehicle_flight_state")
                        .Help("1 for a vehicle's flight state, 0 for its other states "
                              "(LANDED, TAKING_OFF, FLYING, HOVERING, LANDING, EMERGENCY)")
                        .Register(registry)),
      crashed_(prometheus::BuildGauge()
                   .Name("behaviorlib_simulator_vehicle_crashed")
                   .Help("1 after a vehicle crashed (hard impact, tip-over, collision)")
                   .Register(registry)),
      samples_(prometheus::BuildCounter()
                   .Name("behaviorlib_simulator_sensor_samples_total")
                   .Help("Sensor samples handed to the publisher")
                   .Register(registry)),
      samples_dropped_(prometheus::BuildCounter()
                           .Name("behaviorlib_simulator_sensor_samples_dropped_total")
                           .Help("Sensor samples not published: reason \"fault\" (an injected "
                                 "off or intermittent fault) or \"worker_busy\" (a lidar or "
                                 "camera frame due before the previous one was done)")
                           .Register(registry)),
      frame_seconds_(prometheus::BuildHistogram()
                         .Name("behaviorlib_simulator_sensor_frame_seconds")
                         .Help("Wall time to make one lidar scan (ray casting) or camera frame "
                               "(rendering and encoding)")
                         .Register(registry)),
      publish_dropped_(prometheus::BuildCounter()
                           .Name("behaviorlib_simulator_publish_dropped_total")
                           .Help("Samples the publishing queue dropped because the broker was "
                                 "too slow, per stream (state: clock, ground truth, flight "
                                 "state; sensors)")
                           .Register(registry)),
      publish_gated_(
          prometheus::BuildCounter()
              .Name("behaviorlib_simulator_publish_gated_total")
              .Help("Samples not published because nobody wanted their topic, or its "
                    "readers wanted it only at a lower rate (DataChannel.WatchInterest), "
                    "per stream")
              .Register(registry)),
      pace_slips_(prometheus::BuildCounter()
                      .Name("behaviorlib_simulator_pace_slips_total")
                      .Help("Times the physics fell behind the scaled wall clock and the "
                            "published time line restarted from it (decision 16)")
                      .Register(registry)
                      .Add({})),
      active_faults_(prometheus::BuildGauge()
                         .Name("behaviorlib_simulator_active_faults")
                         .Help("Injected faults in effect per vehicle and component (motor: "
                               "how many motors; the wind has robot \"\")")
                         .Register(registry)),
      lidar_frame_seconds_(&frame_seconds_.Add({{"sensor", "lidar"}}, frameBuckets())),
      camera_frame_seconds_(&frame_seconds_.Add({{"sensor", "camera"}}, frameBuckets())),
      state_dropped_(publish_dropped_.Add({{"stream", "state"}})),
      sensors_dropped_(publish_dropped_.Add({{"stream", "sensors"}})),
      state_gated_(publish_gated_.Add({{"stream", "state"}})),
      sensors_gated_(publish_gated_.Add({{"stream", "sensors"}})),
      step_increments_(stepBuckets().size() + 1, 0.0) {
  simulation_.setStepTimer(
      [this](int steps, std::chrono::nanoseconds wall) { onBatch(steps, wall); });
}

SimulatorMetrics::~SimulatorMetrics() {
  stop();
  simulation_.setStepTimer({});
}

SensorSystem::FrameTimer SimulatorMetrics::frameTimer() {
  return [this](SensorKind kind, std::chrono::nanoseconds wall) {
    prometheus::Histogram* histogram =
        kind == SensorKind::kLidar ? lidar_frame_seconds_ : camera_frame_seconds_;
    histogram->Observe(std::chrono::duration<double>(wall).count());
  };
}

void SimulatorMetrics::onBatch(int steps, std::chrono::nanoseconds wall) {
  // One histogram update per batch: `steps` observations of the batch's mean
  // (the bucket Histogram::Observe would pick), the exact total as the sum.
  const double total_s = std::chrono::duration<double>(wall).count();
  const double mean_s = total_s / steps;
  const auto& bounds = stepBuckets();
  const std::size_t bucket = static_cast<std::size_t>(
      std::find_if(bounds.begin(), bounds.end(), [&](double b) { return b >= mean_s; }) -
      bounds.begin());
  std::fill(step_increments_.begin(), step_increments_.end(), 0.0);
  step_increments_[bucket] = steps;
  step_seconds_.ObserveMultiple(step_increments_, total_s);
}

void SimulatorMetrics::start(Sources sources, std::chrono::milliseconds period) {
  {
    std::lock_guard lock(update_mutex_);
    sources_ = sources;
  }
  std::lock_guard lock(thread_mutex_);
  if (thread_.joinable()) return;
  stopping_ = false;
  thread_ = std::thread([this, period] { run(period); });
}

void SimulatorMetrics::stop() {
  {
    std::lock_guard lock(thread_mutex_);
    stopping_ = true;
  }
  thread_cv_.notify_all();
  if (thread_.joinable()) thread_.join();
}

void SimulatorMetrics::run(std::chrono::milliseconds period) {
  std::unique_lock lock(thread_mutex_);
  while (!stopping_) {
    lock.unlock();
    update();
    lock.lock();
    thread_cv_.wait_for(lock, period, [this] { return stopping_; });
  }
}

void SimulatorMetrics::update() {
  std::lock_guard lock(update_mutex_);
  real_time_factor_.Set(simulation_.realTimeFactor());
  time_scale_.Set(time_.time_scale.load());
  lock_step_.Set(time_.lock_step.load() ? 1.0 : 0.0);
  time_seconds_.Set(std::chrono::duration<double>(simulation_.now()).count());
  updateVehicles();
  if (sources_.sensors != nullptr) {
    updateSensors(sources_.sensors->sensors());
    advance(sensors_dropped_, sources_.sensors->droppedCount(), sensors_dropped_seen_);
    advance(sensors_gated_, sources_.sensors->gatedCount(), sensors_gated_seen_);
  }
  if (sources_.state != nullptr) {
    advance(state_dropped_, sources_.state->droppedCount(), state_dropped_seen_);
    advance(state_gated_, sources_.state->gatedCount(), state_gated_seen_);
  }
  advance(pace_slips_, simulation_.slipCount(), slips_seen_);
  if (sources_.faults != nullptr) updateFaults(*sources_.faults);
}

void SimulatorMetrics::updateVehicles() {
  const std::vector<std::string> ids = simulation_.robotIds();
  // Vehicles gone with a Reset into another world lose their series.
  for (auto it = vehicles_.begin(); it != vehicles_.end();) {
    if (std::find(ids.begin(), ids.end(), it->first) != ids.end()) {
      ++it;
      continue;
    }
    VehicleSeries& s = it->second;
    for (prometheus::Gauge* g : s.position) position_.Remove(g);
    battery_.Remove(s.battery);
    for (const auto& [state, gauge] : s.flight_state) flight_state_.Remove(gauge);
    crashed_.Remove(s.crashed);
    it = vehicles_.erase(it);
  }
  for (const std::string& id : ids) {
    auto state = simulation_.vehicleState(id);
    if (!state.ok()) continue;  // removed meanwhile
    auto it = vehicles_.find(id);
    if (it == vehicles_.end()) {
      VehicleSeries s;
      const char* axes[3] = {"x", "y", "z"};
      for (int i = 0; i < 3; ++i)
        s.position[i] = &position_.Add({{"robot", id}, {"axis", axes[i]}});
      s.battery = &battery_.Add({{"robot", id}});
      // One series per state (kube-state-metrics' style): a dashboard or
      // an alert selects a state by name, and sum() over robots counts them.
      const auto* states = v1::FlightState_descriptor();
      for (int i = 0; i < states->value_count(); ++i) {
        const int number = states->value(i)->number();
        if (number == v1::FLIGHT_STATE_UNSPECIFIED) continue;
        std::string name = states->value(i)->name();
        constexpr std::string_view kPrefix = "FLIGHT_STATE_";
        if (name.rfind(kPrefix, 0) == 0) name = name.substr(kPrefix.size());
        s.flight_state.emplace_back(number, &flight_state_.Add({{"robot", id}, {"state", name}}));
      }
      s.crashed = &crashed_.Add({{"robot", id}});
      it = vehicles_.emplace(id, s).first;
    }
    const VehicleSnapshot& snapshot = state->first;
    for (int i = 0; i < 3; ++i) it->second.position[i]->Set(snapshot.position_m(i));
    it->second.battery->Set(snapshot.battery_ratio);
    for (const auto& [number, gauge] : it->second.flight_state) {
      gauge->Set(number == state->second ? 1.0 : 0.0);
    }
    it->second.crashed->Set(snapshot.crashed ? 1.0 : 0.0);
  }
}

void SimulatorMetrics::updateSensors(const SensorSystem& sensors) {
  for (const SensorSystem::SensorStats& stats : sensors.stats()) {
    auto key = std::make_pair(stats.robot_id, stats.kind);
    auto it = sensors_.find(key);
    if (it == sensors_.end()) {
      const std::string sensor(sensorName(stats.kind));
      SensorSeries s;
      s.samples = &samples_.Add({{"robot", stats.robot_id}, {"sensor", sensor}});
      s.fault_dropped = &samples_dropped_.Add(
          {{"robot", stats.robot_id}, {"sensor", sensor}, {"reason", "fault"}});
      if (stats.kind == SensorKind::kLidar || stats.kind == SensorKind::kCamera) {
        s.busy_dropped = &samples_dropped_.Add(
            {{"robot", stats.robot_id}, {"sensor", sensor}, {"reason", "worker_busy"}});
      }
      it = sensors_.emplace(key, s).first;
    }
    SensorSeries& s = it->second;
    advance(*s.samples, stats.published, s.published);
    advance(*s.fault_dropped, stats.fault_dropped, s.fault);
    if (s.busy_dropped != nullptr) advance(*s.busy_dropped, stats.frames_dropped, s.busy);
  }
}

void SimulatorMetrics::updateFaults(const FaultInjector& faults) {
  for (const FaultInjector::Active& active : faults.active()) {
    auto key = std::make_pair(active.robot_id, active.component);
    auto it = faults_.find(key);
    if (it == faults_.end()) {
      it = faults_
               .emplace(key, &active_faults_.Add(
                                 {{"robot", active.robot_id}, {"component", active.component}}))
               .first;
    }
    it->second->Set(active.count);
  }
}

}  // namespace behaviorlib::sim
