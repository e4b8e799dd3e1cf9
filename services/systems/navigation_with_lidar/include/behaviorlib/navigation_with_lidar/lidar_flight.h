#pragma once

// What the behaviors that fly on the lidar map share (EXPLORE_WITH_FRONTIERS,
// NAVIGATE_TO): the map's part of their situation, the check of the path
// ahead against walls seen since it was planned, following a path or
// holding a position.

#include <Eigen/Core>
#include <functional>
#include <optional>
#include <vector>

#include "absl/status/statusor.h"
#include "behaviorlib/behavior_execution_manager.h"
#include "behaviorlib/motion_behaviors/follow_path_behavior.h"
#include "behaviorlib/motion_behaviors/reference_support.h"
#include "behaviorlib/motion_control/path_tracker.h"
#include "behaviorlib/navigation_with_lidar/lidar_mapper.h"

namespace behaviorlib::nav {

/// Infeasible without a data channel; otherwise `vehicle()` (the reference
/// behavior's own situation), infeasible too before an activation (`active`
/// false) while the map is empty.
Situation lidarFlightSituation(const LidarMapper& mapper, const std::function<Situation()>& vehicle,
                               bool active);

/// Whether the next `look_ahead_m` of the polyline `points`, from `done_m`
/// along it (the distance the reference covered), now passes within
/// `radius_m` of an occupied voxel: a wall seen since it was planned
/// (unknown space counts as free for the plan). Sampled every half voxel.
bool pathAheadBlocked(const LidarMapper& mapper, const std::vector<Eigen::Vector3d>& points,
                      double done_m, double look_ahead_m, double radius_m);

/// A path follower along `path` (waypoints, world frame) at `speed_m_s`,
/// started from the vehicle's position and yaw, or continuing from
/// `*continue_from` (the reference of the path followed until now: no jump,
/// no stop); makePathTracker's errors.
absl::StatusOr<motion::PathTracker> trackerFromVehicle(
    const std::vector<Eigen::Vector3d>& path, double speed_m_s,
    const motion_behaviors::PathSettings& settings,
    const motion_behaviors::ReferenceSupport& support,
    const motion::ReferencePoint* continue_from = nullptr);

/// One tick's reference: `tracker`'s, advanced since `last_update` (then
/// set to `now`), when it is given; else a position reference that holds
/// `*hold_m` (the vehicle's position, kept in `hold_m`, when it is empty)
/// at the vehicle's yaw.
void followOrHold(motion_behaviors::ReferenceSupport& support, motion::PathTracker* tracker,
                  std::optional<Eigen::Vector3d>& hold_m, TimePoint& last_update, TimePoint now);

}  // namespace behaviorlib::nav
