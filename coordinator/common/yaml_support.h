#pragma once

// Reading the coordinator's YAML files (catalog, missions) with messages
// that name the file and line: "<file>:<line>: <what>: <problem>".
// Internal to coordinator/.

#include <google/protobuf/struct.pb.h>
#include <yaml-cpp/yaml.h>

#include <cmath>
#include <set>
#include <sstream>
#include <string>
#include <vector>

#include "absl/status/status.h"
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
  return server::loadYaml(text, file, out);
}

class Reader {
 public:
  explicit Reader(std::string file) : file_(std::move(file)) {}
  const std::string& file() const { return file_; }

  absl::Status error(const YAML::Node& node, const std::string& what) const {
    return absl::InvalidArgumentError(cat(file_, ":", lineOf(node), ": ", what));
  }

  /// A mapping whose keys are all in `allowed` (any key when empty), with no
  /// duplicate.
  absl::Status mapping(const YAML::Node& node, const std::string& what,
                       const std::vector<std::string>& allowed) const {
    if (!node.IsMap()) return error(node, what + ": expected a mapping");
    std::set<std::string> seen;
    for (const auto& entry : node) {
      if (!entry.first.IsScalar()) return error(entry.first, what + ": a key must be a plain name");
      const std::string key = entry.first.Scalar();
      if (!seen.insert(key).second)
        return error(entry.first, what + ": duplicate key '" + key + "'");
      bool known = allowed.empty();
      for (const auto& a : allowed) known = known || a == key;
      if (!known) {
        return error(entry.first,
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
  std::string file_;
};

}  // namespace behaviorlib::coordinator::yaml
