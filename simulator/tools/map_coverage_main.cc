// map_coverage: how much of a world's building a saved OctoMap knows.
//
//   map_coverage --world simulator/worlds/rooms.yaml --map building.bt [--json]
//       [--height-m 1.3] [--band-m 0.3] [--cell-m 0.1]
//
// Prints the plan-view mapped fraction of the building's free space at the
// lidar's height (navigation/tools/map_coverage.h says how it is counted);
// with --json, one JSON object. Exit 0 on success, 2 on bad arguments or
// files that cannot be read.

#include <octomap/OcTree.h>

#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <iostream>
#include <memory>
#include <string>

#include "formats/world/world.h"
#include "simulator/tools/map_coverage.h"

namespace {

constexpr char kUsage[] =
    "usage: map_coverage --world WORLD.yaml --map MAP.bt|MAP.ot [--json]\n"
    "                    [--height-m H] [--band-m B] [--cell-m C] [--cells FILE]\n"
    "  --world     the simulator's world file (its walls bound the building)\n"
    "  --map       an OctoMap saved by SAVE_OCCUPANCY_GRID (.bt, or .ot)\n"
    "  --height-m  height of the plan view in metres, world frame (default 1.3:\n"
    "              flight altitude 1.2 m plus the lidar's 0.1 m mount)\n"
    "  --band-m    a free voxel this far above or below counts (default 0.3)\n"
    "  --cell-m    plan-view cell edge in metres (default 0.1)\n"
    "  --json      print one JSON object instead of text\n"
    "  --cells     write the map's occupied cells at that height (plan view, one\n"
    "              centre per cell) to FILE as JSON: {cell_m, occupied_xy_m}\n";

int usage(const std::string& problem) {
  std::cerr << "map_coverage: " << problem << "\n" << kUsage;
  return 2;
}

bool parsePositive(const std::string& text, double* value) {
  char* end = nullptr;
  const double v = std::strtod(text.c_str(), &end);
  if (end == text.c_str() || *end != '\0' || !(v > 0.0)) return false;
  *value = v;
  return true;
}

std::unique_ptr<octomap::OcTree> readMap(const std::string& path, std::string* error) {
  if (!std::ifstream(path).good()) {
    *error = "cannot read the map file " + path;
    return nullptr;
  }
  if (path.size() > 3 && path.compare(path.size() - 3, 3, ".ot") == 0) {
    std::unique_ptr<octomap::AbstractOcTree> tree(octomap::AbstractOcTree::read(path));
    auto* octree = dynamic_cast<octomap::OcTree*>(tree.get());
    if (octree == nullptr) {
      *error = path + " is not an OcTree in OctoMap's full (.ot) format";
      return nullptr;
    }
    tree.release();
    return std::unique_ptr<octomap::OcTree>(octree);
  }
  auto tree = std::make_unique<octomap::OcTree>(0.1);
  if (!tree->readBinary(path)) {
    *error = path + " is not an OctoMap binary (.bt) file";
    return nullptr;
  }
  return tree;
}

}  // namespace

int main(int argc, char** argv) {
  std::string world_path, map_path, cells_path;
  bool json = false;
  behaviorlib::nav::CoverageOptions options;
  for (int i = 1; i < argc; ++i) {
    const std::string arg = argv[i];
    if (arg == "--help" || arg == "-h") {
      std::cout << kUsage;
      return 0;
    }
    if (arg == "--json") {
      json = true;
      continue;
    }
    if (i + 1 >= argc) return usage(arg + " needs a value");
    const std::string value = argv[++i];
    if (arg == "--world") {
      world_path = value;
    } else if (arg == "--map") {
      map_path = value;
    } else if (arg == "--cells") {
      cells_path = value;
    } else if (arg == "--height-m") {
      if (!parsePositive(value, &options.height_m)) return usage("--height-m must be > 0");
    } else if (arg == "--band-m") {
      if (!parsePositive(value, &options.band_m)) return usage("--band-m must be > 0");
    } else if (arg == "--cell-m") {
      if (!parsePositive(value, &options.cell_m)) return usage("--cell-m must be > 0");
    } else {
      return usage("unknown option " + arg);
    }
  }
  if (world_path.empty() || map_path.empty()) return usage("--world and --map are required");

  auto world = behaviorlib::world::loadWorld(world_path);
  if (!world.ok()) {
    std::cerr << "map_coverage: " << world.status().message() << "\n";
    return 2;
  }
  std::string error;
  const std::unique_ptr<octomap::OcTree> map = readMap(map_path, &error);
  if (map == nullptr) {
    std::cerr << "map_coverage: " << error << "\n";
    return 2;
  }
  const behaviorlib::nav::MapCoverage c = behaviorlib::nav::measureCoverage(*world, *map, options);
  if (!cells_path.empty()) {
    std::FILE* out = std::fopen(cells_path.c_str(), "w");
    if (out == nullptr) {
      std::cerr << "map_coverage: --cells: cannot write " << cells_path << "\n";
      return 2;
    }
    std::fprintf(out, "{\"cell_m\": %.3f, \"occupied_xy_m\": [", options.cell_m);
    for (size_t i = 0; i < c.occupied_xy_m.size(); ++i) {
      std::fprintf(out, "%s[%.3f, %.3f]", i ? ", " : "", c.occupied_xy_m[i].x(),
                   c.occupied_xy_m[i].y());
    }
    std::fprintf(out, "]}\n");
    if (std::fclose(out) != 0) {
      std::cerr << "map_coverage: --cells: cannot write " << cells_path << "\n";
      return 2;
    }
  }
  if (c.free_cells == 0) {
    std::cerr << "map_coverage: " << world_path << " has no walls: no building to cover\n";
    return 2;
  }
  if (json) {
    std::printf(
        "{\"mapped_fraction\": %.4f, \"free_cells\": %zu, \"known_free_cells\": %zu, "
        "\"occupied_free_cells\": %zu, \"free_area_m2\": %.2f, \"mapped_area_m2\": %.2f, "
        "\"height_m\": %.3f, \"band_m\": %.3f, \"cell_m\": %.3f, "
        "\"building_min_m\": [%.2f, %.2f], \"building_max_m\": [%.2f, %.2f], "
        "\"occupied_voxels\": %zu, \"wall_error_mean_m\": %.4f, \"wall_error_max_m\": %.4f}\n",
        c.mappedFraction(), c.free_cells, c.known_free_cells, c.occupied_cells, c.freeAreaM2(),
        c.mappedAreaM2(), options.height_m, options.band_m, options.cell_m, c.building_min_m.x(),
        c.building_min_m.y(), c.building_max_m.x(), c.building_max_m.y(), c.occupied_voxels,
        c.wall_error_mean_m, c.wall_error_max_m);
  } else {
    std::printf(
        "mapped fraction of the building's free space at %.2f m: %.1f %% (%.1f of %.1f m^2; "
        "%zu free cells marked occupied)\n"
        "wall error: %zu occupied voxels within %.2f m of that height are %.3f m from the "
        "world's surfaces on average (at most %.3f m)\n",
        options.height_m, 100.0 * c.mappedFraction(), c.mappedAreaM2(), c.freeAreaM2(),
        c.occupied_cells, c.occupied_voxels, options.band_m, c.wall_error_mean_m,
        c.wall_error_max_m);
  }
  return 0;
}
