#pragma once

// Flies a motion controller in closed loop against the simulator's
// quadrotor dynamics and autopilot, in-process with fixed steps: physics at
// 1 kHz, the controller at 100 Hz sending attitude + thrust setpoints, as the
// motion behavior systems do through the FlightController.

#include <cmath>
#include <functional>
#include <vector>

#include "behaviorlib/motion_control/motion_types.h"
#include "behaviorlib/motion_control/path_tracker.h"
#include "simulator/dynamics/autopilot.h"
#include "simulator/dynamics/quadrotor.h"

namespace behaviorlib::motion::testing {

inline VehicleModel modelOf(const sim::QuadrotorParams& p) {
  VehicleModel m;
  m.mass_kg = p.mass_kg;
  m.max_thrust_n = p.maxThrustN();
  m.gravity_m_s2 = p.gravity_m_s2;
  return m;
}

class ClosedLoop {
 public:
  /// `controller(state, reference, dt)` returns the attitude command.
  using Controller =
      std::function<AttitudeThrustCommand(const StateEstimate&, const MotionReference&, double)>;

  explicit ClosedLoop(const Eigen::Vector3d& start, Eigen::Vector3d wind = Eigen::Vector3d::Zero())
      : quad_(params_, hovering(start)), autopilot_(params_) {
    quad_.setWindVelocity(wind);
  }

  const sim::QuadrotorParams& params() const { return params_; }
  StateEstimate estimate() const {
    StateEstimate e;
    e.position_m = quad_.state().position_m;
    e.velocity_m_s = quad_.state().velocity_m_s;
    e.orientation = quad_.state().orientation;
    return e;
  }

  /// One 10 ms control period: the controller, then ten physics steps.
  void step(const Controller& controller, const MotionReference& reference) {
    const AttitudeThrustCommand cmd = controller(estimate(), reference, kControlDt);
    const sim::Setpoint setpoint = sim::AttitudeThrust{cmd.orientation, cmd.thrust_ratio};
    for (int i = 0; i < 10; ++i)
      quad_.step(0.001, autopilot_.update(quad_.state(), setpoint, 0.001));
  }

  /// Follows `tracker`'s path; returns the cross-track errors sampled every
  /// control step until the reference reached the end and the vehicle is
  /// within 0.1 m of it (or `max_s` of flight).
  std::vector<double> followPath(PathTracker& tracker, const Controller& controller, double max_s) {
    std::vector<double> errors;
    tracker.start(estimate().position_m, estimate().yawRad());
    for (double t = 0; t < max_s; t += kControlDt) {
      const MotionReference ref = tracker.update(estimate().position_m, kControlDt);
      step(controller, ref);
      errors.push_back(tracker.crossTrackErrorM(estimate().position_m));
      if (tracker.referenceAtEnd() &&
          (estimate().position_m - tracker.points().back()).norm() < 0.1)
        break;
    }
    return errors;
  }

  static constexpr double kControlDt = 0.01;

 private:
  sim::QuadrotorState hovering(const Eigen::Vector3d& start) const {
    sim::QuadrotorState s;
    s.position_m = start;
    s.motor_speeds_rad_s.fill(params_.hoverMotorSpeedRadS());
    return s;
  }

  sim::QuadrotorParams params_;
  sim::Quadrotor quad_;
  sim::Autopilot autopilot_;
};

inline double rms(const std::vector<double>& v) {
  double sum = 0;
  for (double x : v) sum += x * x;
  return v.empty() ? NAN : std::sqrt(sum / static_cast<double>(v.size()));
}

/// The 4 m square of the flight-behavior tests, at 1 m altitude.
inline std::vector<Eigen::Vector3d> square() {
  return {{4, 0, 1}, {4, 4, 1}, {0, 4, 1}, {0, 0, 1}};
}

}  // namespace behaviorlib::motion::testing
