// navigation_with_lidar: the behavior system that maps with the lidar while
// it runs and plans paths on that map (GENERATE_PATH_WITH_OCCUPANCY_GRID,
// CLEAR_OCCUPANCY_GRID, SAVE_OCCUPANCY_GRID), explores an area by its
// frontiers (EXPLORE_WITH_FRONTIERS: motion references, followed by a motion
// system's controller; --flight-controller for the flight state), and
// localizes with the lidar (SELF_LOCALIZE_AND_MAP_WITH_LIDAR).

#include <cstdlib>
#include <filesystem>
#include <iostream>
#include <memory>

#include "absl/flags/flag.h"
#include "behaviorlib/config/v1/navigation_with_lidar.pb.h"
#include "behaviorlib/flight_common/remote_vehicle.h"
#include "behaviorlib/motion_behaviors/motion_link.h"
#include "behaviorlib/navigation_with_lidar/explore_behavior.h"
#include "behaviorlib/navigation_with_lidar/generate_path_behavior.h"
#include "behaviorlib/navigation_with_lidar/lidar_mapper.h"
#include "behaviorlib/navigation_with_lidar/map_behaviors.h"
#include "behaviorlib/navigation_with_lidar/navigate_behavior.h"
#include "behaviorlib/navigation_with_lidar/slam_behavior.h"
#include "behaviorlib/server/behavior_system_main.h"
#include "behaviorlib/server_kit/confined_files.h"
#include "behaviorlib/v1/behaviors/navigation_with_lidar.behaviors.h"

ABSL_FLAG(std::string, map_dir, "",
          "directory SAVE_OCCUPANCY_GRID writes maps in (file_path relative to it, or inside "
          "it; no '..', no link out of it); made if missing; empty: maps cannot be saved");

int main(int argc, char** argv) {
  return behaviorlib::server::runBehaviorSystem(
      argc, argv, "navigation_with_lidar", [](behaviorlib::server::BehaviorSystemBuilder& b) {
        namespace nav = behaviorlib::nav;
        const auto& context = b.context();
        // The system's own keys (the mapping: section), declared in
        // proto/behaviorlib/config/v1/navigation_with_lidar.proto.
        auto system = b.systemConfiguration<behaviorlib::config::v1::NavigationWithLidarConfig>();
        absl::Status configured = system.status();
        nav::MapperSettings settings;
        if (configured.ok()) configured = settings.configure(system->mapping());
        if (!configured.ok()) {
          std::cerr << "navigation_with_lidar: --config: " << configured.message() << std::endl;
          std::exit(2);
        }
        auto& mapper =
            b.own(std::make_unique<nav::LidarMapper>(context.channel, context.robot_id, settings));
        // Deterministic mode: the map holds every scan received before a grant
        // is reported, whatever the machine's load.
        b.addCatchUpCheck([&mapper] { return mapper.caughtUp(); });
        b.add<nav::SlamBehavior>(context.channel, settings.lidar_mount_m);
        b.add<nav::GeneratePathBehavior>(mapper, context.beliefs);
        auto& vehicle = b.own(std::make_unique<behaviorlib::flight::RemoteVehicle>(context));
        auto& link = b.own(std::make_unique<behaviorlib::motion_behaviors::RemoteMotionLink>(
            context.channel, context.robot_id));
        b.add<nav::ExploreBehavior>(mapper, vehicle, link);
        b.add<nav::NavigateBehavior>(mapper, vehicle, link);
        b.add<nav::ClearOccupancyGridBehavior>(mapper);
        const std::string map_dir = absl::GetFlag(FLAGS_map_dir);
        std::error_code made;
        if (!map_dir.empty()) std::filesystem::create_directories(map_dir, made);
        auto maps = behaviorlib::server_kit::ConfinedDirectory::open("maps", map_dir, 0);
        if (!maps.ok()) {
          std::cerr << "navigation_with_lidar: --map-dir: " << maps.status().message()
                    << (made ? " (" + made.message() + ")" : "") << std::endl;
          std::exit(2);
        }
        b.add<nav::SaveOccupancyGridBehavior>(mapper, context.beliefs, std::move(*maps));
      });
}
