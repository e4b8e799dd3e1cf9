#pragma once

// The shipped building (simulator/worlds/rooms.yaml) as text, and the
// variants the navigation tests fly in: the C-D door walled up. Needs
// BEHAVIORLIB_WORLDS_DIR.

#include <fstream>
#include <optional>
#include <sstream>
#include <string>

namespace support {

/// simulator/worlds/rooms.yaml's text ("" if it cannot be read).
inline std::string roomsWorldText() {
  std::ifstream in(std::string(BEHAVIORLIB_WORLDS_DIR) + "/rooms.yaml");
  std::stringstream all;
  all << in.rdbuf();
  return all.str();
}

/// The building with the door between rooms C and D walled up; nullopt when
/// the world file no longer declares that door as expected.
inline std::optional<std::string> roomsWithTheCdDoorWalledUp() {
  std::string text = roomsWorldText();
  const std::string door = R"(    doors:
      - offset_m: 3.0        # C <-> D at x = 15
        width_m: 1.2
        height_m: 2.2
)";
  const size_t at = text.find(door);
  if (at == std::string::npos) return std::nullopt;
  text.erase(at, door.size());
  return text;
}

}  // namespace support
