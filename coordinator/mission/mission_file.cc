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

class MissionParser {
 public:
  explicit MissionParser(const std::string& file) : r_(file) {}

  absl::StatusOr<MissionSpec> parse(const YAML::Node& root) {
    MissionSpec spec;
    spec.file = r_.file();
    r_.index(root);
    if (root.IsNull()) return absl::InvalidArgumentError(r_.file() + ":1: the mission is empty");
    if (auto s = r_.mapping(
            root, "mission",
            {"name", "description", "robot", "geofence", "recurrent", "safety", "steps"});
        !s.ok()) {
      return s;
    }
    if (root["name"]) {
      if (auto s = r_.text(root["name"], "mission name", &spec.name); !s.ok()) return s;
    }
    if (root["description"]) {
      if (auto s = r_.text(root["description"], "mission description", &spec.description);
          !s.ok()) {
        return s;
      }
    }
    if (root["robot"]) {
      if (auto s = r_.text(root["robot"], "mission robot", &spec.robot_id); !s.ok()) return s;
      spec.robot_line = lineOf(root["robot"]);
    }
    if (root["geofence"]) {
      if (auto s = geofence(root["geofence"], &spec); !s.ok()) return s;
    }
    if (!root["steps"]) return r_.error(root, "mission: missing 'steps'");
    if (auto s = stepList(root["steps"], "steps", &spec.steps); !s.ok()) return s;
    if (spec.steps.empty()) return r_.error(root["steps"], "mission: 'steps' is empty");
    for (auto [key, out] :
         {std::pair{"recurrent", &spec.recurrent}, std::pair{"safety", &spec.safety}}) {
      if (!root[key]) continue;
      if (auto s = stepList(root[key], key, out); !s.ok()) return s;
      for (const auto& step : *out) {
        if (step.behavior.empty()) {
          return stepError(step.path + ".behavior",
                           cat(r_.file(), ":", step.line, ": ", key, " step: missing 'behavior'"));
        }
        if (!step.on.empty() || step.condition) {
          return stepError(
              step.path + (step.on.empty() ? ".if" : ".on"),
              cat(r_.file(), ":", step.line, ": ", key, " step: 'on' and 'if' are for steps only"));
        }
      }
    }
    return spec;
  }

 private:
  // geofence: {min_m: [x, y, z], max_m: [x, y, z]} (world ENU, metres).
  absl::Status geofence(const YAML::Node& node, MissionSpec* spec) {
    if (auto s = r_.mapping(node, "geofence", {"min_m", "max_m"}); !s.ok()) return s;
    Geofence fence;
    for (auto [key, out] : {std::pair{"min_m", &fence.min_m}, std::pair{"max_m", &fence.max_m}}) {
      const YAML::Node corner = node[key];
      if (!corner)
        return r_.error(node, cat("geofence: missing '", key, "' ([x, y, z] in metres)"));
      if (!corner.IsSequence() || corner.size() != 3) {
        return r_.error(corner, cat("geofence ", key, ": expected [x, y, z] in metres"));
      }
      for (size_t i = 0; i < 3; ++i) {
        try {
          (*out)[i] = corner[i].as<double>();
        } catch (const YAML::Exception&) {
          return r_.error(corner[i],
                          cat("geofence ", key, ": '", corner[i].Scalar(), "' is not a number"));
        }
        if (!std::isfinite((*out)[i])) {
          return r_.error(corner[i], cat("geofence ", key, ": coordinates must be finite"));
        }
      }
    }
    for (size_t i = 0; i < 3; ++i) {
      if (!(fence.min_m[i] < fence.max_m[i])) {
        return r_.error(node, "geofence: min_m must be below max_m on every axis");
      }
    }
    fence.line = node.Mark().line + 1;
    spec->geofence = fence;
    return absl::OkStatus();
  }

  absl::Status stepList(const YAML::Node& node, const std::string& what,
                        std::vector<MissionStep>* out) {
    if (!node.IsSequence()) return r_.error(node, what + ": expected a list of steps");
    for (const auto& item : node) {
      MissionStep step;
      if (auto s = parseStep(item, what, &step); !s.ok()) return s;
      out->push_back(std::move(step));
    }
    return absl::OkStatus();
  }

  absl::Status parseStep(const YAML::Node& node, const std::string& list, MissionStep* step) {
    step->line = lineOf(node);
    step->path = r_.pathOf(node);
    const std::string what = list + " step";
    if (auto s = r_.mapping(node, what, {"name", "behavior", "parameters", "on", "if", "remember"});
        !s.ok()) {
      return s;
    }
    if (node["name"]) {
      if (auto s = r_.text(node["name"], what + " name", &step->name); !s.ok()) return s;
    }
    const std::string label = step->name.empty() ? what : what + " '" + step->name + "'";
    if (node["behavior"]) {
      if (auto s = r_.text(node["behavior"], label + " behavior", &step->behavior); !s.ok())
        return s;
    }
    if (const YAML::Node params = node["parameters"]) {
      if (!params.IsMap()) return r_.error(params, label + " parameters: expected a mapping");
      google::protobuf::Value value;
      if (auto s = r_.value(params, label + " parameters", &value); !s.ok()) return s;
      step->parameters = value.struct_value();
      for (const auto& entry : params) {
        step->parameter_lines[entry.first.as<std::string>()] = lineOf(entry.first);
      }
      if (auto s = checkBindings(params, label); !s.ok()) return s;
    }
    if (const YAML::Node remember = node["remember"]) {
      if (auto s = r_.mapping(remember, label + " remember", {}); !s.ok()) return s;
      for (const auto& entry : remember) {
        if (auto s = BeliefStore::checkKey(entry.first.as<std::string>()); !s.ok()) {
          return r_.keyError(entry.first, label + " remember: " + std::string(s.message()));
        }
      }
      google::protobuf::Value value;
      if (auto s = r_.value(remember, label + " remember", &value); !s.ok()) return s;
      step->remember = value.struct_value();
      if (auto s = checkBindings(remember, label); !s.ok()) return s;
    }
    if (step->behavior.empty() && step->remember.fields().empty()) {
      return r_.error(node, label + ": needs a 'behavior' (or only 'remember')");
    }
    if (const YAML::Node condition = node["if"]) {
      if (auto s = r_.mapping(condition, label + " if", {"belief", "exists", "equals"}); !s.ok()) {
        return s;
      }
      BeliefCondition c;
      c.line = lineOf(condition);
      if (!condition["belief"])
        return r_.error(condition, label + " if: missing 'belief' (the key)");
      if (auto s = r_.text(condition["belief"], label + " if belief", &c.key); !s.ok()) return s;
      if (auto s = BeliefStore::checkKey(c.key); !s.ok()) {
        return r_.error(condition["belief"], label + " if: " + std::string(s.message()));
      }
      if (condition["exists"]) {
        bool exists = false;
        if (!condition["exists"].IsScalar() ||
            !YAML::convert<bool>::decode(condition["exists"], exists)) {
          return r_.error(condition["exists"], label + " if exists: expected true or false");
        }
        c.exists = exists;
      }
      if (condition["equals"]) {
        google::protobuf::Value v;
        if (auto s = r_.value(condition["equals"], label + " if equals", &v); !s.ok()) return s;
        c.equals = v;
      }
      if (c.exists.has_value() == c.equals.has_value()) {
        return r_.error(condition, label + " if: give exactly one of 'exists' and 'equals'");
      }
      step->condition = c;
    }
    if (const YAML::Node on = node["on"]) {
      if (step->behavior.empty()) return r_.error(on, label + ": 'on' needs a 'behavior'");
      if (auto s = r_.mapping(on, label + " on", causeKeys()); !s.ok()) return s;
      for (const auto& entry : on) {
        MissionAction action;
        const std::string cause = entry.first.as<std::string>();
        if (auto s = parseAction(entry.second, label + " on " + cause, &action); !s.ok()) return s;
        step->on[cause] = std::move(action);
      }
    }
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
        return r_.error(node, cat(what, ": unknown action '", word,
                                  "' (expected continue, abort, {retry: N}, {fallback: [steps]})"));
      }
      return absl::OkStatus();
    }
    if (auto s = r_.mapping(node, what, {"retry", "then", "fallback"}); !s.ok()) return s;
    if (node["retry"]) {
      if (node["fallback"]) return r_.error(node, what + ": give 'retry' or 'fallback', not both");
      int retries = -1;
      if (!node["retry"].IsScalar() || !YAML::convert<int>::decode(node["retry"], retries) ||
          retries < 1 || retries > 100) {
        return r_.error(node["retry"], what + " retry: expected a whole number of retries, 1..100");
      }
      action->kind = MissionAction::Kind::kRetry;
      action->retries = retries;
      if (node["then"]) {
        action->then = std::make_shared<MissionAction>();
        if (auto s = parseAction(node["then"], what + " then", action->then.get()); !s.ok())
          return s;
        if (action->then->kind == MissionAction::Kind::kRetry) {
          return r_.error(node["then"], what + " then: a retry cannot follow a retry");
        }
      }
      return absl::OkStatus();
    }
    if (node["then"]) return r_.error(node["then"], what + ": 'then' goes with 'retry'");
    if (!node["fallback"]) return r_.error(node, what + ": expected 'retry' or 'fallback'");
    action->kind = MissionAction::Kind::kFallback;
    if (auto s = stepList(node["fallback"], what + " fallback", &action->fallback); !s.ok())
      return s;
    if (action->fallback.empty()) return r_.error(node["fallback"], what + " fallback: empty");
    return absl::OkStatus();
  }

  // Checks the syntax of every ${belief.<key>} in the strings under `node`.
  absl::Status checkBindings(const YAML::Node& node, const std::string& what) {
    if (node.IsScalar()) {
      auto keys = BeliefStore::bindingsIn(node.Scalar());
      if (!keys.ok()) return r_.error(node, what + ": " + std::string(keys.status().message()));
    } else if (node.IsSequence()) {
      for (const auto& item : node) {
        if (auto s = checkBindings(item, what); !s.ok()) return s;
      }
    } else if (node.IsMap()) {
      for (const auto& entry : node) {
        if (auto s = checkBindings(entry.second, what); !s.ok()) return s;
      }
    }
    return absl::OkStatus();
  }

  yaml::Reader r_;
};

bool hasBinding(const google::protobuf::Value& value) {
  if (value.has_string_value()) return value.string_value().find("${belief.") != std::string::npos;
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
      problems->add(mission.file, line, field,
                    cat(step.behavior, " has no parameter '", key,
                        "' (its parameters: ", known.empty() ? "none" : yaml::join(known), ")"));
    } else if (!literalMatches(*schema, value)) {
      problems->add(mission.file, line, field,
                    cat(step.behavior, " parameter '", key, "' must be ",
                        schema->repeated() ? "a list of " : "a ", schema->type()));
    } else if (auto range = outOfRange(*schema, value, key)) {
      problems->add(mission.file, line, field, cat(step.behavior, " ", *range));
    }
  }
  for (const auto& p : d.parameters()) {
    if (p.required() && p.default_json().empty() && !step.parameters.fields().contains(p.name())) {
      problems->add(mission.file, step.line, cat(step.path, ".parameters.", p.name()),
                    cat(step.behavior, " needs parameter '", p.name(), "'",
                        p.description().empty() ? "" : ": " + p.description()));
    }
  }
}

void checkSteps(const MissionSpec& mission, const std::vector<MissionStep>& steps,
                const BehaviorLookup& lookup, MissionProblems* problems) {
  for (const auto& step : steps) {
    if (!step.behavior.empty()) {
      if (const v1::BehaviorDescription* d = lookup(step.behavior)) {
        checkParameters(mission, step, *d, problems);
      } else {
        problems->add(mission.file, step.line, step.path + ".behavior",
                      cat("behavior ", step.behavior, " is not hosted by any registered system",
                          mission.robot_id.empty() ? "" : " of robot '" + mission.robot_id + "'"));
      }
    }
    for (const auto& [cause, action] : step.on) {
      for (const MissionAction* a = &action; a != nullptr; a = a->then.get()) {
        checkSteps(mission, a->fallback, lookup, problems);
      }
    }
  }
}

}  // namespace

absl::StatusOr<MissionSpec> parseMission(const std::string& text, const std::string& file) {
  YAML::Node root;
  if (auto s = yaml::load(text, file, &root); !s.ok()) {
    return errors::withReason(errors::withFieldViolation(s, "", s.message()), v1::MISSION_INVALID);
  }
  absl::StatusOr<MissionSpec> mission = absl::InternalError("not parsed");
  const absl::Status guarded = server_kit::guardYamlParse(file, [&] {
    mission = MissionParser(file).parse(root);
    return absl::OkStatus();
  });
  if (!guarded.ok()) return errors::withReason(guarded, v1::MISSION_INVALID);
  if (!mission.ok()) return errors::withReason(mission.status(), v1::MISSION_INVALID);
  return mission;
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
  if (list.size() >= kMaxProblems) {
    ++left_out;
    return;
  }
  MissionProblem problem;
  problem.file = file;
  problem.line = line;
  problem.field = std::move(field);
  problem.description = line > 0 ? cat(file, ":", line, ": ", what) : cat(file, ": ", what);
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
    checkSteps(mission, *list, lookup, &problems);
  }
  return problems;
}

absl::Status checkMission(const MissionSpec& mission, const BehaviorLookup& lookup) {
  return checkMissionProblems(mission, lookup).status();
}

std::string causeName(v1::TerminationCause cause) {
  std::string name = v1::TerminationCause_Name(cause);
  const std::string prefix = "TERMINATION_CAUSE_";
  return name.rfind(prefix, 0) == 0 ? name.substr(prefix.size()) : name;
}

}  // namespace behaviorlib::coordinator
