#include "behaviorlib/navigation_with_lidar/lidar_flight.h"

#include <algorithm>

#include "behaviorlib/motion_behaviors/motion_messages.h"

namespace behaviorlib::nav {

Situation lidarFlightSituation(const LidarMapper& mapper, const std::function<Situation()>& vehicle,
                               bool active) {
  if (!mapper.channel()) {
    return Situation::infeasible(
        v1::SITUATION_REASON_CONFIGURATION,
        "no data channel configured: start the behavior system with --channel HOST:PORT");
  }
  Situation s = vehicle();
  if (!active) {
    const bool empty =
        mapper.withMap([](const OccupancyMap& map) { return map.tree().size() == 0; });
    if (empty) {
      s.feasible = false;
      s.performance_ratio = 0;
      s.add(v1::SITUATION_REASON_MAP_UNAVAILABLE,
            "the map is empty: no lidar scan on " + mapper.scanTopic() + " has been mapped yet");
    }
  }
  return s;
}

bool pathAheadBlocked(const LidarMapper& mapper, const std::vector<Eigen::Vector3d>& points,
                      double done_m, double look_ahead_m, double radius_m) {
  return mapper.withMap([&](const OccupancyMap& map) {
    const double step = 0.5 * map.resolutionM();
    double at = 0.0;  // distance along the path of points[i - 1]
    for (size_t i = 1; i < points.size(); ++i) {
      const Eigen::Vector3d a = points[i - 1], b = points[i];
      const double length = (b - a).norm();
      for (double s = std::max(0.0, done_m - at); s <= length; s += step) {
        if (at + s > done_m + look_ahead_m) return false;
        if (map.collides(a + (b - a) * (length > 0 ? s / length : 0.0), radius_m)) return true;
      }
      at += length;
    }
    return false;
  });
}

absl::StatusOr<motion::PathTracker> trackerFromVehicle(
    const std::vector<Eigen::Vector3d>& path, double speed_m_s,
    const motion_behaviors::PathSettings& settings,
    const motion_behaviors::ReferenceSupport& support,
    const motion::ReferencePoint* continue_from) {
  constexpr double kAccelerationM_S2 = 0.5;
  google::protobuf::RepeatedPtrField<v1::Vector3> points;
  for (const Eigen::Vector3d& q : path) motion_behaviors::toProto(q, points.Add());
  auto tracker = motion_behaviors::makePathTracker(points, speed_m_s, kAccelerationM_S2, settings,
                                                   support.settings().min_altitude_m);
  if (!tracker.ok()) return tracker;
  if (continue_from != nullptr) {
    tracker->continueFrom(*continue_from, support.yawRad());
  } else {
    tracker->start(support.state().position_m, support.yawRad());
  }
  return tracker;
}

void followOrHold(motion_behaviors::ReferenceSupport& support, motion::PathTracker* tracker,
                  std::optional<Eigen::Vector3d>& hold_m, TimePoint& last_update, TimePoint now) {
  const double dt = std::chrono::duration<double>(now - last_update).count();
  last_update = now;
  if (tracker != nullptr) {
    // A refused sample shows in the controller's status (it stops following).
    (void)support.publish(tracker->update(support.state().position_m, dt), now);
    return;
  }
  if (!hold_m) hold_m = support.state().position_m;
  motion::MotionReference reference;
  reference.mode = motion::MotionReference::Mode::kPosition;
  reference.point.position_m = *hold_m;
  reference.point.yaw_rad = support.yawRad();
  (void)support.publish(reference, now);
}

}  // namespace behaviorlib::nav
