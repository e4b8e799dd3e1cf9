#pragma once

// Reading YAML from outside (missions, catalogs, worlds, sensor and system
// configurations) within limits.
//
// yaml-cpp shares an anchored node between its aliases, so a 520-byte text of
// nested anchors loads instantly; it is whoever walks the tree afterwards
// (converting it to a protobuf Struct, say) that meets 10^9 nodes. loadYaml
// therefore parses the text twice: first as a stream of events, counting the
// nodes the document has once every alias is expanded, its depth and its
// aliases, and stopping at the first limit passed; then, if it is within
// every limit, into a YAML::Node. Both passes are linear in the text.
//
//   YAML::Node root;
//   if (absl::Status s = loadYaml(text, "mission.yaml", &root); !s.ok()) return s;
//
// Errors are INVALID_ARGUMENT, "<file>:<line>: ...".

#include <yaml-cpp/yaml.h>

#include <cstddef>
#include <functional>
#include <string>
#include <string_view>

#include "absl/status/status.h"

namespace behaviorlib::server_kit {

struct YamlLimits {
  size_t max_bytes = 1 << 20;  ///< the text
  size_t max_nodes = 100'000;  ///< scalars, sequences and mappings, aliases expanded
  size_t max_aliases = 1'000;  ///< alias references in the text
  size_t max_depth = 64;       ///< nesting of sequences and mappings, aliases expanded
};

/// Parses one YAML document within `limits`; `file` names the text in errors.
absl::Status loadYaml(std::string_view text, const std::string& file, YAML::Node* out,
                      const YamlLimits& limits = {});

/// Runs `parse` (which walks YAML nodes) and turns any exception it throws
/// into INVALID_ARGUMENT: a YAML::Exception with "<file>:<line>: ...", any
/// other with "<file>: ...". A parser of outside input must not let one
/// escape: nothing above it catches.
absl::Status guardYamlParse(const std::string& file, const std::function<absl::Status()>& parse);

}  // namespace behaviorlib::server_kit
