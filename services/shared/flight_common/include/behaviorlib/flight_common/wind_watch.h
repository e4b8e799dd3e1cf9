#pragma once

// WindWatch: the flight behaviors' estimate of the wind they fly in, and what
// it does to their performance estimate (checkSituation). The vehicle has no
// anemometer: the wind is read from the lean the vehicle needs to hold
// against it — the pose estimate's attitude against the acceleration of the
// velocity estimate (motion::WindEstimator, services/motion_control/
// wind_estimator.h) — with the airframe's drag model from the behavior's
// config (FlightSettings: mass_kg, linear_drag_n_s_m, quadratic_drag_n_s2_m2,
// wind_time_constant_s, calm_wind_m_s, max_wind_m_s).
//
//   onConfigure     wind_.configure(settings_)
//   checkProcesses  wind_.observe(status_, pose_, twist_)      // every tick
//   checkSituation  Situation s = ...; wind_.apply(&s)         // performance x windPerformance
//   (before activation: wind_.observe(status, vehicle) reads the estimate once)
//
// The estimate is forgotten while the vehicle is not airborne (on the ground
// it leans on nothing).

#include "behaviorlib/behavior_execution_manager.h"
#include "behaviorlib/flight_common/flight_support.h"
#include "behaviorlib/flight_common/vehicle.h"
#include "behaviorlib/motion_control/wind_estimator.h"

namespace behaviorlib::flight {

class WindWatch {
 public:
  WindWatch() = default;

  /// Takes the drag model, filter and performance mapping of `settings`
  /// (forgets the estimate).
  void configure(const FlightSettings& settings);
  /// One sample of the pose and velocity estimates (the velocity's stamp
  /// times it).
  void observe(const v1::FlightStatus& status, const v1::PoseStamped& pose,
               const v1::TwistStamped& twist);
  /// Reads the pose and velocity estimates from `vehicle` (nothing on an
  /// error).
  void observe(const v1::FlightStatus& status, Vehicle& vehicle);
  void reset() { estimator_.reset(); }

  /// Multiplies a feasible situation's performance by
  /// motion::windPerformance(speed, calm_wind_m_s, max_wind_m_s) and, when
  /// that lowers it, adds a reason naming the estimated wind.
  void apply(Situation* situation) const;

  /// The estimated horizontal wind speed (m/s); 0 without an estimate.
  double speedMS() const { return estimator_.speedMS(); }
  /// windPerformance() of the present estimate.
  double performance() const;
  const motion::WindEstimator& estimator() const { return estimator_; }

 private:
  motion::WindEstimator estimator_;
  // observe(status, vehicle)'s reads.
  Held<v1::PoseStamped> pose_;
  Held<v1::TwistStamped> twist_;
  double calm_wind_m_s_ = 2.0;
  double max_wind_m_s_ = 10.0;
};

}  // namespace behaviorlib::flight
