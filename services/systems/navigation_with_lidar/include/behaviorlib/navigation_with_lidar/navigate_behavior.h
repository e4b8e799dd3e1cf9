#pragma once

// NAVIGATE_TO (goal-based): flies to a point the map need not have seen, on
// the system's lidar map (LidarMapper), by motion references as FOLLOW_PATH
// and EXPLORE_WITH_FRONTIERS do (decision 48).
//
//   onActivate      bounds ordered and not too large, the goal inside them at
//                   a planning altitude, the vehicle inside them
//                   (INVALID_ARGUMENT); a fresh estimate and a flying vehicle
//                   (ReferenceSupport); the first plan is started
//   plan (background): planThroughUnknown() from the vehicle to the goal in
//                   the lidar's plane at the goal's altitude, unknown space
//                   free at unknown_cost, at most max_unknown_m of it
//   onExecute       the path's PathTracker reference, or holding the
//                   vehicle's position while planning or paused
//   checkGoal       within arrival_radius_m of the goal -> GOAL_ACHIEVED
//   checkProgress   a plan that failed: planned again on a newer map, up to
//                   3 times, then WRONG_PROGRESS with the planner's reason
//                   (unreachable: blocked on every side seen so far); the
//                   next look_ahead_m of the path meeting a wall seen since
//                   the plan (checked every 0.2 s): the vehicle holds and a
//                   new plan is made; straying beyond max_cross_track_m or
//                   stalling behind the reference: the same; while flying,
//                   a new plan at most every replan_interval_s when the map
//                   changed, followed when shorter than what is left by
//                   replan_gain; the way left not shrinking by 0.5 m over
//                   stall_s -> WRONG_PROGRESS
//   checkProcesses  ReferenceSupport's (estimate, controller) -> PROCESS_FAILURE
//   time_limit_s    the activation's maximum execution time -> TIME_OUT
//
// The finished message counts the plans (made, followed while flying, made
// after a wall ahead), the paths' length and the planning times.

#include <Eigen/Core>
#include <cstdint>
#include <optional>
#include <stop_token>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "behaviorlib/behavior_execution_manager.h"
#include "behaviorlib/config/v1/navigation_with_lidar.pb.h"
#include "behaviorlib/flight_common/flight_monitoring.h"
#include "behaviorlib/motion_behaviors/follow_path_behavior.h"
#include "behaviorlib/motion_behaviors/reference_support.h"
#include "behaviorlib/motion_control/path_tracker.h"
#include "behaviorlib/navigation/unknown_space_planner.h"
#include "behaviorlib/navigation_with_lidar/lidar_mapper.h"
#include "behaviorlib/v1/behaviors/navigation_with_lidar.pb.h"

namespace behaviorlib::nav {

class NavigateBehavior final
    : public motion_behaviors::ReferenceBehavior<v1::NavigateToParameters,
                                                 config::v1::NavigateToConfig> {
 public:
  NavigateBehavior(LidarMapper& mapper, flight::Vehicle& vehicle,
                   motion_behaviors::MotionLink& link);

  /// One plan (the background job's result).
  struct Plan {
    bool done = false;  ///< no result yet
    absl::Status status;
    UnknownSpacePlan path;
    uint64_t revision = 0;  ///< the map's, when planned
  };

 protected:
  absl::Status onConfigure(const config::v1::NavigateToConfig& config) override;
  absl::Status onActivate() override;
  void onExecute() override;
  void onDeactivate() override;
  void onPause() override;
  void onResume() override;
  absl::Status onModify(const v1::NavigateToParameters& new_parameters) override;

  Situation checkSituation() override;
  Verdict checkGoal() override;
  Verdict checkProgress() override;

 private:
  UnknownSpacePlanOptions planOptions() const;
  /// Plans in the background, from the vehicle, or from the reference while
  /// `flying` (the path followed is kept until the plan is known to be
  /// better).
  void startPlan(bool flying);
  /// The background job: plans on the map with nothing of the worker's but
  /// what it is given.
  Plan plan(const Eigen::Vector3d& start_m, const Eigen::Vector3d& goal_m,
            const UnknownSpacePlanOptions& options, std::stop_token stop) const;
  void startPath(const std::vector<Eigen::Vector3d>& path);
  void toPlanning();
  /// Whether the next look_ahead_m of the path now passes within the
  /// vehicle's radius of an occupied voxel.
  bool pathBlocked() const;
  /// What is left of the way to the goal (m): along the path followed, or
  /// the last plan's length while planning.
  double wayLeftM() const;
  std::string summary() const;

  LidarMapper& mapper_;
  motion_behaviors::PathSettings path_settings_;
  double look_ahead_m_ = 3.0;
  double slice_half_height_m_ = 0.15;
  double unknown_cost_ = 1.5;
  double preferred_clearance_m_ = 0.2;
  Duration replan_interval_ = std::chrono::seconds(1);
  double replan_gain_ = 0.15;
  Duration check_interval_ = std::chrono::milliseconds(200);
  Duration retry_interval_ = std::chrono::seconds(1);

  // Worker-thread state of the activation.
  enum class Phase { kPlanning, kFlying, kDone };
  Phase phase_ = Phase::kPlanning;
  bool paused_ = false;
  bool planning_ = false;  // a plan runs in the background
  Plan plan_;              // the latest finished plan
  std::optional<motion::PathTracker> tracker_;
  uint64_t path_revision_ = 0;  // the map's when the path followed was planned
  std::optional<Eigen::Vector3d> hold_m_;
  TimePoint last_update_{}, last_check_{}, last_plan_{};
  flight::DwellTracker lagging_{std::chrono::seconds(3)};
  uint32_t failures_ = 0;  // failed plans in a row
  std::string failure_;    // the last one's reason
  double best_way_m_ = 0;  // the least way left, and when it last shrank by 0.5 m
  TimePoint best_way_time_{};
  double last_plan_length_m_ = 0;
  // Counts for the finished message and the figures.
  uint32_t plans_ = 0, followed_ = 0, stops_ = 0, astray_ = 0;
  double paths_m_ = 0, unknown_m_ = 0;
  std::vector<double> plan_times_s_;
  std::string done_message_;
  // Calls off the running plan (inBackground's cancellation).
  std::stop_source planning_stop_;
};

}  // namespace behaviorlib::nav
