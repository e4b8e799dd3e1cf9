#pragma once

// GENERATE_PATH_WITH_OCCUPANCY_GRID (goal-based): plans from the current pose
// estimate to a goal against the system's lidar map (LidarMapper) inflated
// by the vehicle's radius, with OMPL's RRT-Connect (navigation/path_planner.h),
// and writes the path to belief memory and the data channel.
//
//   onActivate      the goal inside the map's box (else INVALID_ARGUMENT), at
//                   least the radius from occupied voxels (INVALID_ARGUMENT),
//                   the vehicle itself clear of them (FAILED_PRECONDITION);
//                   hands the first attempt to the behavior's background
//                   thread (inBackground; the result returns on the worker)
//   background job per attempt: a 26-connected flood fill of the inflated
//                   grid from the vehicle (no passage to the goal: the goal is
//                   unreachable), then planPath() with the attempt's time
//                   limit, then the path is published on
//                   robots/{id}/navigation/path (Path) and written to the
//                   belief key as a list of {x, y, z}
//   checkProcesses  the pose estimate older than pose_timeout_s (behavior
//                   clock), or the path could not be published or written
//                   -> PROCESS_FAILURE
//   checkSituation  before: a data channel, a fresh pose estimate, a map
//   checkGoal       the path written -> GOAL_ACHIEVED
//   checkProgress   the goal unreachable (or no longer valid on the updated
//                   map) -> WRONG_PROGRESS; an attempt that found nothing
//                   within planning_time_limit_s, or still runs past it (by
//                   wall time, the planner's computation time, plus a grace),
//                   is a planning time-out: re-plan, up to max_replans times,
//                   then the activation ends TIME_OUT (its maximum execution
//                   time is set to the time spent)
//
// Config (defaults): pose_timeout_s [0.5], timeout_grace_s [0.5] (wall
// time an attempt may run past its limit before it counts as timed out:
// building the inflated grid is not part of OMPL's budget),
// preferred_clearance_m [0.2] (distance beyond vehicle_radius_m that the
// shortened path keeps from obstacles where the space allows it; see
// PlanOptions).

#include <atomic>
#include <chrono>
#include <cstdint>
#include <optional>
#include <string>
#include <utility>

#include "behaviorlib/behavior_execution_manager.h"
#include "behaviorlib/navigation/path_planner.h"
#include "behaviorlib/navigation_with_lidar/lidar_mapper.h"
#include "behaviorlib/server/belief_client.h"
#include "behaviorlib/v1/behaviors/navigation_with_lidar.pb.h"

namespace behaviorlib::nav {

/// Topic of the planned paths.
std::string pathTopic(const std::string& robot_id);

/// Whether a 26-connected chain of free cells of `grid` (the box
/// [min_m, max_m] at `resolution_m`) joins `from` to `to`.
bool freelyConnected(const InflatedGrid& grid, const Eigen::Vector3d& min_m,
                     const Eigen::Vector3d& max_m, double resolution_m, const Eigen::Vector3d& from,
                     const Eigen::Vector3d& to);

class GeneratePathBehavior final : public Behavior<v1::GeneratePathWithOccupancyGridParameters> {
 public:
  /// `beliefs` may be null (no coordinator): the path then goes to the
  /// channel only.
  GeneratePathBehavior(LidarMapper& mapper, const server::BeliefClient* beliefs);

 protected:
  absl::Status onConfigure(const YAML::Node& config) override;
  absl::Status onActivate() override;
  void onDeactivate() override;
  void onPause() override;
  void onResume() override;
  absl::Status onModify(const google::protobuf::Message& new_parameters) override;

  Situation checkSituation() override;
  Verdict checkGoal() override;
  Verdict checkProgress() override;
  Verdict checkProcesses() override;

 private:
  enum class Outcome { kRunning, kWritten, kUnreachable, kTimedOut, kInvalid, kOutputFailed };
  /// An axis-aligned box: lowest and highest corner, metres, world frame.
  using Box = std::pair<Eigen::Vector3d, Eigen::Vector3d>;
  /// The map's planning volume (LidarMapper::planningVolumeLocked) clipped
  /// to `bounds` when given; nullopt for an empty map.
  std::optional<Box> planningVolume(const OccupancyMap& map,
                                    const std::optional<Box>& bounds) const;
  /// bounds_min_m/bounds_max_m of the activation, when both are given.
  std::optional<Box> boundsParameter() const;

  struct Attempt {
    uint64_t id = 0;
    Eigen::Vector3d start_m, goal_m;
    PlanOptions options;
    std::string belief_key;
    std::optional<Box> bounds;  ///< bounds_min_m/bounds_max_m, read on the behavior's thread
  };
  struct Result {
    uint64_t id = 0;
    Outcome outcome = Outcome::kRunning;
    std::string message;
    size_t waypoints = 0;
    double length_m = 0, planning_time_s = 0, min_clearance_m = 0;
  };

  void startAttempt();
  // The background job: reads only the attempt, the map, and current_id_.
  Result plan(const Attempt& attempt) const;
  std::string beliefKey() const;
  std::optional<std::string> poseProblem() const;

  LidarMapper& mapper_;
  const server::BeliefClient* beliefs_;
  Duration pose_timeout_ = std::chrono::milliseconds(500);
  double timeout_grace_s_ = 0.5;
  double preferred_clearance_m_ = 0.2;

  // Worker-thread state of the activation.
  Eigen::Vector3d start_m_ = Eigen::Vector3d::Zero();
  uint32_t replans_ = 0;
  bool paused_ = false;
  bool waiting_ = false;  // an attempt is due once resumed
  std::chrono::steady_clock::time_point attempt_started_{};

  Result result_;  // of the current attempt
  // The current attempt; the background job reads it to drop a superseded
  // or abandoned attempt's output.
  std::atomic<uint64_t> current_id_{0};
};

}  // namespace behaviorlib::nav
