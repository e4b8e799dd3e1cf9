#pragma once

// The console map's world: the boxes (walls, with their doors left open, and
// obstacles) and QR markers of a simulator world file, as JSON for the page
// (GET /api/world).

#include <string>

#include "absl/status/statusor.h"

namespace behaviorlib::console {

/// {"boxes": [{name, kind: "wall"|"box", center_m, size_m, yaw_rad}],
///  "markers": [{name, text, center_m}]}, or the file's error with its line.
absl::StatusOr<std::string> worldJson(const std::string& path);

}  // namespace behaviorlib::console
