#include "coordinator/registry/systems_config.h"

#include <yaml-cpp/yaml.h>

#include <cctype>
#include <fstream>
#include <set>
#include <sstream>

#include "absl/status/status.h"
#include "behaviorlib/server_kit/yaml_guard.h"

namespace behaviorlib::coordinator {

namespace {

absl::Status errorAt(const std::string& name, const YAML::Mark& mark, const std::string& what) {
  // yaml-cpp lines are 0-based; a null mark (-1) has no position.
  const std::string where = mark.line >= 0 ? name + ":" + std::to_string(mark.line + 1) : name;
  return absl::InvalidArgumentError(where + ": " + what);
}

}  // namespace

bool isHostPort(const std::string& address) {
  const auto colon = address.rfind(':');
  if (colon == std::string::npos || colon == 0 || colon + 1 >= address.size()) return false;
  const std::string port = address.substr(colon + 1);
  if (port.size() > 5) return false;
  for (char c : port) {
    if (!std::isdigit(static_cast<unsigned char>(c))) return false;
  }
  const int value = std::stoi(port);
  return value >= 1 && value <= 65535;
}

namespace {

absl::StatusOr<std::vector<ConfiguredSystem>> parseRoot(const YAML::Node& root,
                                                        const std::string& name) {
  std::vector<ConfiguredSystem> out;
  if (!root || root.IsNull()) return out;
  if (!root.IsMap()) return errorAt(name, root.Mark(), "expected a mapping with key 'systems'");
  for (const auto& entry : root) {
    const std::string key = entry.first.as<std::string>();
    if (key != "systems") {
      return errorAt(name, entry.first.Mark(), "unknown key '" + key + "' (expected 'systems')");
    }
  }
  const YAML::Node systems = root["systems"];
  if (!systems || systems.IsNull()) return out;
  if (!systems.IsSequence()) {
    return errorAt(name, systems.Mark(), "'systems' must be a list of {robot_id, address} entries");
  }
  std::set<std::string> addresses;
  for (const auto& item : systems) {
    if (!item.IsMap()) {
      return errorAt(name, item.Mark(), "each system must be a mapping {robot_id, address}");
    }
    ConfiguredSystem system;
    system.line = item.Mark().line + 1;
    for (const auto& field : item) {
      const std::string key = field.first.as<std::string>();
      if (!field.second.IsScalar()) {
        return errorAt(name, field.second.Mark(), key + ": expected a string");
      }
      if (key == "robot_id") {
        system.robot_id = field.second.as<std::string>();
      } else if (key == "address") {
        system.address = field.second.as<std::string>();
      } else {
        return errorAt(name, field.first.Mark(),
                       "unknown key '" + key + "' (expected robot_id, address)");
      }
    }
    if (system.robot_id.empty()) return errorAt(name, item.Mark(), "robot_id is missing");
    if (system.address.empty()) return errorAt(name, item.Mark(), "address is missing");
    if (!isHostPort(system.address)) {
      return errorAt(name, item["address"].Mark(),
                     "address '" + system.address + "': expected host:port");
    }
    if (!addresses.insert(system.address).second) {
      return errorAt(name, item.Mark(), "address '" + system.address + "' is listed twice");
    }
    out.push_back(std::move(system));
  }
  return out;
}

}  // namespace

absl::StatusOr<std::vector<ConfiguredSystem>> parseSystemsConfig(const std::string& text,
                                                                 const std::string& name) {
  YAML::Node root;
  if (absl::Status s = server_kit::loadYaml(text, name, &root); !s.ok()) return s;
  absl::StatusOr<std::vector<ConfiguredSystem>> systems = absl::InternalError("not parsed");
  const absl::Status guarded = server_kit::guardYamlParse(name, [&] {
    systems = parseRoot(root, name);
    return absl::OkStatus();
  });
  if (!guarded.ok()) return guarded;
  return systems;
}

absl::StatusOr<std::vector<ConfiguredSystem>> loadSystemsConfig(const std::string& path) {
  std::ifstream in(path);
  if (!in) return absl::NotFoundError("cannot read " + path);
  std::stringstream text;
  text << in.rdbuf();
  return parseSystemsConfig(text.str(), path);
}

}  // namespace behaviorlib::coordinator
