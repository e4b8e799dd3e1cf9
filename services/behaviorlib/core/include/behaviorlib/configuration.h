#pragma once

// Typed configuration (decision 45): a YAML section of a --config file decoded
// into proto messages that declare its keys once, with the same field rules
// as parameters ((behaviorlib.v1.param): range, default_json, description).
// An unknown key, a value of the wrong type or out of range is an error that
// names the file, line and column:
//
//   systems.yaml:14:5: behaviors.TAKE_OFF: key 'altitude_tolerance_m' = -1 is
//   out of range [0, 10]
//
// A message field marked (behaviorlib.v1.flatten) spreads its message's keys
// into the section of the message that holds it, so that settings shared by
// several behaviors (the flight keys) are declared once.
//
//   config::v1::ExecutionConfig execution;
//   config::v1::TakeOffConfig own;
//   absl::Status s = config::decode(section, {"systems.yaml", "behaviors.TAKE_OFF"},
//                                   {&execution, &own});

#include <google/protobuf/descriptor.h>
#include <google/protobuf/message.h>
#include <yaml-cpp/yaml.h>

#include <initializer_list>
#include <string>
#include <vector>

#include "absl/status/status.h"

namespace behaviorlib::config {

/// Where a section comes from, for messages: its file ("" when the YAML did
/// not come from a file) and its path in the file ("behaviors.TAKE_OFF").
struct Source {
  std::string file;
  std::string section;
  /// Keys of the section that something else reads (the library's
  /// `behaviors` at the top of a system's file): passed over.
  std::vector<std::string> skip = {};
};

/// Decodes the map `node` into `targets` (each cleared first): every key must
/// name a field of one of them, the first that has it, flattened fields
/// included. Then applies each target's defaults and checks its rules
/// (params::applyDefaultsAndValidate). A null or missing node decodes as an
/// empty section. INVALID_ARGUMENT "<file>:<line>:<column>: <section>: ..."
/// on the first problem (a key of the wrong type or out of range names the
/// key's line; a required key that is missing names the section's).
absl::Status decode(const YAML::Node& node, const Source& source,
                    std::initializer_list<google::protobuf::Message*> targets);

/// The keys that `targets` accept, flattened, one per line under `indent`:
/// name, type, unit, range, default and description, for --help.
std::string document(std::initializer_list<const google::protobuf::Descriptor*> targets,
                     const std::string& indent);

/// "file:line:column" of a node (line and column from 1), or the file alone
/// when the node has no position.
std::string position(const YAML::Node& node, const std::string& file);

}  // namespace behaviorlib::config
