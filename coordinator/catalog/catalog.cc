#include "coordinator/catalog/catalog.h"

#include <yaml-cpp/yaml.h>

#include <cmath>
#include <fstream>
#include <functional>
#include <set>
#include <sstream>

#include "coordinator/common/parameter_types.h"
#include "coordinator/common/yaml_support.h"

namespace behaviorlib::coordinator {
namespace {

using yaml::cat;
using yaml::join;
using yaml::lineOf;

// The JSON type a ParameterSchema accepts, checked against a default value.
bool typeMatches(const v1::ParameterSchema& schema, const google::protobuf::Value& value) {
  if (schema.repeated()) {
    if (!value.has_list_value()) return false;
    v1::ParameterSchema element = schema;
    element.set_repeated(false);
    for (const auto& item : value.list_value().values()) {
      if (!typeMatches(element, item)) return false;
    }
    return true;
  }
  return valueHasType(schema, value);
}

}  // namespace

absl::StatusOr<Catalog> Catalog::load(const std::string& path) {
  std::ifstream in(path);
  if (!in) return absl::InvalidArgumentError(cat(path, ": cannot read the catalog file"));
  std::stringstream text;
  text << in.rdbuf();
  return parse(text.str(), path);
}

absl::StatusOr<Catalog> Catalog::parse(const std::string& yaml, const std::string& file_name) {
  YAML::Node root;
  if (auto s = yaml::load(yaml, file_name, &root); !s.ok()) return s;
  absl::StatusOr<Catalog> catalog = absl::InternalError("not parsed");
  const absl::Status guarded = server_kit::guardYamlParse(file_name, [&] {
    catalog = parseTree(root, file_name);
    return absl::OkStatus();
  });
  if (!guarded.ok()) return guarded;
  return catalog;
}

absl::StatusOr<Catalog> Catalog::parseTree(const YAML::Node& root, const std::string& file_name) {
  yaml::Reader p(file_name);
  if (root.IsNull()) return absl::InvalidArgumentError(file_name + ":1: the catalog is empty");
  if (auto s = p.mapping(root, "catalog", {"capabilities", "resources", "behaviors"}); !s.ok()) {
    return s;
  }
  Catalog catalog;
  catalog.file_name_ = file_name;
  if (const YAML::Node caps = root["capabilities"]) {
    if (auto s = p.mapping(caps, "capabilities", {}); !s.ok()) return s;
    for (const auto& entry : caps) {
      Capability c;
      c.name = entry.first.as<std::string>();
      c.line = lineOf(entry.first);
      const std::string what = "capability '" + c.name + "'";
      if (!entry.second.IsNull()) {
        if (auto s = p.mapping(entry.second, what, {"description", "default"}); !s.ok()) return s;
        if (entry.second["description"])
          c.description = entry.second["description"].as<std::string>();
        if (entry.second["default"]) c.default_provider = entry.second["default"].as<std::string>();
      }
      catalog.capabilities_[c.name] = c;
    }
  }
  if (const YAML::Node resources = root["resources"]) {
    if (auto s = p.mapping(resources, "resources", {}); !s.ok()) return s;
    for (const auto& entry : resources) {
      catalog.resources_[entry.first.as<std::string>()] =
          entry.second.IsScalar() ? entry.second.as<std::string>() : "";
    }
  }
  const YAML::Node behaviors = root["behaviors"];
  if (!behaviors) return p.error(root, "catalog: missing 'behaviors'");
  if (auto s = p.mapping(behaviors, "behaviors", {}); !s.ok()) return s;
  for (const auto& entry : behaviors) {
    CatalogBehavior b;
    b.name = entry.first.as<std::string>();
    b.line = lineOf(entry.first);
    const std::string what = "behavior '" + b.name + "'";
    if (!entry.second.IsNull()) {
      const YAML::Node& body = entry.second;
      if (auto s = p.mapping(
              body, what, {"description", "provides", "requires", "holds", "defaults", "writes"});
          !s.ok()) {
        return s;
      }
      if (body["description"]) b.description = body["description"].as<std::string>();
      for (auto [key, out] : {std::pair{"provides", &b.provides},
                              std::pair{"requires", &b.requires_}, std::pair{"holds", &b.holds}}) {
        if (!body[key]) continue;
        if (auto s = p.names(body[key], what + " " + key, out); !s.ok()) return s;
        for (const auto& name : *out) {
          const bool is_resource = std::string(key) == "holds";
          const bool declared = is_resource ? catalog.resources_.count(name) > 0
                                            : catalog.capabilities_.count(name) > 0;
          if (!declared) {
            return p.error(body[key],
                           cat(what, ": ", key, " '", name, "', which is not a declared ",
                               is_resource ? "resource" : "capability"));
          }
        }
      }
      if (const YAML::Node writes = body["writes"]) {
        if (auto s = p.names(writes, what + " writes", &b.writes); !s.ok()) return s;
        for (const auto& pattern : b.writes) {
          if (auto problem = beliefPatternProblem(pattern)) {
            return p.error(writes, cat(what, " writes '", pattern, "': ", *problem));
          }
        }
      }
      if (const YAML::Node defaults = body["defaults"]) {
        if (!defaults.IsMap()) return p.error(defaults, what + " defaults: expected a mapping");
        google::protobuf::Value value;
        if (auto s = p.value(defaults, what + " defaults", &value); !s.ok()) return s;
        b.defaults = value.struct_value();
      }
    }
    catalog.behaviors_[b.name] = std::move(b);
  }
  if (auto s = catalog.validate(); !s.ok()) return s;
  return catalog;
}

std::optional<std::string> beliefPatternProblem(const std::string& pattern) {
  if (pattern.empty()) return "empty";
  for (size_t at = pattern.find('{'); at != std::string::npos; at = pattern.find('{', at + 1)) {
    const size_t end = pattern.find('}', at);
    if (end == std::string::npos) return "a '{' without its '}'";
    const std::string inside = pattern.substr(at + 1, end - at - 1);
    if (inside != "robot" && (inside.rfind("parameter:", 0) != 0 || inside.size() == 10)) {
      return "'{" + inside + "}' is neither {robot} nor {parameter:NAME}";
    }
  }
  const size_t star = pattern.find('*');
  if (star != std::string::npos && star != pattern.size() - 1) return "'*' only at the end";
  return std::nullopt;
}

std::optional<std::string> instantiateBeliefPattern(const std::string& pattern,
                                                    const std::string& robot,
                                                    const google::protobuf::Struct& parameters) {
  std::string out;
  size_t i = 0;
  while (i < pattern.size()) {
    if (pattern[i] != '{') {
      out += pattern[i++];
      continue;
    }
    const size_t end = pattern.find('}', i);
    if (end == std::string::npos) return std::nullopt;
    const std::string inside = pattern.substr(i + 1, end - i - 1);
    if (inside == "robot") {
      out += robot;
    } else {
      const auto it = parameters.fields().find(inside.substr(10));
      if (it == parameters.fields().end() || !it->second.has_string_value() ||
          it->second.string_value().empty() ||
          it->second.string_value().find("${") != std::string::npos) {
        return std::nullopt;  // not given, or known only when the step starts
      }
      out += it->second.string_value();
    }
    i = end + 1;
  }
  return out;
}

std::string Catalog::where(int line) const { return cat(file_name_, ":", line, ": "); }

absl::Status Catalog::validate() const {
  for (const auto& [name, c] : capabilities_) {
    if (c.default_provider.empty()) continue;
    const CatalogBehavior* provider = find(c.default_provider);
    if (provider == nullptr) {
      return absl::InvalidArgumentError(cat(where(c.line), "capability '", name, "': default '",
                                            c.default_provider, "' is not a listed behavior"));
    }
    bool provides = false;
    for (const auto& p : provider->provides) provides = provides || p == name;
    if (!provides) {
      return absl::InvalidArgumentError(cat(where(c.line), "capability '", name, "': default '",
                                            c.default_provider, "' does not provide it"));
    }
  }
  // Requirements followed through default providers must not loop.
  std::map<std::string, int> mark;  // 1 visiting, 2 done
  std::function<absl::Status(const CatalogBehavior&, std::vector<std::string>&)> visit =
      [&](const CatalogBehavior& b, std::vector<std::string>& chain) -> absl::Status {
    if (mark[b.name] == 2) return absl::OkStatus();
    if (mark[b.name] == 1) {
      chain.push_back(b.name);
      std::string path;
      for (const auto& n : chain) path += (path.empty() ? "" : " -> ") + n;
      return absl::InvalidArgumentError(
          cat(where(b.line), "behavior '", b.name, "': requirements loop: ", path));
    }
    mark[b.name] = 1;
    chain.push_back(b.name);
    for (const auto& cap : b.requires_) {
      bool self = false;
      for (const auto& p : b.provides) self = self || p == cap;
      const Capability* c = capability(cap);
      if (self || c == nullptr || c->default_provider.empty()) continue;
      if (auto s = visit(*find(c->default_provider), chain); !s.ok()) return s;
    }
    chain.pop_back();
    mark[b.name] = 2;
    return absl::OkStatus();
  };
  for (const auto& [name, b] : behaviors_) {
    std::vector<std::string> chain;
    if (auto s = visit(b, chain); !s.ok()) return s;
  }
  return absl::OkStatus();
}

const CatalogBehavior* Catalog::find(const std::string& behavior) const {
  auto it = behaviors_.find(behavior);
  return it == behaviors_.end() ? nullptr : &it->second;
}

const Capability* Catalog::capability(const std::string& name) const {
  auto it = capabilities_.find(name);
  return it == capabilities_.end() ? nullptr : &it->second;
}

absl::Status Catalog::checkRegistration(const v1::BehaviorDescription& registered,
                                        const std::string& system) const {
  const CatalogBehavior* entry = find(registered.name());
  if (entry == nullptr) return absl::OkStatus();
  for (const auto& [key, value] : entry->defaults.fields()) {
    const v1::ParameterSchema* schema = nullptr;
    std::vector<std::string> known;
    for (const auto& p : registered.parameters()) {
      known.push_back(p.name());
      if (p.name() == key) schema = &p;
    }
    if (schema == nullptr) {
      return absl::InvalidArgumentError(
          cat(where(entry->line), "behavior '", entry->name, "': default parameter '", key,
              "' is not a parameter of ", entry->name, " as registered by ", system,
              " (its parameters: ", known.empty() ? "none" : join(known), ")"));
    }
    if (!typeMatches(*schema, value)) {
      return absl::InvalidArgumentError(cat(where(entry->line), "behavior '", entry->name,
                                            "': default parameter '", key, "' must be of type ",
                                            schema->repeated() ? "list of " : "", schema->type(),
                                            " as registered by ", system));
    }
  }
  return absl::OkStatus();
}

}  // namespace behaviorlib::coordinator
