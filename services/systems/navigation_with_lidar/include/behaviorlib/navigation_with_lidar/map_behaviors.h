#pragma once

// CLEAR_OCCUPANCY_GRID and SAVE_OCCUPANCY_GRID (goal-based): act on the
// system's lidar map (LidarMapper) at activation and finish GOAL_ACHIEVED on
// the first tick.
//
//   CLEAR_OCCUPANCY_GRID  onActivate clears the map (mapping goes on).
//   SAVE_OCCUPANCY_GRID   onActivate writes the map to file_path (.bt, or
//                         .ot for OctoMap's full format), relative to the
//                         system's --map-dir or inside it; a path outside
//                         refuses the activation with PERMISSION_DENIED
//                         naming the directory, a path that cannot be
//                         written with INVALID_ARGUMENT naming it. The file's absolute path
//                         then goes to belief memory (belief_key, default
//                         {robot_id}/map_file) from checkGoal;
//                         checkProcesses -> PROCESS_FAILURE when that write
//                         fails.
//
// Config: none of their own (google::protobuf::Empty): their sections take
// the library's keys only, and any other key is refused at start.

#include <google/protobuf/empty.pb.h>

#include <optional>
#include <string>

#include "behaviorlib/behavior_execution_manager.h"
#include "behaviorlib/navigation_with_lidar/lidar_mapper.h"
#include "behaviorlib/server/belief_client.h"
#include "behaviorlib/server_kit/confined_files.h"
#include "behaviorlib/v1/behaviors/navigation_with_lidar.pb.h"

namespace behaviorlib::nav {

class ClearOccupancyGridBehavior final
    : public Behavior<v1::ClearOccupancyGridParameters, google::protobuf::Empty> {
 public:
  explicit ClearOccupancyGridBehavior(LidarMapper& mapper);

 protected:
  absl::Status onActivate() override;
  Verdict checkGoal() override;

 private:
  LidarMapper& mapper_;
};

class SaveOccupancyGridBehavior final
    : public Behavior<v1::SaveOccupancyGridParameters, google::protobuf::Empty> {
 public:
  /// `beliefs` may be null (no coordinator): the file is saved, no belief
  /// written. Files are written inside `maps` only.
  SaveOccupancyGridBehavior(LidarMapper& mapper, const server::BeliefClient* beliefs,
                            server_kit::ConfinedDirectory maps);

 protected:
  absl::Status onActivate() override;
  Verdict checkGoal() override;
  Verdict checkProcesses() override;

 private:
  LidarMapper& mapper_;
  const server::BeliefClient* beliefs_;
  const server_kit::ConfinedDirectory maps_;
  std::string saved_path_;
  size_t occupied_ = 0;
  std::optional<std::string> belief_error_;
};

}  // namespace behaviorlib::nav
