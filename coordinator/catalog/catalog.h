#pragma once

// The behavior catalog: what each behavior provides and requires, and which
// resources it holds exclusively — capabilities and resources, never
// addresses (which system hosts a behavior, and its parameter schema, come
// from the systems' registration). Read from a YAML file:
//
//   capabilities:
//     self_localization:
//       description: a pose estimate on robots/{id}/self_localization/pose
//       default: SELF_LOCALIZE_WITH_GROUND_TRUTH   # activated when missing
//   resources:
//     platform_commands: commands the vehicle through the FlightController lease
//   behaviors:
//     QUADROTOR_PID_MOTION_CONTROL:
//       provides: [motion_control]
//       requires: [self_localization]
//       holds: [platform_commands]
//     FOLLOW_PATH:
//       requires: [self_localization, motion_control]
//       holds: [motion_reference]
//       defaults: {speed_m_s: 1.0}   # when a plan activates it as a requirement
//     GENERATE_PATH_WITH_OCCUPANCY_GRID:
//       writes: ["{parameter:belief_key}", "{robot}/path"]   # beliefs it may write
//
// Every problem is reported as "<file>:<line>: <what>: <problem>"
// (INVALID_ARGUMENT): unknown keys, undeclared capabilities or resources, a
// default provider that does not provide its capability, requirement cycles
// through default providers. A behavior the catalog does not list has no
// rules (it requires and holds nothing).

#include <google/protobuf/struct.pb.h>

#include <map>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "behaviorlib/v1/behavior.pb.h"

namespace YAML {
class Node;
}

namespace behaviorlib::coordinator {

/// One behavior's rules.
struct CatalogBehavior {
  std::string name;
  std::string description;
  std::vector<std::string> provides;   ///< capabilities
  std::vector<std::string> requires_;  ///< capabilities
  std::vector<std::string> holds;      ///< exclusive resources
  google::protobuf::Struct defaults;   ///< parameters when a plan activates it as a requirement
  /// The belief keys it may write: patterns with {robot}, {parameter:NAME}
  /// (the step's literal string parameter) and a trailing '*' (any rest).
  std::vector<std::string> writes;
  int line = 0;  ///< of the entry, for messages
};

/// What is wrong with a `writes` pattern, or nullopt.
std::optional<std::string> beliefPatternProblem(const std::string& pattern);
/// `pattern` for a step on `robot` with `parameters`; nullopt when it names
/// a parameter the step does not give as a literal string.
std::optional<std::string> instantiateBeliefPattern(const std::string& pattern,
                                                    const std::string& robot,
                                                    const google::protobuf::Struct& parameters);

/// A capability some behaviors provide and others require.
struct Capability {
  std::string name;
  std::string description;
  std::string default_provider;  ///< empty: never activated automatically
  int line = 0;
};

class Catalog {
 public:
  Catalog() = default;

  /// Reads and checks a catalog file.
  static absl::StatusOr<Catalog> load(const std::string& path);
  /// Parses catalog text; `file_name` is used in messages.
  static absl::StatusOr<Catalog> parse(const std::string& yaml, const std::string& file_name);

  const std::string& fileName() const { return file_name_; }
  /// The entry of `behavior`, or nullptr when the catalog does not list it.
  const CatalogBehavior* find(const std::string& behavior) const;
  const Capability* capability(const std::string& name) const;
  const std::map<std::string, CatalogBehavior>& behaviors() const { return behaviors_; }
  const std::map<std::string, Capability>& capabilities() const { return capabilities_; }
  const std::map<std::string, std::string>& resources() const { return resources_; }

  /// Checks the entry of `registered.name()` against what a system
  /// registered: every default parameter must be one of its parameters, with
  /// a value of the right JSON type. INVALID_ARGUMENT naming the catalog
  /// file, the line and the parameter; OK for a behavior not listed.
  absl::Status checkRegistration(const v1::BehaviorDescription& registered,
                                 const std::string& system) const;

 private:
  static absl::StatusOr<Catalog> parseTree(const YAML::Node& root, const std::string& file_name);
  absl::Status validate() const;
  std::string where(int line) const;

  std::string file_name_;
  std::map<std::string, CatalogBehavior> behaviors_;
  std::map<std::string, Capability> capabilities_;
  std::map<std::string, std::string> resources_;  // name -> description
};

}  // namespace behaviorlib::coordinator
