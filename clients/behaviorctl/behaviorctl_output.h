#pragma once

// behaviorctl's output forms (-o): the listing commands (list, systems,
// status, mission list, belief list) print an aligned table by default, as
// kubectl does; `-o wide` adds columns (the parameter schemas among them),
// `-o json` prints the reply as one JSON object (the machine form, what
// every other command prints), `-o yaml` the same as YAML (yaml-cpp).
// Errors print the gRPC code and message, then the reason and each field
// the server named (google.rpc ErrorInfo and BadRequest).

#include <grpcpp/grpcpp.h>

#include <chrono>
#include <string>
#include <string_view>
#include <vector>

#include "absl/status/statusor.h"
#include "behaviorlib/v1/behavior.pb.h"
#include "behaviorlib/v1/coordinator.pb.h"
#include "behaviorlib/v1/mission.pb.h"

namespace behaviorlib::behaviorctl {

enum class OutputFormat { kTable, kWide, kJson, kYaml };

/// "" (the command's default), "table", "wide", "json" or "yaml";
/// INVALID_ARGUMENT names the accepted ones otherwise.
absl::StatusOr<OutputFormat> parseOutputFormat(std::string_view text, OutputFormat fallback);

/// Rows under a header; render() aligns the columns (two spaces between
/// them, no trailing spaces) and writes "-" for an empty cell.
struct Table {
  std::vector<std::string> header;
  std::vector<std::vector<std::string>> rows;
  std::string render() const;
};

/// The message as one line of JSON (proto field names), or as YAML.
std::string toJson(const google::protobuf::Message& message);
std::string toYaml(const google::protobuf::Message& message);

/// kubectl's age: "45s", "12m", "5h", "3d" from `since` to `now`; "-" when
/// `since` is unset.
std::string age(const google::protobuf::Timestamp& since,
                std::chrono::system_clock::time_point now);

/// The tables of the listing commands; `wide` adds columns. `now` dates the
/// ages.
Table fleetBehaviorsTable(const v1::ListFleetBehaviorsResponse& response, bool wide);
Table systemBehaviorsTable(const v1::ListBehaviorsResponse& response, bool wide);
Table activationTable(const std::string& behavior, const v1::CheckActivationResponse& response,
                      bool wide);
Table systemsTable(const v1::ListSystemsResponse& response, bool wide,
                   std::chrono::system_clock::time_point now);
Table missionsTable(const v1::ListMissionsResponse& response, bool wide,
                    std::chrono::system_clock::time_point now);
Table beliefsTable(const v1::ListBeliefsResponse& response, bool wide,
                   std::chrono::system_clock::time_point now);

/// A mission check as the user reads it: each problem on a line ("file:line:
/// what"), a summary line, then a table of each step's plan (NODE, STEP,
/// LINE, PLAN: "deactivate HOVER, activate TAKE_OFF", or why there is none).
/// `wide` adds the situation checks to PLAN and each plan step's reason, one
/// a line under the table.
std::string missionCheckText(const v1::CheckMissionResponse& response, bool wide);

/// A failed call as the user reads it:
///   behaviorctl: INVALID_ARGUMENT: <message>
///     reason: PARAMETER_OUT_OF_RANGE
///     field parameters.altitude_m: <what is wrong with it>
std::string describeError(const grpc::Status& status);

}  // namespace behaviorlib::behaviorctl
