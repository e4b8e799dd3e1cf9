#include "simulator/core/simulation.h"

#include <algorithm>
#include <limits>
#include <thread>

#include "behaviorlib/error_details.h"

namespace behaviorlib::sim {

Simulation::Simulation(SimulationOptions options) : options_(options) {}

absl::Status Simulation::addVehicle(const std::string& robot_id,
                                    std::unique_ptr<VehicleModel> model) {
  std::lock_guard lock(mutex_);
  if (vehicles_.count(robot_id)) {
    return absl::AlreadyExistsError("vehicle " + robot_id + " is already in the world");
  }
  Vehicle vehicle{VehiclePlatform(robot_id, options_.platform), std::move(model)};
  vehicle.model->setWind(wind_);
  vehicle.platform.update(now_, vehicle.model->snapshot());
  vehicles_.emplace(robot_id, std::move(vehicle));
  return absl::OkStatus();
}

void Simulation::resetVehicles(std::map<std::string, std::unique_ptr<VehicleModel>> vehicles,
                               const std::function<void()>& then) {
  std::lock_guard lock(mutex_);
  vehicles_.clear();
  now_ = SimTime{0};
  ++epoch_;
  {
    // Readers of the pace see the restart at once, also in lock-step.
    std::lock_guard pace_lock(pace_mutex_);
    pace_ = Pace{now_, std::chrono::steady_clock::now(), pace_.scale, epoch_, pace_.generation + 1};
  }
  wind_ = Wind{};
  for (auto& [id, model] : vehicles) {
    Vehicle vehicle{VehiclePlatform(id, options_.platform), std::move(model)};
    vehicle.platform.update(now_, vehicle.model->snapshot());
    vehicles_.emplace(id, std::move(vehicle));
  }
  if (then) then();
}

std::vector<std::string> Simulation::robotIds() const {
  std::lock_guard lock(mutex_);
  std::vector<std::string> ids;
  for (const auto& [id, vehicle] : vehicles_) ids.push_back(id);
  return ids;
}

void Simulation::addStepListener(StepListener listener) {
  std::lock_guard lock(mutex_);
  listeners_.push_back(std::move(listener));
}

void Simulation::setStepTimer(StepTimer timer) {
  std::lock_guard lock(mutex_);
  step_timer_ = std::move(timer);
}

void Simulation::setWind(const Wind& wind) {
  std::lock_guard lock(mutex_);
  wind_ = wind;
  for (auto& [id, vehicle] : vehicles_) vehicle.model->setWind(wind_);
}

Wind Simulation::wind() const {
  std::lock_guard lock(mutex_);
  return wind_;
}

void Simulation::stepBatchLocked(SimTime target, int max_steps) {
  // Two clock reads per batch, not per step: the timer sees the mean.
  const auto start =
      step_timer_ ? std::chrono::steady_clock::now() : std::chrono::steady_clock::time_point{};
  int steps = 0;
  for (; steps < max_steps && now_ < target; ++steps) stepLocked();
  if (step_timer_ && steps > 0) step_timer_(steps, std::chrono::steady_clock::now() - start);
}

SimTime Simulation::now() const {
  std::lock_guard lock(mutex_);
  return now_;
}

absl::Status Simulation::unknownVehicle(const std::string& robot_id) const {
  std::string known;
  for (const auto& [id, vehicle] : vehicles_) known += (known.empty() ? "" : ", ") + id;
  return errors::withReason(
      absl::NotFoundError("unknown vehicle '" + robot_id +
                          "'; the world has: " + (known.empty() ? std::string("none") : known)),
      v1::UNKNOWN_VEHICLE, {{"robot", robot_id}});
}

void Simulation::stepLocked() {
  const double dt = std::chrono::duration<double>(options_.physics_step).count();
  for (auto& [id, vehicle] : vehicles_) {
    // The platform decides with the state at the start of the step; the
    // model integrates the step with that command.
    vehicle.platform.update(now_, vehicle.model->snapshot());
    vehicle.model->command(vehicle.platform.command());
    vehicle.model->step(dt);
  }
  now_ += options_.physics_step;
  if (listeners_.empty()) return;
  reports_.clear();
  for (const auto& [id, vehicle] : vehicles_) {
    reports_.push_back({&id, vehicle.model->snapshot(), &vehicle.platform});
  }
  for (auto& listener : listeners_) listener(now_, reports_);
}

void Simulation::advance(SimDuration duration) {
  std::lock_guard lock(mutex_);
  stepBatchLocked(now_ + duration, std::numeric_limits<int>::max());
}

Pace Simulation::pace() const {
  std::lock_guard lock(pace_mutex_);
  return pace_;
}

void Simulation::setPace(SimTime sim, std::chrono::steady_clock::time_point wall, double scale,
                         uint64_t epoch) {
  std::lock_guard lock(pace_mutex_);
  pace_ = Pace{sim, wall, scale, epoch, pace_.generation + 1};
}

void Simulation::runRealTime(const std::atomic<double>& time_scale, const std::atomic<bool>& paused,
                             const std::atomic<bool>& stop) {
  using Clock = std::chrono::steady_clock;
  // The line being followed (restarted by a slip), and the start of the
  // measured real-time factor (restarted only when the pace is changed).
  auto wall_start = Clock::now();
  SimTime sim_start = now();
  auto rate_wall_start = wall_start;
  SimTime rate_sim_start = sim_start;
  double scale = time_scale.load();
  bool was_paused = true;  // the first pass anchors the line
  uint64_t epoch = 0;
  {
    std::lock_guard lock(mutex_);
    epoch = epoch_;
  }
  while (!stop.load()) {
    if (paused.load()) {
      if (!was_paused) {
        std::lock_guard lock(mutex_);
        setPace(now_, Clock::now(), 0.0, epoch_);  // lock-step: others advance time
      }
      was_paused = true;
      std::this_thread::sleep_for(std::chrono::milliseconds(5));
      continue;
    }
    const double current = time_scale.load();
    if (current != scale || was_paused) {  // re-anchor: the new pace applies from now on
      was_paused = false;
      scale = current;
      std::lock_guard lock(mutex_);
      wall_start = rate_wall_start = Clock::now();
      sim_start = rate_sim_start = now_;
      epoch = epoch_;
      setPace(sim_start, wall_start, scale, epoch);
    }
    const auto wall_elapsed = Clock::now() - wall_start;
    const SimTime target =
        sim_start + std::chrono::duration_cast<SimDuration>(wall_elapsed * scale);
    SimTime reached;
    {
      std::lock_guard lock(mutex_);
      if (epoch_ != epoch) {  // time restarted (Reset): pace from here
        epoch = epoch_;
        wall_start = rate_wall_start = Clock::now();
        sim_start = rate_sim_start = now_;
        setPace(sim_start, wall_start, scale, epoch);
        continue;
      }
      // Catch up in bounded batches so that RPCs get the mutex in between.
      stepBatchLocked(target, 100);
      reached = now_;
      const auto wall_now = Clock::now();
      if (reached + kSlipLag < target && wall_now - wall_start >= kMinLineAge) {
        // Behind the line: restart it from here, so that readers
        // extrapolating it are never far ahead of the physics.
        wall_start = wall_now;
        sim_start = reached;
        setPace(sim_start, wall_start, scale, epoch);
        slips_.fetch_add(1, std::memory_order_relaxed);
      }
    }
    const double wall_s = std::chrono::duration<double>(Clock::now() - rate_wall_start).count();
    if (wall_s > 0.5) {
      real_time_factor_.store(std::chrono::duration<double>(reached - rate_sim_start).count() /
                              wall_s);
    }
    if (reached >= target) {
      // Ahead of the scaled wall clock: sleep until the next step is due,
      // but at least kMinWallSleep, so that above 1x the steps come in
      // small batches instead of a wake-up per step (10 000 a second at 10x).
      const auto due = wall_start + std::chrono::duration_cast<Clock::duration>(
                                        (reached - sim_start + options_.physics_step) / scale);
      std::this_thread::sleep_until(std::max(due, Clock::now() + kMinWallSleep));
    }
  }
}

absl::StatusOr<std::pair<VehicleSnapshot, v1::FlightState>> Simulation::vehicleState(
    const std::string& robot_id) const {
  std::lock_guard lock(mutex_);
  auto it = vehicles_.find(robot_id);
  if (it == vehicles_.end()) return unknownVehicle(robot_id);
  return std::make_pair(it->second.model->snapshot(), it->second.platform.state());
}

}  // namespace behaviorlib::sim
