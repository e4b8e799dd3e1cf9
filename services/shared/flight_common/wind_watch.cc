#include "behaviorlib/flight_common/wind_watch.h"

#include "behaviorlib/flight_common/flight_monitoring.h"

namespace behaviorlib::flight {

void WindWatch::configure(const FlightSettings& settings) {
  estimator_ = motion::WindEstimator(settings.wind);
  calm_wind_m_s_ = settings.calm_wind_m_s;
  max_wind_m_s_ = settings.max_wind_m_s;
}

void WindWatch::observe(const v1::FlightStatus& status, const v1::PoseStamped& pose,
                        const v1::TwistStamped& twist) {
  if (!airborne(status.state())) {
    estimator_.reset();
    return;
  }
  const auto& q = pose.pose().orientation();
  const auto& v = twist.twist().linear_m_s();
  const double t_s =
      std::chrono::duration<double>(stampTime(twist.header()).time_since_epoch()).count();
  estimator_.add(t_s, Eigen::Quaterniond(q.w(), q.x(), q.y(), q.z()),
                 Eigen::Vector3d(v.x(), v.y(), v.z()));
}

void WindWatch::observe(const v1::FlightStatus& status, Vehicle& vehicle) {
  if (!airborne(status.state())) {
    estimator_.reset();
    return;
  }
  if (!vehicle.readPoseEstimate(&pose_).ok() || !vehicle.readTwistEstimate(&twist_).ok()) return;
  observe(status, *pose_, *twist_);
}

double WindWatch::performance() const {
  return motion::windPerformance(estimator_.speedMS(), calm_wind_m_s_, max_wind_m_s_);
}

void WindWatch::apply(Situation* situation) const {
  if (!situation->feasible || !estimator_.hasEstimate()) return;
  const double factor = performance();
  if (factor >= 1.0) return;
  situation->performance_ratio *= factor;
  // Not a refusal but a lowered performance: no code names the weather.
  situation->add(v1::SITUATION_REASON_UNSPECIFIED,
                 "wind of about " + fixed2(speedMS()) +
                     " m/s (estimated from the vehicle's lean; calm_wind_m_s " +
                     fixed2(calm_wind_m_s_) + ", max_wind_m_s " + fixed2(max_wind_m_s_) +
                     "): performance x" + fixed2(factor));
}

}  // namespace behaviorlib::flight
