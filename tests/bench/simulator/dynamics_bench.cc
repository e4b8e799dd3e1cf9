// Real-time factor of the simulator's dynamics: Quadrotor + Autopilot at a
// 1 kHz physics step, no sensors, no transport. The autopilot flies velocity
// setpoints that a motion controller would send at 50 Hz (a slow circle with
// some climbing and descending), so every loop of the cascade runs.
//
//   sim_dynamics_bench --benchmark_repetitions=5 --benchmark_report_aggregates_only=true
//
// Counter "rtf" = simulated seconds / wall-clock seconds (targets: >= 200 for
// one vehicle, >= 20 for ten). The per-component benchmarks give the cost of
// one physics step and one autopilot update.

#include <benchmark/benchmark.h>

#include <chrono>
#include <cmath>
#include <string>
#include <vector>

#include "simulator/dynamics/autopilot.h"
#include "simulator/dynamics/quadrotor.h"
#include "simulator/dynamics/world_sim.h"

namespace behaviorlib::sim {
namespace {

constexpr double kDt = 0.001;
constexpr int kStepsPerSimSecond = 1000;
constexpr int kSetpointEvery = 20;  // 50 Hz

QuadrotorParams benchParams() {
  QuadrotorParams p;
  p.battery_capacity_wh = 1e9;  // long runs must not end in a flat battery
  return p;
}

QuadrotorState hoveringAt(const QuadrotorParams& p, const Eigen::Vector3d& position_m) {
  QuadrotorState s;
  s.position_m = position_m;
  s.motor_speeds_rad_s.fill(p.hoverMotorSpeedRadS());
  return s;
}

Setpoint circleSetpoint(double t, int vehicle) {
  const double phase = 0.5 * t + 0.7 * vehicle;
  return VelocityYawRate{{2.0 * std::cos(phase), 2.0 * std::sin(phase), 0.5 * std::sin(0.3 * t)},
                         0.2 * std::cos(0.1 * t)};
}

// N vehicles in one WorldSim, one simulated second per iteration.
void BM_WorldSimVelocityMode(benchmark::State& state) {
  const int vehicles = static_cast<int>(state.range(0));
  const QuadrotorParams params = benchParams();
  WorldSim world;
  std::vector<SimVehicle*> fleet;
  for (int i = 0; i < vehicles; ++i) {
    fleet.push_back(world.addVehicle("drone" + std::to_string(i),
                                     hoveringAt(params, {20.0 * i, 0.0, 20.0}), params));
  }
  double sim_seconds = 0.0;
  double wall_seconds = 0.0;
  for (auto _ : state) {
    const auto start = std::chrono::steady_clock::now();
    for (int k = 0; k < kStepsPerSimSecond; ++k) {
      if (k % kSetpointEvery == 0) {
        const double t = world.timeS();
        for (int i = 0; i < vehicles; ++i) fleet[i]->setSetpoint(circleSetpoint(t, i));
      }
      world.step();
    }
    wall_seconds += std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    sim_seconds += 1.0;
  }
  for (const SimVehicle* v : fleet) {
    if (v->state().crashed || v->state().landed) {
      state.SkipWithError("a vehicle crashed or landed: the benchmark flew no real flight");
      return;
    }
  }
  state.counters["rtf"] = sim_seconds / wall_seconds;
  state.counters["vehicles"] = vehicles;
  state.counters["steps_per_s"] =
      benchmark::Counter(sim_seconds * kStepsPerSimSecond * vehicles, benchmark::Counter::kIsRate);
}
BENCHMARK(BM_WorldSimVelocityMode)
    ->ArgName("vehicles")
    ->Arg(1)
    ->Arg(10)
    ->UseRealTime()
    ->Unit(benchmark::kMillisecond);

// One Quadrotor::step at hover (the rigid body, motors, drag, battery).
void BM_QuadrotorStep(benchmark::State& state) {
  const QuadrotorParams params = benchParams();
  Quadrotor quad(params, hoveringAt(params, {0.0, 0.0, 1e6}));
  const double u = params.hoverMotorCommand();
  const MotorCommands commands{u, u, u, u};
  for (auto _ : state) {
    quad.step(kDt, commands);
    benchmark::DoNotOptimize(quad.state());
  }
}
BENCHMARK(BM_QuadrotorStep);

// One Autopilot::update in velocity mode (all four loops and the mixer).
void BM_AutopilotUpdate(benchmark::State& state) {
  const QuadrotorParams params = benchParams();
  Autopilot autopilot(params);
  QuadrotorState s = hoveringAt(params, {0.0, 0.0, 10.0});
  s.velocity_m_s = {0.5, -0.2, 0.1};
  s.orientation = Eigen::Quaterniond(Eigen::AngleAxisd(0.1, Eigen::Vector3d(1, 1, 0).normalized()));
  const Setpoint setpoint = VelocityYawRate{{2.0, 0.0, 0.0}, 0.1};
  for (auto _ : state) {
    MotorCommands u = autopilot.update(s, setpoint, kDt);
    benchmark::DoNotOptimize(u);
  }
}
BENCHMARK(BM_AutopilotUpdate);

}  // namespace
}  // namespace behaviorlib::sim

BENCHMARK_MAIN();
