#include "coordinator/mission/mission_file.h"

#include <cmath>
#include <fstream>
#include <sstream>

#include "absl/strings/str_join.h"
#include "behaviorlib/parameters.h"
#include "coordinator/belief/belief_store.h"
#include "coordinator/common/parameter_types.h"
#include "coordinator/common/yaml_support.h"

namespace behaviorlib::coordinator {
namespace {

using yaml::cat;
using yaml::lineOf;

const std::vector<std::string>& causeKeys() {
  static const std::vector<std::string> keys = {
      "GOAL_ACHIEVED",   "TIME_OUT",    "WRONG_PROGRESS", "SITUATION_CHANGE",
      "PROCESS_FAILURE", "INTERRUPTED", "REFUSED",        "otherwise"};
  return keys;
}

// A mission refused for one field: MISSION_INVALID with the field's path.
absl::Status stepError(const std::string& field, const std::string& message) {
  return errors::withReason(
      errors::withFieldViolation(absl::InvalidArgumentError(message), field, message),
      v1::MISSION_INVALID);
}

bool hasBinding(const google::protobuf::Value& value);

// A sub-mission's declared parameter.
struct SubParameter {
  std::string name;
  std::string type;  // number, string, bool, list, object or any
  std::string description;
  std::optional<double> min;
  std::optional<double> max;
  std::optional<google::protobuf::Value> default_value;
};

// What is wrong with `value` for `parameter`, if anything (a value bound to
// a belief is known only when its step starts).
std::optional<std::string> argumentProblem(const SubParameter& parameter,
                                           const google::protobuf::Value& value) {
  if (hasBinding(value)) return std::nullopt;
  const std::string& type = parameter.type;
  const bool matches = type == "any" || (type == "number" && value.has_number_value()) ||
                       (type == "string" && value.has_string_value()) ||
                       (type == "bool" && value.has_bool_value()) ||
                       (type == "list" && value.has_list_value()) ||
                       (type == "object" && value.has_struct_value());
  if (!matches) return cat("expected a ", type);
  if (value.has_number_value()) {
    const double v = value.number_value();
    if ((parameter.min && v < *parameter.min) || (parameter.max && v > *parameter.max)) {
      v1::Range range;
      if (parameter.min) range.set_min(*parameter.min);
      if (parameter.max) range.set_max(*parameter.max);
      return cat(params::numberText(v), " is out of range ", params::rangeText(range));
    }
  }
  return std::nullopt;
}

class MissionParser {
 public:
  MissionParser(const std::string& file, ImportReader imports)
      : main_(file), r_(&main_), imports_(std::move(imports)) {}

  absl::StatusOr<MissionSpec> parse(const YAML::Node& root) {
    MissionSpec spec;
    spec.file = r_->file();
    r_->index(root);
    if (root.IsNull()) return absl::InvalidArgumentError(r_->file() + ":1: the mission is empty");
    if (auto s = r_->mapping(root, "mission",
                             {"name", "description", "robot", "geofence", "import", "submissions",
                              "recurrent", "safety", "steps"});
        !s.ok()) {
      return s;
    }
    if (root["import"]) {
      if (auto s = importAll(root["import"], &spec); !s.ok()) return s;
    }
    if (root["submissions"]) {
      if (auto s = definitions(root["submissions"], r_); !s.ok()) return s;
    }
    for (const auto& [name, definition] : defs_) spec.submissions.push_back(name);
    if (root["name"]) {
      if (auto s = r_->text(root["name"], "mission name", &spec.name); !s.ok()) return s;
    }
    if (root["description"]) {
      if (auto s = r_->text(root["description"], "mission description", &spec.description);
          !s.ok()) {
        return s;
      }
    }
    if (root["robot"]) {
      if (auto s = r_->text(root["robot"], "mission robot", &spec.robot_id); !s.ok()) return s;
      spec.robot_line = lineOf(root["robot"]);
    }
    if (root["geofence"]) {
      if (auto s = geofence(root["geofence"], &spec); !s.ok()) return s;
    }
    if (!root["steps"]) return r_->error(root, "mission: missing 'steps'");
    if (auto s = stepList(root["steps"], "steps", &spec.steps); !s.ok()) return s;
    // Every wait_for names a step of the mission (in any branch or call).
    for (const auto& [name, node] : waits_) {
      if (!names_.contains(name)) {
        return r_->error(
            node,
            cat("wait_for step '", name, "': no step of the mission has that name",
                names_.empty() ? ""
                               : " (named: " + yaml::join({names_.begin(), names_.end()}) + ")"));
      }
    }
    if (spec.steps.empty()) return r_->error(root["steps"], "mission: 'steps' is empty");
    for (auto [key, out] :
         {std::pair{"recurrent", &spec.recurrent}, std::pair{"safety", &spec.safety}}) {
      if (!root[key]) continue;
      if (auto s = stepList(root[key], key, out); !s.ok()) return s;
      for (const auto& step : *out) {
        if (step.parallel || step.wait) {
          return stepError(step.path, cat(r_->file(), ":", step.line, ": ", key,
                                          " step: 'parallel' and 'wait_for' are for steps only"));
        }
        if (step.behavior.empty()) {
          return stepError(step.path + ".behavior",
                           cat(r_->file(), ":", step.line, ": ", key, " step: missing 'behavior'"));
        }
        if (!step.on.empty() || step.condition || !step.when.empty()) {
          return stepError(step.path + (!step.on.empty() ? ".on"
                                        : step.condition ? ".if"
                                                         : ".when"),
                           cat(r_->file(), ":", step.line, ": ", key,
                               " step: 'on', 'if' and 'when' are for steps only"));
        }
      }
    }
    spec.robots = robots_;
    return spec;
  }

 private:
  struct Definition;
  // geofence: {min_m: [x, y, z], max_m: [x, y, z]} (world ENU, metres).
  absl::Status geofence(const YAML::Node& node, MissionSpec* spec) {
    if (auto s = r_->mapping(node, "geofence", {"min_m", "max_m"}); !s.ok()) return s;
    Geofence fence;
    for (auto [key, out] : {std::pair{"min_m", &fence.min_m}, std::pair{"max_m", &fence.max_m}}) {
      const YAML::Node corner = node[key];
      if (!corner)
        return r_->error(node, cat("geofence: missing '", key, "' ([x, y, z] in metres)"));
      if (!corner.IsSequence() || corner.size() != 3) {
        return r_->error(corner, cat("geofence ", key, ": expected [x, y, z] in metres"));
      }
      for (size_t i = 0; i < 3; ++i) {
        try {
          (*out)[i] = corner[i].as<double>();
        } catch (const YAML::Exception&) {
          return r_->error(corner[i],
                           cat("geofence ", key, ": '", corner[i].Scalar(), "' is not a number"));
        }
        if (!std::isfinite((*out)[i])) {
          return r_->error(corner[i], cat("geofence ", key, ": coordinates must be finite"));
        }
      }
    }
    for (size_t i = 0; i < 3; ++i) {
      if (!(fence.min_m[i] < fence.max_m[i])) {
        return r_->error(node, "geofence: min_m must be below max_m on every axis");
      }
    }
    fence.line = node.Mark().line + 1;
    spec->geofence = fence;
    return absl::OkStatus();
  }

  absl::Status stepList(const YAML::Node& node, const std::string& what,
                        std::vector<MissionStep>* out) {
    if (!node.IsSequence()) return r_->error(node, what + ": expected a list of steps");
    for (const auto& item : node) {
      MissionStep step;
      if (auto s = parseStep(item, what, &step); !s.ok()) return s;
      out->push_back(std::move(step));
    }
    return absl::OkStatus();
  }

  absl::Status parseStep(const YAML::Node& node, const std::string& list, MissionStep* step) {
    step->line = lineOf(node);
    step->path = r_->pathOf(node);
    const std::string what = list + " step";
    step->file = r_->file();
    if (auto s =
            r_->mapping(node, what,
                        {"name", "robot", "behavior", "call", "with", "for_each", "repeat", "steps",
                         "parallel", "wait_for", "parameters", "on", "if", "when", "remember"});
        !s.ok()) {
      return s;
    }
    if (node["name"]) {
      if (auto s = r_->text(node["name"], what + " name", &step->name); !s.ok()) return s;
      names_.insert(step->name);
    }
    const std::string label = step->name.empty() ? what : what + " '" + step->name + "'";
    step->robot = robot_;
    if (node["robot"]) {
      if (auto s = robot(node["robot"], label, &step->robot); !s.ok()) return s;
    }
    // What the step contains runs on its robot.
    const std::string saved_robot = robot_;
    robot_ = step->robot;
    absl::Status contents = stepContents(node, label, step);
    robot_ = saved_robot;
    return contents;
  }

  // `robot: name` of a step or a branch.
  absl::Status robot(const YAML::Node& node, const std::string& label, std::string* out) {
    if (auto s = r_->text(node, label + " robot", out); !s.ok()) return s;
    if (out->empty() || out->size() > 128) {
      return r_->error(node, label + " robot: a robot id of 1 to 128 characters");
    }
    if (std::find(robots_.begin(), robots_.end(), *out) == robots_.end()) robots_.push_back(*out);
    return absl::OkStatus();
  }

  absl::Status stepContents(const YAML::Node& node, const std::string& label, MissionStep* step) {
    if (node["behavior"]) {
      if (auto s = r_->text(node["behavior"], label + " behavior", &step->behavior); !s.ok())
        return s;
    }
    if (const YAML::Node params = node["parameters"]) {
      if (!params.IsMap()) return r_->error(params, label + " parameters: expected a mapping");
      google::protobuf::Value value;
      if (auto s = r_->value(params, label + " parameters", &value); !s.ok()) return s;
      if (auto s = substitute(params, label + " parameters", &value); !s.ok()) return s;
      if (auto s = checkBindings(params, value, label); !s.ok()) return s;
      step->parameters = value.struct_value();
      for (const auto& entry : params) {
        step->parameter_lines[entry.first.as<std::string>()] = lineOf(entry.first);
      }
    }
    if (const YAML::Node remember = node["remember"]) {
      if (auto s = r_->mapping(remember, label + " remember", {}); !s.ok()) return s;
      for (const auto& entry : remember) {
        if (auto s = BeliefStore::checkKey(entry.first.as<std::string>()); !s.ok()) {
          return r_->keyError(entry.first, label + " remember: " + std::string(s.message()));
        }
      }
      google::protobuf::Value value;
      if (auto s = r_->value(remember, label + " remember", &value); !s.ok()) return s;
      if (auto s = substitute(remember, label + " remember", &value); !s.ok()) return s;
      if (auto s = checkBindings(remember, value, label); !s.ok()) return s;
      step->remember = value.struct_value();
    }
    if (node["call"]) {
      if (auto s = call(node, label, step); !s.ok()) return s;
    } else if (node["with"]) {
      return r_->error(node["with"], label + ": 'with' goes with 'call'");
    }
    if (node["for_each"] || node["repeat"]) {
      if (auto s = loop(node, label, step); !s.ok()) return s;
    } else if (node["steps"]) {
      return r_->error(node["steps"], label + ": 'steps' goes with 'for_each' or 'repeat'");
    }
    for (const char* key : {"parallel", "wait_for"}) {
      if (!node[key]) continue;
      for (const char* other : {"behavior", "call", "for_each", "repeat", "parameters", "remember",
                                key == std::string("parallel") ? "wait_for" : "parallel"}) {
        if (node[other]) {
          return r_->error(node[other], cat(label, ": '", key, "' goes with no '", other, "'"));
        }
      }
    }
    if (node["parallel"]) {
      if (auto s = parallel(node["parallel"], label, step); !s.ok()) return s;
    }
    if (node["wait_for"]) {
      if (auto s = waitFor(node["wait_for"], label, step); !s.ok()) return s;
    }
    const bool runs = !step->behavior.empty() || !step->call.empty() || step->loop ||
                      step->parallel || step->wait;
    if (!runs && step->remember.fields().empty()) {
      return r_->error(node, label +
                                 ": needs a 'behavior', a 'call', a loop, 'parallel' or "
                                 "'wait_for' (or only 'remember')");
    }
    if (const YAML::Node when = node["when"]) {
      if (step->behavior.empty()) {
        return r_->error(when,
                         label + ": 'when' goes with a 'behavior' (it is checked while it runs)");
      }
      if (!when.IsSequence() || when.size() == 0 || when.size() > kMaxVehicleConditions) {
        return r_->error(when, cat(label, " when: a list of 1 to ", kMaxVehicleConditions,
                                   " conditions on the vehicle"));
      }
      for (const auto& item : when) {
        VehicleCondition c;
        if (auto s = vehicleCondition(item, label + " when", &c); !s.ok()) return s;
        step->when.push_back(c);
      }
    }
    if (const YAML::Node condition = node["if"]) {
      BeliefCondition c;
      if (auto s = this->condition(condition, label + " if", &c); !s.ok()) return s;
      step->condition = c;
    }
    if (const YAML::Node on = node["on"]) {
      if (!runs) {
        return r_->error(on, label +
                                 ": 'on' needs a 'behavior', a 'call', a loop, 'parallel' or "
                                 "'wait_for'");
      }
      if (auto s = r_->mapping(on, label + " on", causeKeys()); !s.ok()) return s;
      for (const auto& entry : on) {
        MissionAction action;
        const std::string cause = entry.first.as<std::string>();
        if (auto s = parseAction(entry.second, label + " on " + cause, &action); !s.ok()) return s;
        step->on[cause] = std::move(action);
      }
    }
    return absl::OkStatus();
  }

  // {belief: key, exists: true|false} or {belief: key, equals: value}.
  absl::Status condition(const YAML::Node& condition, const std::string& what, BeliefCondition* out,
                         const std::vector<std::string>& more_keys = {}) {
    std::vector<std::string> keys = {"belief", "exists", "equals"};
    keys.insert(keys.end(), more_keys.begin(), more_keys.end());
    if (auto s = r_->mapping(condition, what, keys); !s.ok()) return s;
    BeliefCondition c;
    c.line = lineOf(condition);
    if (!condition["belief"]) return r_->error(condition, what + ": missing 'belief' (the key)");
    if (auto s = r_->text(condition["belief"], what + " belief", &c.key); !s.ok()) return s;
    if (auto s = BeliefStore::checkKey(c.key); !s.ok()) {
      return r_->error(condition["belief"], what + ": " + std::string(s.message()));
    }
    if (condition["exists"]) {
      bool exists = false;
      if (!condition["exists"].IsScalar() ||
          !YAML::convert<bool>::decode(condition["exists"], exists)) {
        return r_->error(condition["exists"], what + " exists: expected true or false");
      }
      c.exists = exists;
    }
    if (condition["equals"]) {
      google::protobuf::Value v;
      if (auto s = r_->value(condition["equals"], what + " equals", &v); !s.ok()) return s;
      c.equals = v;
    }
    if (c.exists.has_value() == c.equals.has_value()) {
      return r_->error(condition, what + ": give exactly one of 'exists' and 'equals'");
    }
    *out = std::move(c);
    return absl::OkStatus();
  }

  absl::Status parseAction(const YAML::Node& node, const std::string& what, MissionAction* action) {
    action->line = lineOf(node);
    if (node.IsScalar()) {
      const std::string word = node.Scalar();
      if (word == "continue") {
        action->kind = MissionAction::Kind::kContinue;
      } else if (word == "abort") {
        action->kind = MissionAction::Kind::kAbort;
      } else {
        return r_->error(node,
                         cat(what, ": unknown action '", word,
                             "' (expected continue, abort, {retry: N}, {fallback: [steps]})"));
      }
      return absl::OkStatus();
    }
    if (auto s = r_->mapping(node, what, {"retry", "then", "fallback"}); !s.ok()) return s;
    if (node["retry"]) {
      if (node["fallback"]) return r_->error(node, what + ": give 'retry' or 'fallback', not both");
      int retries = -1;
      if (!node["retry"].IsScalar() || !YAML::convert<int>::decode(node["retry"], retries) ||
          retries < 1 || retries > 100) {
        return r_->error(node["retry"],
                         what + " retry: expected a whole number of retries, 1..100");
      }
      action->kind = MissionAction::Kind::kRetry;
      action->retries = retries;
      if (node["then"]) {
        action->then = std::make_shared<MissionAction>();
        if (auto s = parseAction(node["then"], what + " then", action->then.get()); !s.ok())
          return s;
        if (action->then->kind == MissionAction::Kind::kRetry) {
          return r_->error(node["then"], what + " then: a retry cannot follow a retry");
        }
      }
      return absl::OkStatus();
    }
    if (node["then"]) return r_->error(node["then"], what + ": 'then' goes with 'retry'");
    if (!node["fallback"]) return r_->error(node, what + ": expected 'retry' or 'fallback'");
    action->kind = MissionAction::Kind::kFallback;
    if (auto s = stepList(node["fallback"], what + " fallback", &action->fallback); !s.ok())
      return s;
    if (action->fallback.empty()) return r_->error(node["fallback"], what + " fallback: empty");
    return absl::OkStatus();
  }

  // Checks the syntax of every ${belief.<key>} in the strings of `value`
  // (read from the mapping `node`, after ${param.x} were replaced); a
  // problem is named at its entry's line.
  absl::Status checkBindings(const YAML::Node& node, const google::protobuf::Value& value,
                             const std::string& what) const {
    const auto& fields = value.struct_value().fields();
    for (const auto& entry : node) {
      const auto it = fields.find(entry.first.Scalar());
      if (it == fields.end()) continue;
      if (auto s = bindingsValid(it->second); !s.ok()) {
        return r_->error(entry.second, what + ": " + std::string(s.message()));
      }
      if (auto s = eachValid(it->second); !s.ok()) {
        return r_->error(entry.second, what + ": " + std::string(s.message()));
      }
    }
    return absl::OkStatus();
  }

  // Every ${each.<name>} names the item of a for_each around it.
  absl::Status eachValid(const google::protobuf::Value& value) const {
    return forEachString(value, [&](const std::string& text) {
      for (const std::string& name : tokenNames(text, "each")) {
        if (std::find(each_.begin(), each_.end(), name) == each_.end()) {
          return absl::InvalidArgumentError(
              cat("${each.", name, "} is not the item of a for_each around it",
                  each_.empty() ? "" : " (its items: " + yaml::join(each_) + ")"));
        }
      }
      return absl::OkStatus();
    });
  }

  static absl::Status bindingsValid(const google::protobuf::Value& value) {
    return forEachString(
        value, [](const std::string& text) { return BeliefStore::bindingsIn(text).status(); });
  }

  // import: [file, ...]: files of sub-missions, read through imports_ (the
  // mission directory), each a mapping with `submissions` (and an optional
  // `description`); an imported file imports nothing itself.
  absl::Status importAll(const YAML::Node& node, MissionSpec* spec) {
    std::vector<std::string> files;
    if (auto s = r_->names(node, "import", &files); !s.ok()) return s;
    if (files.size() > kMaxImports) {
      return r_->error(node, cat("import: at most ", kMaxImports, " files"));
    }
    for (size_t i = 0; i < files.size(); ++i) {
      const YAML::Node at = node.IsSequence() ? node[i] : node;
      if (!imports_) {
        return r_->error(at,
                         "import: this mission cannot import files (the coordinator has no "
                         "--mission-dir)");
      }
      absl::StatusOr<std::string> text = imports_(files[i]);
      if (!text.ok())
        return r_->error(at, cat("import '", files[i], "': ", text.status().message()));
      YAML::Node root;
      if (auto s = yaml::load(*text, files[i], &root); !s.ok()) return s;
      readers_.push_back(std::make_unique<yaml::Reader>(files[i]));
      yaml::Reader* reader = readers_.back().get();
      reader->index(root);
      roots_.push_back(root);
      if (!root.IsMap()) return reader->error(root, "imported file: expected a mapping");
      if (auto s = reader->mapping(root, "imported file", {"description", "submissions"}); !s.ok())
        return s;
      if (!root["submissions"]) return reader->error(root, "imported file: missing 'submissions'");
      if (auto s = definitions(root["submissions"], reader); !s.ok()) return s;
      spec->imports[files[i]] = std::move(*text);
    }
    return absl::OkStatus();
  }

  // submissions: {name: {description, parameters: {p: {type, default, min,
  // max, description}}, steps: [...]}}. Their steps are parsed at each call,
  // with the call's parameters in place of ${param.<name>}.
  absl::Status definitions(const YAML::Node& node, yaml::Reader* reader) {
    if (auto s = reader->mapping(node, "submissions", {}); !s.ok()) return s;
    for (const auto& entry : node) {
      const std::string name = entry.first.Scalar();
      const std::string what = "submission '" + name + "'";
      if (!validName(name)) {
        return reader->keyError(entry.first, what + ": a name is letters, digits and '_'");
      }
      if (const auto found = defs_.find(name); found != defs_.end()) {
        return reader->keyError(
            entry.first, cat(what, ": defined twice (also ", found->second.reader->file(), ":",
                             found->second.line, ")"));
      }
      if (auto s = reader->mapping(entry.second, what, {"description", "parameters", "steps"});
          !s.ok()) {
        return s;
      }
      Definition definition;
      definition.reader = reader;
      definition.line = lineOf(entry.first);
      if (const YAML::Node params = entry.second["parameters"]) {
        if (auto s = reader->mapping(params, what + " parameters", {}); !s.ok()) return s;
        for (const auto& p : params) {
          SubParameter parameter;
          if (auto s = subParameter(*reader, p.first, p.second, what, &parameter); !s.ok())
            return s;
          definition.parameters.push_back(std::move(parameter));
        }
      }
      definition.steps = entry.second["steps"];
      if (!definition.steps) return reader->error(entry.second, what + ": missing 'steps'");
      if (!definition.steps.IsSequence() || definition.steps.size() == 0) {
        return reader->error(definition.steps, what + " steps: expected a list of steps");
      }
      if (auto s = usesDeclared(*reader, definition.steps, definition, what); !s.ok()) return s;
      defs_[name] = std::move(definition);
    }
    return absl::OkStatus();
  }

  absl::Status subParameter(const yaml::Reader& reader, const YAML::Node& key,
                            const YAML::Node& node, const std::string& what, SubParameter* out) {
    out->name = key.Scalar();
    const std::string label = cat(what, " parameter '", out->name, "'");
    if (!validName(out->name)) return reader.keyError(key, label + ": letters, digits and '_'");
    if (auto s = reader.mapping(node, label, {"type", "default", "min", "max", "description"});
        !s.ok()) {
      return s;
    }
    if (!node["type"]) {
      return reader.error(node, label +
                                    ": missing 'type' (number, string, bool, list, object or "
                                    "any)");
    }
    if (auto s = reader.text(node["type"], label + " type", &out->type); !s.ok()) return s;
    static const std::set<std::string> kTypes = {"number", "string", "bool",
                                                 "list",   "object", "any"};
    if (!kTypes.contains(out->type)) {
      return reader.error(node["type"], cat(label, ": unknown type '", out->type,
                                            "' (number, string, bool, list, object or any)"));
    }
    if (node["description"]) {
      if (auto s = reader.text(node["description"], label + " description", &out->description);
          !s.ok())
        return s;
    }
    for (auto [bound, target] : {std::pair{"min", &out->min}, std::pair{"max", &out->max}}) {
      if (!node[bound]) continue;
      double v = 0;
      if (out->type != "number" || !node[bound].IsScalar() ||
          !YAML::convert<double>::decode(node[bound], v) || !std::isfinite(v)) {
        return reader.error(node[bound], cat(label, " ", bound, ": a number, for type number"));
      }
      *target = v;
    }
    if (node["default"]) {
      google::protobuf::Value v;
      if (auto s = reader.value(node["default"], label + " default", &v); !s.ok()) return s;
      if (auto problem = argumentProblem(*out, v)) {
        return reader.error(node["default"], cat(label, " default: ", *problem));
      }
      out->default_value = v;
    }
    return absl::OkStatus();
  }

  // Every ${param.<name>} under `node` names a declared parameter.
  absl::Status usesDeclared(const yaml::Reader& reader, const YAML::Node& node,
                            const Definition& definition, const std::string& what) {
    if (node.IsScalar()) {
      for (const std::string& name : tokenNames(node.Scalar(), "param")) {
        bool declared = false;
        for (const auto& p : definition.parameters) declared = declared || p.name == name;
        if (!declared) {
          return reader.error(node,
                              cat(what, ": ${param.", name, "} is not one of its parameters"));
        }
      }
    } else if (node.IsSequence() || node.IsMap()) {
      for (const auto& item : node) {
        const YAML::Node child = node.IsMap() ? item.second : YAML::Node(item);
        if (auto s = usesDeclared(reader, child, definition, what); !s.ok()) return s;
      }
    }
    return absl::OkStatus();
  }

  // A call step: `call: name` and `with: {parameter: value}`; its body is the
  // sub-mission's steps, parsed with the call's parameters.
  absl::Status call(const YAML::Node& node, const std::string& label, MissionStep* step) {
    if (node["behavior"]) return r_->error(node["call"], label + ": give 'behavior' or 'call'");
    if (node["parameters"]) {
      return r_->error(node["parameters"], label + ": a call takes 'with', not 'parameters'");
    }
    if (auto s = r_->text(node["call"], label + " call", &step->call); !s.ok()) return s;
    const auto found = defs_.find(step->call);
    if (found == defs_.end()) {
      std::vector<std::string> known;
      for (const auto& [name, d] : defs_) known.push_back(name);
      return r_->error(node["call"], cat(label, ": no sub-mission '", step->call, "' (defined: ",
                                         known.empty() ? "none" : yaml::join(known), ")"));
    }
    const Definition& definition = found->second;
    if (std::find(calling_.begin(), calling_.end(), step->call) != calling_.end() ||
        calling_.size() >= kMaxCallDepth) {
      std::string chain;
      for (const auto& name : calling_) chain += name + " -> ";
      return r_->error(node["call"],
                       calling_.size() >= kMaxCallDepth
                           ? cat(label, ": sub-missions nest deeper than ", kMaxCallDepth)
                           : cat(label, ": sub-mission '", step->call, "' calls itself (", chain,
                                 step->call, ")"));
    }
    std::map<std::string, google::protobuf::Value> arguments;
    if (const YAML::Node with = node["with"]) {
      if (auto s = r_->mapping(with, label + " with", {}); !s.ok()) return s;
      google::protobuf::Value value;
      if (auto s = r_->value(with, label + " with", &value); !s.ok()) return s;
      if (auto s = substitute(with, label + " with", &value); !s.ok()) return s;
      if (auto s = checkBindings(with, value, label); !s.ok()) return s;
      for (const auto& entry : with) {
        const std::string key = entry.first.Scalar();
        const SubParameter* parameter = nullptr;
        std::vector<std::string> names;
        for (const auto& p : definition.parameters) {
          names.push_back(p.name);
          if (p.name == key) parameter = &p;
        }
        if (parameter == nullptr) {
          return r_->keyError(entry.first, cat(label, ": sub-mission '", step->call,
                                               "' has no parameter '", key, "' (its parameters: ",
                                               names.empty() ? "none" : yaml::join(names), ")"));
        }
        const google::protobuf::Value& given = value.struct_value().fields().at(key);
        if (auto problem = argumentProblem(*parameter, given)) {
          return r_->error(entry.second, cat(label, " with ", key, ": ", *problem));
        }
        arguments[key] = given;
      }
      step->with = value.struct_value();
    }
    for (const auto& p : definition.parameters) {
      if (arguments.contains(p.name)) continue;
      if (!p.default_value) {
        return r_->error(node["call"],
                         cat(label, ": sub-mission '", step->call, "' needs parameter '", p.name,
                             "'", p.description.empty() ? "" : ": " + p.description));
      }
      arguments[p.name] = *p.default_value;
    }
    // The body, in the sub-mission's file, with these parameters.
    yaml::Reader* const saved_reader = r_;
    std::map<std::string, google::protobuf::Value> saved_params = std::move(params_);
    r_ = definition.reader;
    params_ = std::move(arguments);
    calling_.push_back(step->call);
    absl::Status parsed =
        stepList(definition.steps, "submission '" + step->call + "'", &step->body);
    calling_.pop_back();
    params_ = std::move(saved_params);
    r_ = saved_reader;
    return parsed;
  }

  // A loop: `for_each: {in: [...] | {belief: key}, as: name, max_items: N}`
  // or `repeat: {times: N}` or `repeat: {until: <belief condition>,
  // max_times: N}`, with its `steps`. Every loop is bounded.
  absl::Status loop(const YAML::Node& node, const std::string& label, MissionStep* step) {
    if (node["behavior"] || node["call"]) {
      return r_->error(node, label + ": a loop has 'steps', not a 'behavior' or a 'call'");
    }
    if (node["for_each"] && node["repeat"]) {
      return r_->error(node, label + ": give 'for_each' or 'repeat', not both");
    }
    if (node["parameters"])
      return r_->error(node["parameters"], label + ": a loop has no parameters");
    MissionLoop loop;
    auto whole = [&](const YAML::Node& n, const std::string& what, int low, int high, int* out) {
      if (!n.IsScalar() || !YAML::convert<int>::decode(n, *out) || *out < low || *out > high) {
        return r_->error(n, cat(label, " ", what, ": a whole number, ", low, "..", high));
      }
      return absl::OkStatus();
    };
    if (const YAML::Node each = node["for_each"]) {
      loop.kind = MissionLoop::Kind::kForEach;
      if (auto s = r_->mapping(each, label + " for_each", {"in", "as", "max_items"}); !s.ok())
        return s;
      if (!each["in"] || !each["as"]) {
        return r_->error(each, label + " for_each: needs 'in' (a list, or {belief: key}) and 'as'");
      }
      if (auto s = r_->text(each["as"], label + " for_each as", &loop.as); !s.ok()) return s;
      if (!validName(loop.as)) {
        return r_->error(each["as"], label + " for_each as: letters, digits and '_'");
      }
      loop.max_items = kMaxLoopItems;
      if (each["max_items"]) {
        if (auto s =
                whole(each["max_items"], "for_each max_items", 1, kMaxLoopItems, &loop.max_items);
            !s.ok())
          return s;
      }
      const YAML::Node in = each["in"];
      if (in.IsMap()) {
        if (auto s = r_->mapping(in, label + " for_each in", {"belief"}); !s.ok()) return s;
        if (!in["belief"]) return r_->error(in, label + " for_each in: expected {belief: key}");
        if (auto s = r_->text(in["belief"], label + " for_each in belief", &loop.belief); !s.ok())
          return s;
        if (auto s = BeliefStore::checkKey(loop.belief); !s.ok()) {
          return r_->error(in["belief"], label + " for_each in: " + std::string(s.message()));
        }
      } else {
        google::protobuf::Value items;
        if (auto s = r_->value(in, label + " for_each in", &items); !s.ok()) return s;
        if (!items.has_list_value()) {
          return r_->error(in, label + " for_each in: expected a list, or {belief: key}");
        }
        if (auto s = substitute(in, label + " for_each in", &items); !s.ok()) return s;
        if (items.list_value().values_size() > loop.max_items) {
          return r_->error(in, cat(label, " for_each in: ", items.list_value().values_size(),
                                   " items, more than max_items ", loop.max_items));
        }
        loop.items = items.list_value();
      }
    } else {
      const YAML::Node repeat = node["repeat"];
      if (auto s = r_->mapping(repeat, label + " repeat", {"times", "until", "max_times"}); !s.ok())
        return s;
      if (repeat["times"]) {
        if (repeat["until"] || repeat["max_times"]) {
          return r_->error(repeat, label + " repeat: give 'times', or 'until' with 'max_times'");
        }
        loop.kind = MissionLoop::Kind::kTimes;
        if (auto s = whole(repeat["times"], "repeat times", 1, kMaxLoopItems, &loop.times); !s.ok())
          return s;
      } else if (repeat["until"]) {
        loop.kind = MissionLoop::Kind::kUntil;
        if (!repeat["max_times"]) {
          return r_->error(repeat, label +
                                       " repeat: 'until' needs 'max_times' (every loop has a "
                                       "bound, so that a mission always ends)");
        }
        if (auto s = whole(repeat["max_times"], "repeat max_times", 1, kMaxLoopItems, &loop.times);
            !s.ok())
          return s;
        BeliefCondition until;
        if (auto s = condition(repeat["until"], label + " repeat until", &until); !s.ok()) return s;
        loop.until = until;
      } else {
        return r_->error(repeat, label +
                                     " repeat: needs 'times', or 'until' with 'max_times' "
                                     "(every loop has a bound, so that a mission always ends)");
      }
    }
    if (!node["steps"]) return r_->error(node, label + ": a loop needs 'steps'");
    step->loop = std::move(loop);
    if (!step->loop->as.empty()) each_.push_back(step->loop->as);
    absl::Status parsed = stepList(node["steps"], label, &step->body);
    if (!step->loop->as.empty()) each_.pop_back();
    if (parsed.ok() && step->body.empty()) {
      return r_->error(node["steps"], label + " steps: empty");
    }
    return parsed;
  }

  // {battery_below: r} or {near: {point_m: [x, y, z], radius_m: r}}, with
  // `ends: <cause>` (default SITUATION_CHANGE) and `max_age_s`.
  absl::Status vehicleCondition(const YAML::Node& node, const std::string& what,
                                VehicleCondition* out) {
    if (auto s = r_->mapping(node, what, {"battery_below", "near", "ends", "max_age_s"}); !s.ok())
      return s;
    out->line = lineOf(node);
    auto number = [&](const YAML::Node& n, const std::string& field, double low, double high,
                      double* value) {
      if (!n.IsScalar() || !YAML::convert<double>::decode(n, *value) || !std::isfinite(*value) ||
          *value < low || *value > high) {
        return r_->error(n, cat(what, " ", field, ": a number in [", params::numberText(low), ", ",
                                params::numberText(high), "]"));
      }
      return absl::OkStatus();
    };
    if (node["battery_below"] && !node["near"]) {
      out->kind = VehicleCondition::Kind::kBatteryBelow;
      if (auto s = number(node["battery_below"], "battery_below", 0, 1, &out->battery_ratio);
          !s.ok())
        return s;
    } else if (node["near"] && !node["battery_below"]) {
      out->kind = VehicleCondition::Kind::kNear;
      const YAML::Node near = node["near"];
      if (auto s = r_->mapping(near, what + " near", {"point_m", "radius_m"}); !s.ok()) return s;
      const YAML::Node point = near["point_m"];
      if (!point || !point.IsSequence() || point.size() != 3) {
        return r_->error(point ? point : near, what + " near: point_m is [x, y, z] in metres");
      }
      for (size_t i = 0; i < 3; ++i) {
        if (auto s = number(point[i], "near point_m", -1e6, 1e6, &out->point_m[i]); !s.ok())
          return s;
      }
      if (!near["radius_m"]) return r_->error(near, what + " near: needs radius_m");
      if (auto s = number(near["radius_m"], "near radius_m", 0.01, 1e6, &out->radius_m); !s.ok())
        return s;
    } else {
      return r_->error(node,
                       what + ": give one of battery_below (0..1) and near ({point_m, radius_m})");
    }
    if (node["ends"]) {
      if (auto s = r_->text(node["ends"], what + " ends", &out->ends); !s.ok()) return s;
      static const std::set<std::string> kEnds = {"GOAL_ACHIEVED", "SITUATION_CHANGE",
                                                  "WRONG_PROGRESS", "TIME_OUT"};
      if (!kEnds.contains(out->ends)) {
        return r_->error(node["ends"], cat(what, " ends: '", out->ends,
                                           "' (GOAL_ACHIEVED, SITUATION_CHANGE, WRONG_PROGRESS or "
                                           "TIME_OUT)"));
      }
    }
    if (node["max_age_s"]) {
      if (auto s = number(node["max_age_s"], "max_age_s", 0.05, 60, &out->max_age_s); !s.ok())
        return s;
    }
    return absl::OkStatus();
  }

  // parallel: {end: all|any, branches: [...]}: each branch is {name, robot,
  // steps: [...]}, or a single step.
  absl::Status parallel(const YAML::Node& node, const std::string& label, MissionStep* step) {
    if (auto s = r_->mapping(node, label + " parallel", {"end", "branches"}); !s.ok()) return s;
    MissionParallel parallel;
    if (node["end"]) {
      std::string end;
      if (auto s = r_->text(node["end"], label + " parallel end", &end); !s.ok()) return s;
      if (end != "all" && end != "any") {
        return r_->error(node["end"], cat(label, " parallel end: '", end, "' (all or any)"));
      }
      parallel.any = end == "any";
    }
    const YAML::Node branches = node["branches"];
    if (!branches || !branches.IsSequence() || branches.size() < 2 ||
        branches.size() > kMaxBranches) {
      return r_->error(branches ? branches : node, cat(label, " parallel branches: a list of 2 to ",
                                                       kMaxBranches, " branches"));
    }
    // Each branch runs on a thread of its own while its step runs: bounded.
    branch_count_ += branches.size();
    if (branch_count_ > kMaxBranchesInMission) {
      return r_->error(branches, cat(label, " parallel: more than ", kMaxBranchesInMission,
                                     " branches in the mission (sub-missions' calls included)"));
    }
    for (size_t i = 0; i < branches.size(); ++i) {
      const YAML::Node b = branches[i];
      const std::string what = cat(label, " branch ", i);
      MissionBranch branch;
      if (b.IsMap() && b["steps"] && !b["for_each"] && !b["repeat"]) {
        if (auto s = r_->mapping(b, what, {"name", "robot", "steps"}); !s.ok()) return s;
        if (b["name"]) {
          if (auto s = r_->text(b["name"], what + " name", &branch.name); !s.ok()) return s;
        }
        const std::string saved_robot = robot_;
        absl::Status parsed = absl::OkStatus();
        if (b["robot"]) parsed = robot(b["robot"], what, &robot_);
        if (parsed.ok()) parsed = stepList(b["steps"], what, &branch.steps);
        robot_ = saved_robot;
        if (!parsed.ok()) return parsed;
        if (branch.steps.empty()) return r_->error(b["steps"], what + " steps: empty");
      } else {
        MissionStep one;
        if (auto s = parseStep(b, what, &one); !s.ok()) return s;
        branch.name = one.name;
        branch.steps.push_back(std::move(one));
      }
      parallel.branches.push_back(std::move(branch));
    }
    step->parallel = std::move(parallel);
    return absl::OkStatus();
  }

  // wait_for: {step: name, timeout_s: T} or {belief: key, exists|equals,
  // timeout_s: T}.
  absl::Status waitFor(const YAML::Node& node, const std::string& label, MissionStep* step) {
    const std::string what = label + " wait_for";
    if (!node.IsMap()) return r_->error(node, what + ": expected a mapping");
    MissionWait wait;
    if (node["step"]) {
      if (auto s = r_->mapping(node, what, {"step", "timeout_s"}); !s.ok()) return s;
      if (auto s = r_->text(node["step"], what + " step", &wait.step); !s.ok()) return s;
      waits_.emplace_back(wait.step, node["step"]);
    } else if (node["belief"]) {
      BeliefCondition c;
      if (auto s = condition(node, what, &c, {"timeout_s"}); !s.ok()) return s;
      wait.belief = std::move(c);
    } else {
      return r_->error(node, what + ": needs 'step' (a step's name) or 'belief' (a condition)");
    }
    const YAML::Node timeout = node["timeout_s"];
    if (!timeout || !timeout.IsScalar() ||
        !YAML::convert<double>::decode(timeout, wait.timeout_s) ||
        !(wait.timeout_s > 0 && wait.timeout_s <= kMaxWaitS)) {
      return r_->error(timeout ? timeout : node,
                       cat(what, ": needs 'timeout_s', a number of seconds in (0, ", kMaxWaitS,
                           "] (every wait has a bound, so that a mission always ends)"));
    }
    step->wait = std::move(wait);
    return absl::OkStatus();
  }

  // ${param.<name>} in the strings of `value` (read from `node`) replaced by
  // the current call's parameters: a whole string by the value itself, a
  // part by its text.
  absl::Status substitute(const YAML::Node& node, const std::string& what,
                          google::protobuf::Value* value) const {
    const absl::Status s = substituteTokens(
        value, "param",
        [this](const std::string& name) -> const google::protobuf::Value* {
          const auto it = params_.find(name);
          return it == params_.end() ? nullptr : &it->second;
        },
        [this](const std::string& name) {
          return cat("${param.", name, "} ",
                     calling_.empty() ? "is only for a sub-mission's steps" : "is not a parameter");
        });
    if (!s.ok()) return r_->error(node, cat(what, ": ", s.message()));
    return absl::OkStatus();
  }

  static bool validName(const std::string& name) {
    if (name.empty() || name.size() > 64 || std::isdigit(static_cast<unsigned char>(name[0]))) {
      return false;
    }
    for (char c : name) {
      if (!std::isalnum(static_cast<unsigned char>(c)) && c != '_') return false;
    }
    return true;
  }

  static constexpr size_t kMaxImports = 16;
  static constexpr int kMaxLoopItems = 1000;
  static constexpr size_t kMaxCallDepth = 8;
  static constexpr size_t kMaxBranches = 16;
  static constexpr size_t kMaxBranchesInMission = 64;
  static constexpr size_t kMaxVehicleConditions = 8;
  static constexpr double kMaxWaitS = 86400;

  struct Definition {
    yaml::Reader* reader = nullptr;
    int line = 0;
    std::vector<SubParameter> parameters;
    YAML::Node steps;
  };

  yaml::Reader main_;
  yaml::Reader* r_;  // of the document being read: the mission, or an imported file
  ImportReader imports_;
  std::vector<std::unique_ptr<yaml::Reader>> readers_;  // of the imported files
  std::vector<YAML::Node> roots_;                       // the imported documents
  std::map<std::string, Definition> defs_;
  std::vector<std::string> calling_;  // the sub-missions whose calls are being parsed
  std::map<std::string, google::protobuf::Value> params_;  // of the innermost call
  std::vector<std::string> each_;    // the `as` names of the for_each loops being parsed
  std::string robot_;                // the robot of the step or branch being parsed
  size_t branch_count_ = 0;          // parallel branches so far
  std::vector<std::string> robots_;  // every robot named, in order
  std::set<std::string> names_;      // every step's name
  std::vector<std::pair<std::string, YAML::Node>> waits_;  // wait_for step: name, where
};

bool hasBinding(const google::protobuf::Value& value) {
  if (value.has_string_value()) {
    // A belief's value, or a for_each item: known when the step starts.
    return value.string_value().find("${belief.") != std::string::npos ||
           value.string_value().find("${each.") != std::string::npos;
  }
  if (value.has_list_value()) {
    for (const auto& v : value.list_value().values()) {
      if (hasBinding(v)) return true;
    }
  }
  if (value.has_struct_value()) {
    for (const auto& [k, v] : value.struct_value().fields()) {
      if (hasBinding(v)) return true;
    }
  }
  return false;
}

bool literalMatches(const v1::ParameterSchema& schema, const google::protobuf::Value& value) {
  if (hasBinding(value)) return true;
  if (schema.repeated()) {
    if (!value.has_list_value()) return false;
    v1::ParameterSchema element = schema;
    element.set_repeated(false);
    for (const auto& item : value.list_value().values()) {
      if (!literalMatches(element, item)) return false;
    }
    return true;
  }
  return valueHasType(schema, value);
}

// A literal number (or each number of a literal list) outside the schema's
// range, as the behavior would refuse it at activation.
std::optional<std::string> outOfRange(const v1::ParameterSchema& schema,
                                      const google::protobuf::Value& value,
                                      const std::string& key) {
  if (!schema.has_range()) return std::nullopt;
  const v1::Range& range = schema.range();
  auto outside = [&](double v) {
    return (range.has_min() && v < range.min()) || (range.has_max() && v > range.max());
  };
  if (value.has_number_value() && outside(value.number_value())) {
    return cat("parameter '", key, "' = ", params::numberText(value.number_value()),
               " is out of range ", params::rangeText(range));
  }
  if (value.has_list_value()) {
    const auto& items = value.list_value().values();
    for (int i = 0; i < items.size(); ++i) {
      if (items[i].has_number_value() && outside(items[i].number_value())) {
        return cat("parameter '", key, "[", i, "]' = ", params::numberText(items[i].number_value()),
                   " is out of range ", params::rangeText(range));
      }
    }
  }
  return std::nullopt;
}

const std::string& fileOf(const MissionSpec& mission, const MissionStep& step) {
  return step.file.empty() ? mission.file : step.file;
}

void checkParameters(const MissionSpec& mission, const MissionStep& step,
                     const v1::BehaviorDescription& d, MissionProblems* problems) {
  std::vector<std::string> known;
  for (const auto& p : d.parameters()) known.push_back(p.name());
  for (const auto& [key, value] : step.parameters.fields()) {
    const auto line_it = step.parameter_lines.find(key);
    const int line = line_it == step.parameter_lines.end() ? step.line : line_it->second;
    const std::string field = cat(step.path, ".parameters.", key);
    const v1::ParameterSchema* schema = nullptr;
    for (const auto& p : d.parameters()) {
      if (p.name() == key) schema = &p;
    }
    if (schema == nullptr) {
      problems->add(fileOf(mission, step), line, field,
                    cat(step.behavior, " has no parameter '", key,
                        "' (its parameters: ", known.empty() ? "none" : yaml::join(known), ")"));
    } else if (!literalMatches(*schema, value)) {
      problems->add(fileOf(mission, step), line, field,
                    cat(step.behavior, " parameter '", key, "' must be ",
                        schema->repeated() ? "a list of " : "a ", schema->type()));
    } else if (auto range = outOfRange(*schema, value, key)) {
      problems->add(fileOf(mission, step), line, field, cat(step.behavior, " ", *range));
    }
  }
  for (const auto& p : d.parameters()) {
    if (p.required() && p.default_json().empty() && !step.parameters.fields().contains(p.name())) {
      problems->add(fileOf(mission, step), step.line, cat(step.path, ".parameters.", p.name()),
                    cat(step.behavior, " needs parameter '", p.name(), "'",
                        p.description().empty() ? "" : ": " + p.description()));
    }
  }
}

// The registered-behavior checks of one step (forEachStep visits them all).
void checkStep(const MissionSpec& mission, const MissionStep& step, const BehaviorLookup& lookup,
               MissionProblems* problems) {
  if (step.behavior.empty()) return;
  if (const v1::BehaviorDescription* d = lookup(step.robot, step.behavior)) {
    checkParameters(mission, step, *d, problems);
  } else {
    const std::string& robot = step.robot.empty() ? mission.robot_id : step.robot;
    problems->add(fileOf(mission, step), step.line, step.path + ".behavior",
                  cat("behavior ", step.behavior, " is not hosted by any registered system",
                      robot.empty() ? "" : " of robot '" + robot + "'"));
  }
}

}  // namespace

absl::StatusOr<MissionSpec> parseMission(const std::string& text, const std::string& file,
                                         const ImportReader& imports) {
  YAML::Node root;
  if (auto s = yaml::load(text, file, &root); !s.ok()) {
    return errors::withReason(errors::withFieldViolation(s, "", s.message()), v1::MISSION_INVALID);
  }
  absl::StatusOr<MissionSpec> mission = absl::InternalError("not parsed");
  const absl::Status guarded = server_kit::guardYamlParse(file, [&] {
    mission = MissionParser(file, imports).parse(root);
    return absl::OkStatus();
  });
  if (!guarded.ok()) return errors::withReason(guarded, v1::MISSION_INVALID);
  if (!mission.ok()) return errors::withReason(mission.status(), v1::MISSION_INVALID);
  return mission;
}

void forEachStep(const std::vector<MissionStep>& steps,
                 const std::function<void(const MissionStep&)>& visit) {
  for (const MissionStep& step : steps) {
    visit(step);
    forEachStep(step.body, visit);
    if (step.parallel) {
      for (const MissionBranch& b : step.parallel->branches) forEachStep(b.steps, visit);
    }
    for (const auto& [cause, action] : step.on) {
      for (const MissionAction* a = &action; a != nullptr; a = a->then.get()) {
        forEachStep(a->fallback, visit);
      }
    }
  }
}

std::vector<std::string> missionRobots(const MissionSpec& mission, const std::string& robot_id) {
  std::vector<std::string> robots = {robot_id};
  for (const std::string& robot : mission.robots) {
    if (robot != robot_id) robots.push_back(robot);
  }
  return robots;
}

absl::StatusOr<MissionSpec> loadMission(const std::string& path) {
  std::ifstream in(path);
  if (!in) return absl::InvalidArgumentError(path + ": cannot read the mission file");
  std::stringstream text;
  text << in.rdbuf();
  return parseMission(text.str(), path);
}

void MissionProblems::add(const std::string& file, int line, std::string field,
                          const std::string& what) {
  const std::string description =
      line > 0 ? cat(file, ":", line, ": ", what) : cat(file, ": ", what);
  for (const MissionProblem& seen : list) {
    // A sub-mission called twice has its problems once.
    if (seen.description == description && seen.field == field) return;
  }
  if (list.size() >= kMaxProblems) {
    ++left_out;
    return;
  }
  MissionProblem problem;
  problem.file = file;
  problem.line = line;
  problem.field = std::move(field);
  problem.description = description;
  list.push_back(std::move(problem));
}

void MissionProblems::addStatus(const absl::Status& status, const std::string& file) {
  // The parser's messages start "<file>:<line>: " (yaml::Reader).
  int line = 0;
  const std::string message(status.message());
  const std::string prefix = file + ":";
  if (message.rfind(prefix, 0) == 0) {
    size_t i = prefix.size();
    while (i < message.size() && message[i] >= '0' && message[i] <= '9') {
      line = line * 10 + (message[i] - '0');
      if (line > 100000000) break;
      ++i;
    }
  }
  std::string field;
  const std::optional<google::rpc::BadRequest> bad = errors::badRequest(status);
  if (bad && bad->field_violations_size() > 0) field = bad->field_violations(0).field();
  if (list.size() >= kMaxProblems) {
    ++left_out;
    return;
  }
  list.push_back({file, line, std::move(field), message});
}

absl::Status MissionProblems::status() const {
  if (list.empty()) return absl::OkStatus();
  std::vector<std::string> lines;
  for (const MissionProblem& p : list) lines.push_back(p.description);
  if (left_out > 0) lines.push_back(cat("... and ", left_out, " more"));
  const std::size_t count = list.size() + left_out;
  absl::Status status = absl::InvalidArgumentError(
      count == 1 ? lines.front()
                 : cat(count, " problems in the mission:\n  ", absl::StrJoin(lines, "\n  ")));
  for (const MissionProblem& p : list) {
    status = errors::withFieldViolation(status, p.field, p.description);
  }
  return errors::withReason(status, v1::MISSION_INVALID);
}

MissionProblems checkMissionProblems(const MissionSpec& mission, const BehaviorLookup& lookup) {
  MissionProblems problems;
  for (const auto* list : {&mission.recurrent, &mission.steps, &mission.safety}) {
    forEachStep(*list,
                [&](const MissionStep& step) { checkStep(mission, step, lookup, &problems); });
  }
  return problems;
}

absl::Status checkMission(const MissionSpec& mission, const BehaviorLookup& lookup) {
  return checkMissionProblems(mission, lookup).status();
}

std::vector<std::string> tokenNames(const std::string& text, const std::string& kind) {
  std::vector<std::string> names;
  const std::string open = "${" + kind + ".";
  for (size_t at = text.find(open); at != std::string::npos; at = text.find(open, at + 1)) {
    const size_t end = text.find('}', at);
    if (end == std::string::npos) break;
    names.push_back(text.substr(at + open.size(), end - at - open.size()));
  }
  return names;
}

absl::Status forEachString(const google::protobuf::Value& value,
                           const std::function<absl::Status(const std::string&)>& check) {
  if (value.has_string_value()) return check(value.string_value());
  if (value.has_list_value()) {
    for (const auto& item : value.list_value().values()) {
      if (auto s = forEachString(item, check); !s.ok()) return s;
    }
  }
  if (value.has_struct_value()) {
    for (const auto& [key, field] : value.struct_value().fields()) {
      if (auto s = forEachString(field, check); !s.ok()) return s;
    }
  }
  return absl::OkStatus();
}

absl::Status substituteTokens(
    google::protobuf::Value* value, const std::string& kind,
    const std::function<const google::protobuf::Value*(const std::string&)>& lookup,
    const std::function<std::string(const std::string&)>& unknown) {
  if (value->has_list_value()) {
    for (auto& item : *value->mutable_list_value()->mutable_values()) {
      if (auto s = substituteTokens(&item, kind, lookup, unknown); !s.ok()) return s;
    }
    return absl::OkStatus();
  }
  if (value->has_struct_value()) {
    for (auto& [key, field] : *value->mutable_struct_value()->mutable_fields()) {
      if (auto s = substituteTokens(&field, kind, lookup, unknown); !s.ok()) return s;
    }
    return absl::OkStatus();
  }
  if (!value->has_string_value()) return absl::OkStatus();
  const std::vector<std::string> names = tokenNames(value->string_value(), kind);
  std::string out = value->string_value();
  for (const std::string& name : names) {
    const google::protobuf::Value* replacement = lookup(name);
    if (replacement == nullptr) return absl::InvalidArgumentError(unknown(name));
    const std::string token = "${" + kind + "." + name + "}";
    if (out == token) {
      *value = *replacement;  // a whole value: the value itself
      return absl::OkStatus();
    }
    std::string part;
    if (replacement->has_string_value()) {
      part = replacement->string_value();
    } else if (replacement->has_number_value()) {
      part = params::numberText(replacement->number_value());
    } else if (replacement->has_bool_value()) {
      part = replacement->bool_value() ? "true" : "false";
    } else {
      return absl::InvalidArgumentError(token +
                                        " is a list or an object; it can only stand alone in a "
                                        "value, not inside a text");
    }
    for (size_t at = out.find(token); at != std::string::npos;
         at = out.find(token, at + part.size())) {
      out.replace(at, token.size(), part);
    }
  }
  if (!names.empty()) value->set_string_value(out);
  return absl::OkStatus();
}

std::string causeName(v1::TerminationCause cause) {
  std::string name = v1::TerminationCause_Name(cause);
  const std::string prefix = "TERMINATION_CAUSE_";
  return name.rfind(prefix, 0) == 0 ? name.substr(prefix.size()) : name;
}

}  // namespace behaviorlib::coordinator
