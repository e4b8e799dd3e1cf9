#include "behaviorlib/navigation_with_lidar/map_behaviors.h"

#include <google/protobuf/struct.pb.h>

#include <utility>

namespace behaviorlib::nav {
namespace {

BehaviorOptions mapBehaviorOptions() {
  BehaviorOptions o;
  o.frequency_hz = 20.0;
  // Saving a large map and one belief write (2 s deadline).
  o.watchdog_timeout = std::chrono::seconds(5);
  return o;
}

}  // namespace

ClearOccupancyGridBehavior::ClearOccupancyGridBehavior(LidarMapper& mapper)
    : Behavior(mapBehaviorOptions()), mapper_(mapper) {}

absl::Status ClearOccupancyGridBehavior::onActivate() {
  mapper_.clear();
  return absl::OkStatus();
}

Verdict ClearOccupancyGridBehavior::checkGoal() {
  return Verdict::finish("the map is cleared; mapping goes on from the next scan");
}

SaveOccupancyGridBehavior::SaveOccupancyGridBehavior(LidarMapper& mapper,
                                                     const server::BeliefClient* beliefs,
                                                     server_kit::ConfinedDirectory maps)
    : Behavior(mapBehaviorOptions()), mapper_(mapper), beliefs_(beliefs), maps_(std::move(maps)) {}

absl::Status SaveOccupancyGridBehavior::onActivate() {
  const std::string& path = parameters().file_path();
  if (path.empty()) {
    return absl::InvalidArgumentError("file_path is empty: give the file to write the map to");
  }
  // Inside the system's --map-dir only: no "..", no link out of it, no
  // device or link at the file's place (a new file renamed over it).
  if (absl::Status s = maps_.resolveForWrite(path).status(); !s.ok()) {
    return absl::Status(s.code(), "file_path: " + std::string(s.message()));
  }
  belief_error_.reset();
  std::string bytes;
  mapper_.withMap([&](const OccupancyMap& map) {
    occupied_ = map.occupiedLeafCount();
    bytes = map.serialize(OccupancyMap::fullFormatFor(path));
  });
  absl::StatusOr<std::string> written = maps_.write(path, bytes);
  if (!written.ok()) {
    return absl::Status(written.status().code(),
                        "file_path: " + std::string(written.status().message()));
  }
  saved_path_ = *written;
  return absl::OkStatus();
}

Verdict SaveOccupancyGridBehavior::checkProcesses() {
  if (belief_error_) return Verdict::finish(*belief_error_);
  return Verdict::keepGoing();
}

Verdict SaveOccupancyGridBehavior::checkGoal() {
  std::string where = " (no coordinator: not in belief memory)";
  if (beliefs_) {
    const std::string key =
        parameters().belief_key().empty() ? robotId() + "/map_file" : parameters().belief_key();
    google::protobuf::Value value;
    value.set_string_value(saved_path_);
    auto written = beliefs_->write(key, value, robotId() + "/SAVE_OCCUPANCY_GRID");
    if (!written.ok()) {
      // Reported by checkProcesses on the next tick as a PROCESS_FAILURE.
      belief_error_ = "the map is saved to " + saved_path_ + " but belief '" + key +
                      "' cannot be written: " + std::string(written.status().message());
      return Verdict::keepGoing();
    }
    where = "; belief '" + key + "'";
  }
  return Verdict::finish("saved the map (" + std::to_string(occupied_) + " occupied voxels) to " +
                         saved_path_ + where);
}

}  // namespace behaviorlib::nav
