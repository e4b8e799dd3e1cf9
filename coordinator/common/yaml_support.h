#pragma once

// Reading the coordinator's YAML files (catalog, missions) with messages
// that name the file and line: "<file>:<line>: <what>: <problem>".
// Internal to coordinator/.

#include <google/protobuf/struct.pb.h>
#include <yaml-cpp/yaml.h>

#include <cmath>
#include <map>
#include <set>
#include <sstream>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "behaviorlib/error_details.h"
#include "behaviorlib/server_kit/yaml_guard.h"

namespace behaviorlib::coordinator::yaml {

template <typename... Args>
std::string cat(const Args&... args) {
  std::ostringstream out;
  (out << ... << args);
  return out.str();
}

inline int lineOf(const YAML::Node& node) {
  const YAML::Mark mark = node.Mark();
  return mark.is_null() ? 1 : mark.line + 1;
}

inline std::string join(const std::vector<std::string>& items) {
  std::string out;
  for (const auto& item : items) out += (out.empty() ? "" : ", ") + item;
  return out;
}

/// Parses YAML text within the server kit's limits (bytes, nodes with
/// aliases expanded, aliases, depth): "<file>:<line>: not valid YAML" or
/// "<file>:<line>: refused: ...".
inline absl::Status load(const std::string& text, const std::string& file, YAML::Node* out) {
  return server_kit::loadYaml(text, file, out);
}

class Reader {
 public:
  explicit Reader(std::string file) : file_(std::move(file)) {}
  const std::string& file() const { return file_; }

  /// INVALID_ARGUMENT "<file>:<line>: <what>", with a BadRequest field
  /// violation naming the node's path in the document (after index()).
  absl::Status error(const YAML::Node& node, const std::string& what) const {
    return violation(node, pathOf(node), what);
  }

  /// The same for a mapping's key (`entry.first`): a key and the mapping it
  /// opens start at the same place in the text, so keys have their own index.
  absl::Status keyError(const YAML::Node& key, const std::string& what) const {
    return violation(key, pathOf(key, keys_), what);
  }

  /// Records the path ("steps[2].parameters.altitude_m") of every node under
  /// `root`, by its position in the text: YAML nodes do not know their
  /// parents. One pass, bounded by the YAML guard's node limit.
  void index(const YAML::Node& root) { indexNode(root, ""); }

  /// The path of `node` in the indexed document ("" for the root, or when
  /// not indexed).
  std::string pathOf(const YAML::Node& node) const { return pathOf(node, paths_); }

  /// A mapping whose keys are all in `allowed` (any key when empty), with no
  /// duplicate.
  absl::Status mapping(const YAML::Node& node, const std::string& what,
                       const std::vector<std::string>& allowed) const {
    if (!node.IsMap()) return error(node, what + ": expected a mapping");
    std::set<std::string> seen;
    for (const auto& entry : node) {
      if (!entry.first.IsScalar()) {
        return keyError(entry.first, what + ": a key must be a plain name");
      }
      const std::string key = entry.first.Scalar();
      if (!seen.insert(key).second)
        return keyError(entry.first, what + ": duplicate key '" + key + "'");
      bool known = allowed.empty();
      for (const auto& a : allowed) known = known || a == key;
      if (!known) {
        return keyError(entry.first,
                        cat(what, ": unknown key '", key, "' (expected ", join(allowed), ")"));
      }
    }
    return absl::OkStatus();
  }

  /// One name or a list of names.
  absl::Status names(const YAML::Node& node, const std::string& what,
                     std::vector<std::string>* out) const {
    if (node.IsScalar()) {
      out->push_back(node.as<std::string>());
      return absl::OkStatus();
    }
    if (!node.IsSequence()) return error(node, what + ": expected a list of names");
    for (const auto& item : node) {
      if (!item.IsScalar()) return error(item, what + ": expected a name");
      out->push_back(item.as<std::string>());
    }
    return absl::OkStatus();
  }

  /// A scalar as text.
  absl::Status text(const YAML::Node& node, const std::string& what, std::string* out) const {
    if (!node.IsScalar()) return error(node, what + ": expected a text value");
    *out = node.Scalar();
    return absl::OkStatus();
  }

  /// Any YAML value as a JSON-like Value: quoted scalars stay strings,
  /// true/false are booleans, finite numbers are numbers.
  absl::Status value(const YAML::Node& node, const std::string& what,
                     google::protobuf::Value* out) const {
    if (node.IsNull()) {
      out->set_null_value(google::protobuf::NULL_VALUE);
    } else if (node.IsScalar()) {
      bool b = false;
      double d = 0;
      if (node.Tag() == "!") {
        out->set_string_value(node.Scalar());
      } else if (YAML::convert<bool>::decode(node, b)) {
        out->set_bool_value(b);
      } else if (YAML::convert<double>::decode(node, d) && std::isfinite(d)) {
        out->set_number_value(d);
      } else {
        out->set_string_value(node.Scalar());
      }
    } else if (node.IsSequence()) {
      auto* list = out->mutable_list_value();
      for (const auto& item : node) {
        if (auto s = value(item, what, list->add_values()); !s.ok()) return s;
      }
    } else if (node.IsMap()) {
      auto* fields = out->mutable_struct_value()->mutable_fields();
      for (const auto& entry : node) {
        if (auto s = value(entry.second, what, &(*fields)[entry.first.as<std::string>()]);
            !s.ok()) {
          return s;
        }
      }
    } else {
      return error(node, what + ": unsupported value");
    }
    return absl::OkStatus();
  }

 private:
  using Paths = std::map<std::pair<int, int>, std::string>;

  absl::Status violation(const YAML::Node& node, const std::string& path,
                         const std::string& what) const {
    const std::string message = cat(file_, ":", lineOf(node), ": ", what);
    return errors::withFieldViolation(absl::InvalidArgumentError(message), path, message);
  }

  static std::string pathOf(const YAML::Node& node, const Paths& paths) {
    const YAML::Mark mark = node.Mark();
    if (mark.is_null()) return "";
    auto it = paths.find({mark.line, mark.column});
    return it == paths.end() ? "" : it->second;
  }

  void indexNode(const YAML::Node& node, const std::string& path) {
    const YAML::Mark mark = node.Mark();
    if (!mark.is_null() && !paths_.emplace(std::pair{mark.line, mark.column}, path).second) {
      return;  // an alias of a node already indexed
    }
    if (node.IsSequence()) {
      for (size_t i = 0; i < node.size(); ++i) indexNode(node[i], cat(path, "[", i, "]"));
    } else if (node.IsMap()) {
      for (const auto& entry : node) {
        const std::string key = entry.first.IsScalar() ? entry.first.Scalar() : "?";
        const std::string child = path.empty() ? key : cat(path, ".", key);
        const YAML::Mark key_mark = entry.first.Mark();
        if (!key_mark.is_null()) keys_.emplace(std::pair{key_mark.line, key_mark.column}, child);
        indexNode(entry.second, child);
      }
    }
  }

  std::string file_;
  Paths paths_;  // nodes (values, mappings, sequences) by position
  Paths keys_;   // mapping keys by position
};

}  // namespace behaviorlib::coordinator::yaml
