#pragma once

// GENERATE_PATH_WITH_OCCUPANCY_GRID (goal-based): plans from the current pose
// estimate to a goal against the system's lidar map (LidarMapper) inflated
// by the vehicle's radius, with OMPL's RRT-Connect (navigation/path_planner.h),
// and writes the path to belief memory and the data channel.
//
//   onActivate      the goal finite and in bounds (bounds_min_m/bounds_max_m
//                   and the planning altitudes; else INVALID_ARGUMENT "out of
//                   bounds"), the vehicle itself inside the planning volume
//                   and clear of obstacles (FAILED_PRECONDITION); hands the
//                   first attempt to the behavior's background thread
//                   (inBackground; the result returns on the worker)
//   background job per attempt, from the newest pose estimate: the goal
//                   outside the space mapped so far, or not seen and cut off,
//                   is "unknown"; an occupied voxel within the radius of the
//                   goal, or no 26-connected chain of free cells to it, is
//                   "blocked"; else planPath() with the attempt's time limit
//                   and the uncertainty margin, and the path is published on
//                   robots/{id}/navigation/path (Path) and written to the
//                   belief key as a list of {x, y, z}
//   checkProcesses  the pose estimate older than pose_timeout_s (behavior
//                   clock), or the path could not be published or written
//                   -> PROCESS_FAILURE
//   checkSituation  before: a data channel, a fresh pose estimate, a map
//   checkGoal       the path written -> GOAL_ACHIEVED
//   checkProgress   unknown or blocked: a new attempt at each change of the
//                   map (new scans), until map_wait_s of the behavior clock
//                   has passed since the first such result -> WRONG_PROGRESS
//                   naming the cause; the plan impossible otherwise ->
//                   WRONG_PROGRESS; an attempt that found nothing within
//                   planning_time_limit_s, or still runs past it (by wall
//                   time, the planner's computation time, plus a grace), is a
//                   planning time-out: re-plan, up to max_replans times, then
//                   the activation ends TIME_OUT (its maximum execution time
//                   is set to the time spent)
//
// The uncertainty margin: uncertainty_sigmas times the pose estimate's
// horizontal_stddev_m (0 when the estimator does not report it), at most
// max_uncertainty_margin_m, added to the inflation where the space allows
// (planPath; decision 27).
//
// Config (its section of --config; the keys, their ranges and defaults are
// declared in proto/behaviorlib/config/v1/navigation_with_lidar.proto,
// GeneratePathWithOccupancyGridConfig): pose_timeout_s [0.5],
// timeout_grace_s [0.5] (wall time an attempt may run past its limit before
// it counts as timed out: building the inflated grid is not part of OMPL's
// budget), preferred_clearance_m [0.2] (distance beyond vehicle_radius_m
// that the shortened path keeps from obstacles where the space allows it;
// see PlanOptions), uncertainty_sigmas [2], max_uncertainty_margin_m [0.3].

#include <chrono>
#include <cstdint>
#include <optional>
#include <stop_token>
#include <string>
#include <utility>

#include "behaviorlib/behavior_execution_manager.h"
#include "behaviorlib/config/v1/navigation_with_lidar.pb.h"
#include "behaviorlib/flight_common/flight_support.h"
#include "behaviorlib/navigation/path_planner.h"
#include "behaviorlib/navigation_with_lidar/lidar_mapper.h"
#include "behaviorlib/server/belief_client.h"
#include "behaviorlib/v1/behaviors/navigation_with_lidar.pb.h"

namespace behaviorlib::nav {

/// Topic of the planned paths.
std::string pathTopic(const std::string& robot_id);

class GeneratePathBehavior final
    : public Behavior<v1::GeneratePathWithOccupancyGridParameters,
                      config::v1::GeneratePathWithOccupancyGridConfig> {
 public:
  /// `beliefs` may be null (no coordinator): the path then goes to the
  /// channel only.
  GeneratePathBehavior(LidarMapper& mapper, const server::BeliefClient* beliefs);

 protected:
  absl::Status onConfigure(const config::v1::GeneratePathWithOccupancyGridConfig& config) override;
  absl::Status onActivate() override;
  void onDeactivate() override;
  void onPause() override;
  void onResume() override;
  absl::Status onModify(const v1::GeneratePathWithOccupancyGridParameters& new_parameters) override;

  Situation checkSituation() override;
  Verdict checkGoal() override;
  Verdict checkProgress() override;
  Verdict checkProcesses() override;

 private:
  enum class Outcome {
    kRunning,
    kWritten,
    kUnknown,  ///< the goal in space not yet seen: wait for the map
    kBlocked,  ///< mapped obstacles at or around the goal: wait for the map
    kTimedOut,
    kInvalid,
    kOutputFailed
  };
  /// An axis-aligned box: lowest and highest corner, metres, world frame.
  using Box = std::pair<Eigen::Vector3d, Eigen::Vector3d>;
  /// The map's planning volume (LidarMapper::planningVolumeLocked) clipped
  /// to `bounds` when given; nullopt for an empty map.
  std::optional<Box> planningVolume(const OccupancyMap& map,
                                    const std::optional<Box>& bounds) const;
  /// bounds_min_m/bounds_max_m of the activation, when both are given.
  std::optional<Box> boundsParameter() const;

  struct Attempt {
    Eigen::Vector3d start_m, goal_m;
    PlanOptions options;
    std::string belief_key;
    std::optional<Box> bounds;  ///< bounds_min_m/bounds_max_m, read on the behavior's thread
    double stddev_m = 0;        ///< the pose estimate's horizontal_stddev_m
  };
  struct Result {
    Outcome outcome = Outcome::kRunning;
    std::string message;
    size_t waypoints = 0;
    double length_m = 0, planning_time_s = 0, min_clearance_m = 0;
    uint64_t map_revision = 0;  ///< of the map the attempt was judged on
  };

  void startAttempt();
  // The background job: reads only the attempt and the map; `stop` says
  // that a newer attempt or the activation's end called it off.
  Result plan(const Attempt& attempt, std::stop_token stop) const;
  std::string beliefKey() const;
  /// No pose estimate, or a stale one: the reason with its code.
  std::optional<flight::SituationProblem> poseProblem() const;
  uint64_t mapRevision() const;
  /// The outcome while waiting for the map: a new attempt when the map has
  /// changed, the end once map_wait_s has passed.
  Verdict waitForTheMap();

  LidarMapper& mapper_;
  const server::BeliefClient* beliefs_;
  Duration pose_timeout_ = std::chrono::milliseconds(500);
  double timeout_grace_s_ = 0.5;
  double preferred_clearance_m_ = 0.2;
  double uncertainty_sigmas_ = 2.0;
  double max_uncertainty_margin_m_ = 0.3;

  // Worker-thread state of the activation.
  Eigen::Vector3d start_m_ = Eigen::Vector3d::Zero();
  uint32_t replans_ = 0;
  bool paused_ = false;
  bool waiting_ = false;  // an attempt is due once resumed
  std::chrono::steady_clock::time_point attempt_started_{};
  std::optional<TimePoint> waiting_since_;  // the first unknown/blocked result
  uint32_t map_changes_ = 0;                // attempts made again on a changed map

  Result result_;  // of the current attempt
  // Calls off the running attempt (inBackground's cancellation): a
  // superseded or abandoned attempt writes nothing.
  std::stop_source attempt_;
};

}  // namespace behaviorlib::nav
