#pragma once

// The coordinator's --systems file: behavior systems to contact at start (and
// again whenever they come back), for systems that do not register
// themselves.
//
//   # systems.yaml
//   systems:
//     - robot_id: drone1
//       address: 127.0.0.1:50061
//     - robot_id: drone2
//       address: 127.0.0.1:50062
//
// Errors name the file and line: "systems.yaml:4: address: expected host:port".

#include <string>
#include <vector>

#include "absl/status/statusor.h"

namespace behaviorlib::coordinator {

struct ConfiguredSystem {
  /// Robot the system must serve (checked against its ListBehaviors).
  std::string robot_id;
  /// Where it serves BehaviorSystem, "host:port".
  std::string address;
  /// Line of the entry in the file (1-based).
  int line = 0;
};

/// Parses the YAML text; `name` is used in messages (usually the path).
absl::StatusOr<std::vector<ConfiguredSystem>> parseSystemsConfig(const std::string& text,
                                                                 const std::string& name);
/// Reads and parses the file at `path`.
absl::StatusOr<std::vector<ConfiguredSystem>> loadSystemsConfig(const std::string& path);

/// Whether `address` looks like "host:port" with a port in 1..65535.
bool isHostPort(const std::string& address);

}  // namespace behaviorlib::coordinator
