// motion_control_bench: the controllers of the motion behavior systems, flown
// in closed loop against the simulator's dynamics and autopilot in-process
// (physics 1 kHz, controller 100 Hz): tracking error on the 4 m square at
// 1 m/s, PID beside MPC, with and without wind; and compute time per
// controller step (median and p99 of the wall time of update()).
//
//   motion_control_bench            # markdown tables
//   motion_control_bench --smoke    # fewer timing samples; fails only on errors

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstring>
#include <vector>

#include "behaviorlib/motion_control/mpc_controller.h"
#include "behaviorlib/motion_control/path_tracker.h"
#include "behaviorlib/motion_control/pid_controller.h"
#include "unit/motion_control/closed_loop.h"

namespace {

using namespace behaviorlib::motion;
using testing::ClosedLoop;

struct Tracking {
  double rms_m = 0, max_m = 0, duration_s = 0;
  bool completed = false;
};

Tracking fly(const char* which, const Eigen::Vector3d& wind) {
  ClosedLoop loop({0, 0, 1}, wind);
  PidMotionController pid(testing::modelOf(loop.params()), PidGains{});
  MpcMotionController mpc(testing::modelOf(loop.params()));
  ClosedLoop::Controller controller;
  if (std::strcmp(which, "PID") == 0) {
    controller = [&](const StateEstimate& s, const MotionReference& r, double dt) {
      return pid.update(s, r, dt);
    };
  } else {
    controller = [&](const StateEstimate& s, const MotionReference& r, double dt) {
      return mpc.update(s, r, dt);
    };
  }
  auto tracker = PathTracker::create(testing::square(), PathTrackerParams{}).value();
  const std::vector<double> errors = loop.followPath(tracker, controller, 120.0);
  Tracking t;
  t.rms_m = testing::rms(errors);
  t.max_m = *std::max_element(errors.begin(), errors.end());
  t.duration_s = static_cast<double>(errors.size()) * ClosedLoop::kControlDt;
  t.completed = tracker.referenceAtEnd();
  return t;
}

template <class Controller>
std::pair<double, double> timePerStep(Controller& controller, int samples) {
  auto tracker = PathTracker::create(testing::square(), PathTrackerParams{}).value();
  tracker.start({0, 0, 1}, 0.0);
  StateEstimate state;
  state.position_m = {0, 0, 1};
  std::vector<double> us;
  us.reserve(samples);
  for (int i = 0; i < samples; ++i) {
    const MotionReference r = tracker.update(state.position_m, 0.01);
    state.position_m = r.point.position_m + Eigen::Vector3d(0.05, -0.03, 0.02);  // a small error
    state.velocity_m_s = r.point.velocity_m_s;
    const auto start = std::chrono::steady_clock::now();
    const AttitudeThrustCommand c = controller.update(state, r, 0.01);
    const auto end = std::chrono::steady_clock::now();
    if (!std::isfinite(c.thrust_ratio)) std::exit(1);
    us.push_back(std::chrono::duration<double, std::micro>(end - start).count());
    if (tracker.referenceAtEnd()) tracker.start({0, 0, 1}, 0.0);
  }
  std::sort(us.begin(), us.end());
  return {us[us.size() / 2], us[static_cast<size_t>(0.99 * static_cast<double>(us.size()))]};
}

}  // namespace

int main(int argc, char** argv) {
  const bool smoke = argc > 1 && std::strcmp(argv[1], "--smoke") == 0;
  std::printf("| controller | wind (m/s) | RMS cross-track (m) | max (m) | flight time (s) |\n");
  std::printf("|---|---:|---:|---:|---:|\n");
  int failures = 0;
  for (double wind : {0.0, 2.0}) {
    for (const char* which : {"PID", "MPC"}) {
      const Tracking t = fly(which, {wind, 0.0, 0.0});
      if (!t.completed || !std::isfinite(t.rms_m)) ++failures;
      std::printf("| %s | %.1f | %.3f | %.3f | %.1f |\n", which, wind, t.rms_m, t.max_m,
                  t.duration_s);
    }
  }
  const int samples = smoke ? 200 : 20000;
  PidMotionController pid(VehicleModel{}, PidGains{});
  MpcMotionController mpc(VehicleModel{});
  const auto [pid_p50, pid_p99] = timePerStep(pid, samples);
  const auto [mpc_p50, mpc_p99] = timePerStep(mpc, samples);
  std::printf("\n| controller step | p50 (us) | p99 (us) |\n|---|---:|---:|\n");
  std::printf("| PID cascade | %.2f | %.2f |\n", pid_p50, pid_p99);
  std::printf("| MPC (N=%d, h=%.2f s, 3 axes) | %.2f | %.2f |\n", mpc.params().horizon_steps,
              mpc.params().step_s, mpc_p50, mpc_p99);
  return failures == 0 ? 0 : 1;
}
