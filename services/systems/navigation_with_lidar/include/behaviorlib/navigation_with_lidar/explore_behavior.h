#pragma once

// EXPLORE_WITH_FRONTIERS (goal-based): explores an area given by its bounds
// on the system's lidar map (LidarMapper), flying by motion references as
// FOLLOW_PATH does (motion_behaviors/reference_support.h).
//
//   onActivate      bounds ordered, altitude_m inside them and the planning
//                   altitudes (INVALID_ARGUMENT); a fresh estimate and a
//                   flying vehicle (ReferenceSupport); the first choice is
//                   started
//   choice (background, per leg): the map's slice at the lidar's plane over
//                   the area (MapSlice), its known fraction and frontiers; a
//                   breadth-first search over the inflated grid at altitude_m
//                   from the vehicle; the frontier whose reachable cell
//                   nearest its centre is nearest the vehicle (by that
//                   search), not within 0.5 m of a target given up before;
//                   planPath() to it (a failed plan: the next is tried; a
//                   choice whose every plan failed is made again, up to 3
//                   times in a row, before those targets are given up)
//   onExecute       the leg's PathTracker reference (or holding the vehicle's
//                   position while choosing or paused)
//   checkGoal       no reachable frontier left, or the known fraction at
//                   coverage -> GOAL_ACHIEVED
//   checkProgress   a leg ends when its reference reached the end and the
//                   vehicle is within 0.3 m of it (then a new choice); when
//                   the next look_ahead_m of its path meets a wall seen since
//                   it was planned (checked every 0.2 s: the vehicle holds, a
//                   new choice); when it strays beyond max_cross_track_m or
//                   stalls (the target is given up, a new choice); the known fraction
//                   growing by less than 0.01 over stall_s -> WRONG_PROGRESS
//   checkProcesses  ReferenceSupport's (estimate, controller) -> PROCESS_FAILURE
//   time_limit_s    the activation's maximum execution time -> TIME_OUT
//
// Config (its section of --config; the keys, their ranges and defaults are
// declared in proto/behaviorlib/config/v1/navigation_with_lidar.proto,
// ExploreWithFrontiersConfig): besides ReferenceSupport's (MotionConfig) and
// PathSettings' (PathConfig) keys, frequency_hz [50], min_frontier_cells [5]
// (shorter frontiers are noise: half a metre at 0.1 m), slice_half_height_m
// [0.15] (the slice around the lidar's plane), look_ahead_m [3] (how much of
// the path ahead is checked against the map).

#include <Eigen/Core>
#include <cstdint>
#include <optional>
#include <stop_token>
#include <string>
#include <utility>
#include <vector>

#include "behaviorlib/behavior_execution_manager.h"
#include "behaviorlib/config/v1/navigation_with_lidar.pb.h"
#include "behaviorlib/flight_common/flight_monitoring.h"
#include "behaviorlib/motion_behaviors/follow_path_behavior.h"
#include "behaviorlib/motion_behaviors/reference_support.h"
#include "behaviorlib/motion_control/path_tracker.h"
#include "behaviorlib/navigation_with_lidar/lidar_mapper.h"
#include "behaviorlib/v1/behaviors/navigation_with_lidar.pb.h"

namespace behaviorlib::nav {

class ExploreBehavior final
    : public motion_behaviors::ReferenceBehavior<v1::ExploreWithFrontiersParameters,
                                                 config::v1::ExploreWithFrontiersConfig> {
 public:
  ExploreBehavior(LidarMapper& mapper, flight::Vehicle& vehicle,
                  motion_behaviors::MotionLink& link);

 protected:
  absl::Status onConfigure(const config::v1::ExploreWithFrontiersConfig& config) override;
  absl::Status onActivate() override;
  void onExecute() override;
  void onDeactivate() override;
  void onPause() override;
  void onResume() override;
  absl::Status onModify(const v1::ExploreWithFrontiersParameters& new_parameters) override;

  Situation checkSituation() override;
  Verdict checkGoal() override;
  Verdict checkProgress() override;

 public:
  /// What one choice found (the background job's result).
  struct Choice {
    bool done = false;  ///< no choice made yet
    double known_fraction = 0;
    size_t frontiers = 0, unreachable = 0;
    std::optional<Eigen::Vector3d> target_m;
    std::vector<Eigen::Vector3d> path_m;
    std::vector<Eigen::Vector3d> given_up;  ///< targets whose plan failed in this choice
    std::string message;                    ///< why nothing was chosen
    std::string plan_failure;               ///< the first failed plan's error
  };

 private:
  struct Request {
    Eigen::Vector3d start_m, lo_m, hi_m;
    double altitude_m = 0, radius_m = 0;
    std::vector<Eigen::Vector3d> given_up;
  };
  Choice choose(const Request& request, std::stop_token stop) const;
  void startChoice();
  void startLeg(const std::vector<Eigen::Vector3d>& path);
  /// Whether the next look_ahead_m of the leg's path now passes within the
  /// vehicle's radius of an occupied voxel (a wall seen since it was planned:
  /// unknown space counts as free for the plan).
  bool legBlocked() const;

  LidarMapper& mapper_;
  motion_behaviors::PathSettings path_settings_;
  size_t min_frontier_cells_ = 5;
  double slice_half_height_m_ = 0.15;
  double look_ahead_m_ = 3.0;
  Duration check_interval_ = std::chrono::milliseconds(200);

  // Worker-thread state of the activation.
  enum class Phase { kChoosing, kFlying, kDone };
  Phase phase_ = Phase::kChoosing;
  bool paused_ = false;
  Choice choice_;  // the latest finished choice
  std::optional<motion::PathTracker> tracker_;
  std::vector<Eigen::Vector3d> leg_path_;
  TimePoint last_check_{};
  uint32_t stops_ = 0;           // legs stopped by a wall seen on the way
  uint32_t failed_choices_ = 0;  // choices in a row whose every plan failed
  std::optional<Eigen::Vector3d> hold_m_;
  std::vector<Eigen::Vector3d> given_up_;
  TimePoint last_update_{};
  flight::DwellTracker lagging_{std::chrono::seconds(3)};
  double known_fraction_ = 0;
  double last_growth_value_ = 0;  // the known fraction when it last grew by 0.01
  TimePoint last_growth_time_{};
  uint32_t legs_ = 0;
  double flown_m_ = 0;
  std::string done_message_;
  // Calls off the running choice (inBackground's cancellation).
  std::stop_source choosing_;
};

}  // namespace behaviorlib::nav
