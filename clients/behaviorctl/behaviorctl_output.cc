#include "clients/behaviorctl/behaviorctl_output.h"

#include <google/protobuf/struct.pb.h>
#include <google/protobuf/util/json_util.h>
#include <google/protobuf/util/time_util.h>
#include <yaml-cpp/yaml.h>

#include <algorithm>
#include <cstdio>
#include <string>
#include <utility>

#include "absl/status/status.h"
#include "absl/strings/ascii.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "behaviorlib/error_details.h"

namespace behaviorlib::behaviorctl {

namespace {

// An enum value's name without its type's prefix: BEHAVIOR_STATE_ACTIVE ->
// ACTIVE. UNSPECIFIED reads as "-".
std::string shortName(const std::string& name, std::string_view prefix) {
  std::string rest = name.rfind(prefix, 0) == 0 ? name.substr(prefix.size()) : name;
  return rest == "UNSPECIFIED" ? "" : rest;
}

std::string compactJson(const google::protobuf::Value& value) {
  std::string out;
  (void)google::protobuf::util::MessageToJsonString(value, &out);
  return out;
}

// At most `width` characters, with "..." at the end when cut.
std::string cut(std::string text, size_t width) {
  if (text.size() > width) text = text.substr(0, width - 3) + "...";
  return text;
}

std::string number(double value) {
  char text[32];
  std::snprintf(text, sizeof text, "%g", value);
  return text;
}

// A parameter schema in one cell: "altitude_m [0.2, 30] = 1.5".
std::string parameterSummary(const v1::ParameterSchema& p) {
  std::string out = p.name();
  if (p.has_range() && (p.range().has_min() || p.range().has_max())) {
    absl::StrAppend(&out, " [", p.range().has_min() ? number(p.range().min()) : "", ", ",
                    p.range().has_max() ? number(p.range().max()) : "", "]");
  }
  if (!p.default_json().empty()) absl::StrAppend(&out, " = ", p.default_json());
  if (p.required()) absl::StrAppend(&out, " (required)");
  return out;
}

std::string parameters(const v1::BehaviorDescription& d) {
  std::vector<std::string> names;
  for (const auto& p : d.parameters()) names.push_back(parameterSummary(p));
  return absl::StrJoin(names, "; ");
}

std::string behaviorState(v1::BehaviorState state) {
  return shortName(v1::BehaviorState_Name(state), "BEHAVIOR_STATE_");
}

void emit(YAML::Emitter& out, const google::protobuf::Value& value) {
  switch (value.kind_case()) {
    case google::protobuf::Value::kStructValue:
      out << YAML::BeginMap;
      {
        // The fields in name order, as the JSON form prints them.
        std::vector<std::string> keys;
        for (const auto& [key, unused] : value.struct_value().fields()) keys.push_back(key);
        std::sort(keys.begin(), keys.end());
        for (const auto& key : keys) {
          out << YAML::Key << key << YAML::Value;
          emit(out, value.struct_value().fields().at(key));
        }
      }
      out << YAML::EndMap;
      break;
    case google::protobuf::Value::kListValue:
      out << YAML::BeginSeq;
      for (const auto& item : value.list_value().values()) emit(out, item);
      out << YAML::EndSeq;
      break;
    case google::protobuf::Value::kNumberValue:
      out << value.number_value();
      break;
    case google::protobuf::Value::kBoolValue:
      out << value.bool_value();
      break;
    case google::protobuf::Value::kStringValue:
      out << value.string_value();
      break;
    default:
      out << YAML::Null;
  }
}

}  // namespace

absl::StatusOr<OutputFormat> parseOutputFormat(std::string_view text, OutputFormat fallback) {
  if (text.empty()) return fallback;
  if (text == "table") return OutputFormat::kTable;
  if (text == "wide") return OutputFormat::kWide;
  if (text == "json") return OutputFormat::kJson;
  if (text == "yaml") return OutputFormat::kYaml;
  return absl::InvalidArgumentError(
      absl::StrCat("-o ", std::string(text), ": the output is one of table, wide, json, yaml"));
}

std::string Table::render() const {
  // Every row as wide as the header, an empty cell as "-".
  std::vector<std::vector<std::string>> lines = {header};
  for (const auto& row : rows) {
    std::vector<std::string> cells(header.size(), "-");
    for (size_t i = 0; i < row.size() && i < cells.size(); ++i) {
      if (!row[i].empty()) cells[i] = row[i];
    }
    lines.push_back(std::move(cells));
  }
  std::vector<size_t> widths(header.size(), 0);
  for (const auto& cells : lines) {
    for (size_t i = 0; i < cells.size(); ++i) widths[i] = std::max(widths[i], cells[i].size());
  }
  std::string out;
  for (const auto& cells : lines) {
    std::string text;
    for (size_t i = 0; i < cells.size(); ++i) {
      text += cells[i];
      if (i + 1 < cells.size()) text += std::string(widths[i] - cells[i].size() + 2, ' ');
    }
    while (!text.empty() && text.back() == ' ') text.pop_back();
    out += text + "\n";
  }
  return out;
}

std::string toJson(const google::protobuf::Message& message) {
  std::string out;
  google::protobuf::util::JsonPrintOptions options;
  options.preserve_proto_field_names = true;
  (void)google::protobuf::util::MessageToJsonString(message, &out, options);
  return out;
}

std::string toYaml(const google::protobuf::Message& message) {
  google::protobuf::Value value;
  (void)google::protobuf::util::JsonStringToMessage(toJson(message), &value);
  YAML::Emitter out;
  emit(out, value);
  return std::string(out.c_str()) + "\n";
}

std::string age(const google::protobuf::Timestamp& since,
                std::chrono::system_clock::time_point now) {
  if (since.seconds() == 0 && since.nanos() == 0) return "";
  const int64_t then_s = since.seconds();
  const int64_t now_s =
      std::chrono::duration_cast<std::chrono::seconds>(now.time_since_epoch()).count();
  const int64_t s = std::max<int64_t>(0, now_s - then_s);
  if (s < 120) return absl::StrCat(s, "s");
  if (s < 120 * 60) return absl::StrCat(s / 60, "m");
  if (s < 48 * 3600) return absl::StrCat(s / 3600, "h");
  return absl::StrCat(s / 86400, "d");
}

Table fleetBehaviorsTable(const v1::ListFleetBehaviorsResponse& response, bool wide) {
  Table table{{"ROBOT", "SYSTEM", "BEHAVIOR", "STATE", "ACTIVATION"}, {}};
  if (wide) {
    for (const char* column : {"KIND", "ADDRESS", "PARAMETERS"}) table.header.push_back(column);
  }
  for (const auto& b : response.behaviors()) {
    // A behavior's state is known while its system is up; otherwise the
    // system's state says why not.
    std::string state = behaviorState(b.description().state());
    if (state.empty()) {
      state = "system " + shortName(v1::SystemState_Name(b.system_state()), "SYSTEM_STATE_");
    }
    std::vector<std::string> row = {b.robot_id(), b.system(), b.description().name(), state,
                                    b.activation_id()};
    if (wide) {
      row.push_back(shortName(v1::BehaviorKind_Name(b.description().kind()), "BEHAVIOR_KIND_"));
      row.push_back(b.address());
      row.push_back(parameters(b.description()));
    }
    table.rows.push_back(std::move(row));
  }
  return table;
}

Table systemBehaviorsTable(const v1::ListBehaviorsResponse& response, bool wide) {
  Table table{{"ROBOT", "SYSTEM", "BEHAVIOR", "STATE", "KIND"}, {}};
  if (wide) {
    for (const char* column : {"FREQUENCY_HZ", "PARAMETERS"}) table.header.push_back(column);
  }
  for (const auto& d : response.behaviors()) {
    std::vector<std::string> row = {response.robot_id(), response.system(), d.name(),
                                    behaviorState(d.state()),
                                    shortName(v1::BehaviorKind_Name(d.kind()), "BEHAVIOR_KIND_")};
    if (wide) {
      row.push_back(d.frequency_hz() > 0 ? number(d.frequency_hz()) : "");
      row.push_back(parameters(d));
    }
    table.rows.push_back(std::move(row));
  }
  return table;
}

Table activationTable(const std::string& behavior, const v1::CheckActivationResponse& response,
                      bool wide) {
  Table table{{"BEHAVIOR", "STATE", "ACTIVATION", "ACTIVE_S"}, {}};
  if (wide) table.header.push_back("PARAMETERS");
  std::vector<std::string> row = {
      behavior, behaviorState(response.state()), response.activation_id(),
      response.active()
          ? number(static_cast<double>(google::protobuf::util::TimeUtil::DurationToMilliseconds(
                       response.active_duration())) /
                   1e3)
          : ""};
  if (wide) {
    google::protobuf::Value parameters;
    *parameters.mutable_struct_value() = response.parameters();
    row.push_back(response.parameters().fields().empty() ? "" : compactJson(parameters));
  }
  table.rows.push_back(std::move(row));
  return table;
}

Table systemsTable(const v1::ListSystemsResponse& response, bool wide,
                   std::chrono::system_clock::time_point now) {
  Table table{{"ROBOT", "SYSTEM", "STATE", "ADDRESS", "BEHAVIORS", "AGE"}, {}};
  if (wide) {
    for (const char* column : {"SOURCE", "INCARNATION", "LAST_EVENT_SEQ", "MESSAGE"}) {
      table.header.push_back(column);
    }
  }
  for (const auto& s : response.systems()) {
    std::vector<std::string> row = {s.robot_id(),
                                    s.system(),
                                    shortName(v1::SystemState_Name(s.state()), "SYSTEM_STATE_"),
                                    s.address(),
                                    absl::StrCat(s.behaviors_size()),
                                    age(s.state_time(), now)};
    if (wide) {
      row.push_back(shortName(v1::SystemSource_Name(s.source()), "SYSTEM_SOURCE_"));
      row.push_back(s.incarnation());
      row.push_back(absl::StrCat(s.last_event_seq()));
      row.push_back(s.state_message());
    }
    table.rows.push_back(std::move(row));
  }
  return table;
}

Table missionsTable(const v1::ListMissionsResponse& response, bool wide,
                    std::chrono::system_clock::time_point now) {
  Table table{{"MISSION", "NAME", "ROBOT", "STATE", "STEP", "AGE"}, {}};
  if (wide) {
    for (const char* column : {"FILE", "MESSAGE"}) table.header.push_back(column);
  }
  for (const auto& m : response.missions()) {
    // The step the mission is at, or ended on.
    std::string step;
    if (m.steps_size() > 0) {
      const auto& last = m.steps(m.steps_size() - 1);
      step =
          absl::StrCat(last.name().empty() ? last.behavior() : last.name(), " ",
                       shortName(v1::MissionStepState_Name(last.state()), "MISSION_STEP_STATE_"));
    }
    std::string state = shortName(v1::MissionState_Name(m.state()), "MISSION_STATE_");
    if (m.in_safety_steps()) state += " (safety steps)";
    // A fleet mission's robots, its own first.
    const std::string robots =
        m.robot_ids_size() > 1 ? absl::StrJoin(m.robot_ids(), ",") : m.robot_id();
    std::vector<std::string> row = {m.mission_id(), m.name(), robots,
                                    state,          step,     age(m.start_time(), now)};
    if (wide) {
      row.push_back(m.file());
      row.push_back(m.message());
    }
    table.rows.push_back(std::move(row));
  }
  return table;
}

std::string missionCheckText(const v1::CheckMissionResponse& response, bool wide) {
  std::string out;
  for (const auto& problem : response.problems())
    absl::StrAppend(&out, problem.description(), "\n");
  const size_t count = response.problems_size() + response.problems_left_out();
  if (response.problems_left_out() > 0) {
    absl::StrAppend(&out, "... and ", response.problems_left_out(), " more\n");
  }
  const std::string what =
      absl::StrCat("mission '", response.name(), "' for robot '", response.robot_id(), "'");
  if (count == 0) {
    absl::StrAppend(&out, what, ": no problem found\n");
  } else {
    absl::StrAppend(&out, what, ": ", count, count == 1 ? " problem" : " problems", "\n");
  }
  if (response.plans().empty()) return out;
  Table table{{"NODE", "STEP", "LINE", "PLAN"}, {}};
  std::string reasons;
  for (const auto& plan : response.plans()) {
    std::vector<std::string> steps;
    for (const auto& step : plan.plan()) {
      const std::string kind = shortName(v1::ActivationPlanStep::Kind_Name(step.kind()), "KIND_");
      // The situation checks only in the wide form.
      if (wide || step.kind() != v1::ActivationPlanStep::KIND_CHECK_SITUATION) {
        steps.push_back(absl::StrCat(absl::AsciiStrToLower(kind), " ", step.behavior()));
      }
      if (wide) {
        absl::StrAppend(&reasons, plan.node(), ": ", absl::AsciiStrToLower(kind), " ",
                        step.behavior(), ": ", step.reason(), "\n");
      }
    }
    table.rows.push_back(
        {plan.node(), plan.name().empty() ? plan.behavior() : plan.name(),
         std::to_string(plan.line()),
         plan.no_plan().empty() ? absl::StrJoin(steps, ", ") : "no plan: " + plan.no_plan()});
  }
  absl::StrAppend(&out, "\n", table.render(), reasons.empty() ? "" : "\n", reasons);
  return out;
}

Table beliefsTable(const v1::ListBeliefsResponse& response, bool wide,
                   std::chrono::system_clock::time_point now) {
  Table table{{"KEY", "VALUE", "VERSION", "WRITER", "AGE"}, {}};
  if (wide) {
    for (const char* column : {"TYPE", "AUTHENTICATED_WRITER"}) table.header.push_back(column);
  }
  for (const auto& b : response.beliefs()) {
    const std::string value = compactJson(b.value());
    std::vector<std::string> row = {b.key(), wide ? value : cut(value, 40),
                                    absl::StrCat(b.version()), b.writer(),
                                    age(b.update_time(), now)};
    if (wide) {
      row.push_back(b.type());
      row.push_back(b.authenticated_writer());
    }
    table.rows.push_back(std::move(row));
  }
  return table;
}

std::string describeError(const grpc::Status& status) {
  // gRPC's codes are absl's, number for number.
  std::string out = absl::StrCat(
      "behaviorctl: ", absl::StatusCodeToString(static_cast<absl::StatusCode>(status.error_code())),
      ": ", status.error_message(), "\n");
  if (auto info = errors::errorInfo(status);
      info && !info->reason().empty() && info->reason() != "ERROR_REASON_UNSPECIFIED") {
    absl::StrAppend(&out, "  reason: ", info->reason(), "\n");
  }
  if (auto bad = errors::badRequest(status)) {
    for (const auto& violation : bad->field_violations()) {
      absl::StrAppend(&out, "  field ", violation.field(), ": ", violation.description(), "\n");
    }
  }
  return out;
}

}  // namespace behaviorlib::behaviorctl
