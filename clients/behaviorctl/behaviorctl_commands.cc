#include "clients/behaviorctl/behaviorctl_commands.h"

#include <google/protobuf/util/json_util.h>
#include <grpcpp/grpcpp.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <fstream>
#include <iostream>
#include <sstream>
#include <string>
#include <utility>

#include "behaviorlib/server_kit/transport_security.h"
#include "behaviorlib/v1/behavior.grpc.pb.h"
#include "behaviorlib/v1/coordinator.grpc.pb.h"
#include "clients/behaviorctl/behaviorctl_output.h"
#include "coordinator/registry/health_check.h"

namespace behaviorlib::behaviorctl {

namespace {

int usageError() {
  std::fputs("behaviorctl: unknown command; run with --help for the list\n", stderr);
  return 2;
}

int fail(const grpc::Status& status) {
  std::fputs(describeError(status).c_str(), stderr);
  return 1;
}

// The format of a command's reply: a table for the listing commands unless
// -o says otherwise; JSON (or YAML) for the others, and for a listing with
// -o json or -o yaml.
OutputFormat formatOf(const CtlOptions& c, bool listing) {
  const OutputFormat format =
      parseOutputFormat(c.output, listing ? OutputFormat::kTable : OutputFormat::kJson)
          .value_or(OutputFormat::kJson);  // runCtl refused a bad -o already
  if (!listing && (format == OutputFormat::kTable || format == OutputFormat::kWide)) {
    return OutputFormat::kJson;
  }
  return format;
}

// A reply in the machine form -o asks for (JSON unless yaml).
void printMessage(const CtlOptions& c, const google::protobuf::Message& message) {
  if (formatOf(c, false) == OutputFormat::kYaml) {
    std::cout << toYaml(message) << "---" << std::endl;
  } else {
    std::cout << toJson(message) << std::endl;
  }
}

// A listing's reply: its table (wide with -o wide), or the machine form.
template <class Response, class MakeTable>
void printListing(const CtlOptions& c, const Response& response, MakeTable make_table) {
  const OutputFormat format = formatOf(c, true);
  if (format == OutputFormat::kTable || format == OutputFormat::kWide) {
    const Table table = make_table(response, format == OutputFormat::kWide);
    if (table.rows.empty()) {
      std::fputs("behaviorctl: nothing found\n", stderr);  // as kubectl: no header
    } else {
      std::cout << table.render() << std::flush;
    }
  } else {
    printMessage(c, response);
  }
}

// One line per change of a mission's step records, on stderr (the last
// status is printed as JSON on stdout by the caller). `seen` holds each
// record's state and cause as last printed: a fleet mission's branches change
// earlier records too.
void printProgress(const v1::MissionStatus& status, std::vector<std::string>* seen) {
  const int n = status.steps_size();
  seen->resize(std::max<size_t>(seen->size(), static_cast<size_t>(n)));
  for (int i = 0; i < n; ++i) {
    const auto& step = status.steps(i);
    std::string cause;
    if (step.cause() != v1::TERMINATION_CAUSE_UNSPECIFIED) {
      cause = v1::TerminationCause_Name(step.cause());
    }
    const std::string state = v1::MissionStepState_Name(step.state());
    if ((*seen)[i] == state + cause) continue;
    (*seen)[i] = state + cause;
    std::string what = step.behavior();
    if (!step.call().empty()) what = "call " + step.call();
    if (!step.parallel().empty()) what = "parallel, " + step.parallel();
    if (!step.wait_for().empty()) what = "wait for " + step.wait_for();
    if (status.robot_ids_size() > 1) what += " on " + step.robot_id();
    std::fprintf(stderr, "mission %s: %-16s %-36s attempt %d  %s%s%s\n",
                 status.mission_id().c_str(), step.name().c_str(), what.c_str(), step.attempt(),
                 state.c_str(), cause.empty() ? "" : " ", cause.c_str());
  }
  if (status.has_end_time() || status.state() == v1::MISSION_STATE_SUCCEEDED) {
    std::fprintf(stderr, "mission %s: %s%s%s\n", status.mission_id().c_str(),
                 v1::MissionState_Name(status.state()).c_str(),
                 status.message().empty() ? "" : ": ", status.message().c_str());
  }
}

// Follows a mission until it ends; 0 when it SUCCEEDED.
int followMission(const CtlOptions& c, v1::Coordinator::Stub& stub, const std::string& mission_id) {
  grpc::ClientContext context;
  v1::WatchMissionRequest request;
  request.set_mission_id(mission_id);
  auto reader = stub.WatchMission(&context, request);
  v1::WatchMissionResponse message;
  v1::MissionStatus last;
  std::vector<std::string> printed;
  while (reader->Read(&message)) {
    last = message.status();
    printProgress(last, &printed);
  }
  auto s = reader->Finish();
  if (!s.ok()) return fail(s);
  printMessage(c, last);
  return last.state() == v1::MISSION_STATE_SUCCEEDED ? 0 : 1;
}

// One unary call under the command's deadline: `call(context, response)`
// makes it; `print` shows the response. 1 when the call fails.
template <class Response, class Call, class Print>
int unary(const CtlOptions&, Call call, Print print) {
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(10));
  Response response;
  if (grpc::Status s = call(&context, &response); !s.ok()) return fail(s);
  print(response);
  return 0;
}

template <class Response, class Call>
int unary(const CtlOptions& c, Call call) {
  return unary<Response>(c, call, [&](const Response& r) { printMessage(c, r); });
}

// Every page of a List call (AIP-158) as one reply, printed once: each
// page's repeated fields appended to the reply, next_page_token cleared.
// `call(context, request, page)` makes one call; each has the deadline of
// unary().
template <class Response, class Request, class Call, class Print>
int listAll(const CtlOptions&, Request request, Call call, Print print) {
  Response all;
  for (;;) {
    grpc::ClientContext context;
    context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(10));
    Response page;
    if (grpc::Status s = call(&context, request, &page); !s.ok()) return fail(s);
    std::string next = page.next_page_token();
    page.clear_next_page_token();
    all.MergeFrom(page);
    if (next.empty()) break;
    request.set_page_token(std::move(next));
  }
  print(all);
  return 0;
}

template <class Response, class Request, class Call>
int listAll(const CtlOptions& c, Request request, Call call) {
  return listAll<Response>(c, std::move(request), call,
                           [&](const Response& r) { printMessage(c, r); });
}

// Prints a stream's messages as they come, until `last` says one was the
// last (0), the stream ends (0), or it fails (1). --timeout-s bounds it.
template <class Message, class Open, class Last>
int watch(const CtlOptions& c, Open open, Last last) {
  grpc::ClientContext context;
  if (c.timeout_s > 0) {
    context.set_deadline(std::chrono::system_clock::now() +
                         std::chrono::milliseconds(static_cast<int64_t>(c.timeout_s * 1e3)));
  }
  auto reader = open(&context);
  Message message;
  while (reader->Read(&message)) {
    printMessage(c, message);
    if (last(message)) {
      context.TryCancel();
      reader->Finish();
      return 0;
    }
  }
  if (grpc::Status s = reader->Finish(); !s.ok()) return fail(s);
  return 0;
}

// Parses args[index] (when given) as JSON into `out`; false after saying why.
bool parseJson(const CtlOptions& c, size_t index, google::protobuf::Message* out,
               const char* what) {
  if (c.args.size() <= index) return true;
  if (auto status = google::protobuf::util::JsonStringToMessage(c.args[index], out); !status.ok()) {
    std::fprintf(stderr, "behaviorctl: %s: %s\n", what, std::string(status.message()).c_str());
    return false;
  }
  return true;
}

constexpr const char* kNotAnObject = "parameters are not a JSON object";

int beliefCommand(v1::Coordinator::Stub& stub, const CtlOptions& c) {
  // belief list [PREFIX] | get KEY | set KEY JSON | delete KEY
  const std::string verb = c.args.size() > 1 ? c.args[1] : "";
  const std::string key = c.args.size() > 2 ? c.args[2] : "";
  if (verb == "list") {
    v1::ListBeliefsRequest request;
    request.set_prefix(key);
    return listAll<v1::ListBeliefsResponse>(
        c, request,
        [&](auto* context, auto& q, auto* r) { return stub.ListBeliefs(context, q, r); },
        [&](const v1::ListBeliefsResponse& r) {
          printListing(c, r, [](const auto& l, bool wide) {
            return beliefsTable(l, wide, std::chrono::system_clock::now());
          });
        });
  }
  if (verb == "get" && !key.empty()) {
    v1::ReadBeliefRequest request;
    request.set_key(key);
    return unary<v1::ReadBeliefResponse>(
        c, [&](auto* context, auto* r) { return stub.ReadBelief(context, request, r); },
        [&](const v1::ReadBeliefResponse& r) { printMessage(c, r.belief()); });
  }
  if (verb == "set" && c.args.size() > 3) {
    v1::WriteBeliefRequest request;
    request.set_key(key);
    request.set_writer("operator");
    if (!parseJson(c, 3, request.mutable_value(),
                   "the value must be JSON (a string needs quotes: '\"yes\"')")) {
      return 2;
    }
    return unary<v1::WriteBeliefResponse>(
        c, [&](auto* context, auto* r) { return stub.WriteBelief(context, request, r); },
        [&](const v1::WriteBeliefResponse& r) { printMessage(c, r.belief()); });
  }
  if (verb == "delete" && !key.empty()) {
    v1::DeleteBeliefRequest request;
    request.set_key(key);
    request.set_writer("operator");
    return unary<v1::DeleteBeliefResponse>(
        c, [&](auto* context, auto* r) { return stub.DeleteBelief(context, request, r); },
        [](const v1::DeleteBeliefResponse&) {});
  }
  std::fputs(
      "usage: behaviorctl --coordinator ADDR belief list [PREFIX] | get KEY | set KEY JSON | "
      "delete KEY\n",
      stderr);
  return 2;
}

// A mission file's text (sent as text: the coordinator need not see the
// file); false, having said why, when it cannot be read.
bool readMissionFile(const std::string& path, std::string* text) {
  std::ifstream in(path);
  if (!in) {
    std::fprintf(stderr, "behaviorctl: cannot read mission file %s\n", path.c_str());
    return false;
  }
  std::stringstream read;
  read << in.rdbuf();
  *text = read.str();
  return true;
}

int missionCommand(v1::Coordinator::Stub& stub, const CtlOptions& c) {
  const std::string verb = c.args.size() > 1 ? c.args[1] : "";
  const std::string arg = c.args.size() > 2 ? c.args[2] : "";
  auto printStatus = [&](const auto& r) { printMessage(c, r.status()); };
  if (verb == "run" && !arg.empty()) {
    std::string text;
    if (!readMissionFile(arg, &text)) return 2;
    v1::StartMissionRequest request;
    request.set_text(text);
    request.set_source_name(arg);
    request.set_robot_id(c.robot);
    request.set_mission_id(c.mission_id);
    std::string started;
    const int code = unary<v1::StartMissionResponse>(
        c, [&](auto* context, auto* r) { return stub.StartMission(context, request, r); },
        [&](const v1::StartMissionResponse& r) {
          if (c.detach) printMessage(c, r.status());
          started = r.status().mission_id();
        });
    if (code != 0 || c.detach) return code;
    return followMission(c, stub, started);
  }
  if (verb == "check" && !arg.empty()) {
    std::string text;
    if (!readMissionFile(arg, &text)) return 2;
    v1::CheckMissionRequest request;
    request.set_text(text);
    request.set_source_name(arg);
    request.set_robot_id(c.robot);
    bool problems = false;
    const int code = unary<v1::CheckMissionResponse>(
        c, [&](auto* context, auto* r) { return stub.CheckMission(context, request, r); },
        [&](const v1::CheckMissionResponse& r) {
          problems = r.problems_size() > 0 || r.problems_left_out() > 0;
          const OutputFormat format = formatOf(c, true);
          if (format == OutputFormat::kTable || format == OutputFormat::kWide) {
            std::cout << missionCheckText(r, format == OutputFormat::kWide);
          } else {
            printMessage(c, r);
          }
        });
    // As a linter: 1 when the mission has problems.
    return code != 0 ? code : problems ? 1 : 0;
  }
  if (verb == "watch" && !arg.empty()) return followMission(c, stub, arg);
  if (verb == "status" && !arg.empty()) {
    v1::GetMissionRequest request;
    request.set_mission_id(arg);
    return unary<v1::GetMissionResponse>(
        c, [&](auto* context, auto* r) { return stub.GetMission(context, request, r); },
        printStatus);
  }
  if (verb == "list") {
    return listAll<v1::ListMissionsResponse>(
        c, v1::ListMissionsRequest(),
        [&](auto* context, auto& q, auto* r) { return stub.ListMissions(context, q, r); },
        [&](const v1::ListMissionsResponse& r) {
          printListing(c, r, [](const auto& l, bool wide) {
            return missionsTable(l, wide, std::chrono::system_clock::now());
          });
        });
  }
  if ((verb == "pause" || verb == "resume" || verb == "abort") && !arg.empty()) {
    v1::MissionControlRequest request;
    request.set_mission_id(arg);
    request.set_reason(c.args.size() > 3 ? c.args[3] : "requested with behaviorctl");
    return unary<v1::MissionControlResponse>(
        c,
        [&](auto* context, auto* r) {
          return verb == "pause"    ? stub.PauseMission(context, request, r)
                 : verb == "resume" ? stub.ResumeMission(context, request, r)
                                    : stub.AbortMission(context, request, r);
        },
        printStatus);
  }
  std::fputs(
      "usage: behaviorctl --coordinator ADDR mission run FILE [--robot ID] [--mission-id ID] "
      "[--detach] | check FILE [--robot ID] | status ID | list | watch ID | pause ID | resume ID | "
      "abort ID [REASON]\n",
      stderr);
  return 2;
}

// The commands through the coordinator (behaviorlib.v1.Coordinator).
int runCoordinator(const CtlOptions& c) {
  auto stub = v1::Coordinator::NewStub(behaviorlib::server_kit::makeChannel(c.coordinator));
  const std::string& command = c.args[0];
  const std::string behavior = c.args.size() > 1 ? c.args[1] : "";
  const bool needs_robot =
      command == "status" || command == "activate" || command == "deactivate" ||
      command == "situation" || command == "pause" || command == "resume" || command == "modify" ||
      command == "activation" || command == "emergency-land" || command == "kill";
  if (needs_robot && c.robot.empty()) {
    std::fprintf(stderr, "behaviorctl: '%s' through the coordinator needs --robot ID\n",
                 command.c_str());
    return 2;
  }
  if (command == "list" || command == "status") {
    v1::ListFleetBehaviorsRequest request;
    request.set_robot_id(c.robot);
    if (command == "status") request.set_behavior(behavior);
    bool missing = false;
    const int code = listAll<v1::ListFleetBehaviorsResponse>(
        c, request,
        [&](auto* context, auto& q, auto* r) { return stub->ListBehaviors(context, q, r); },
        [&](const v1::ListFleetBehaviorsResponse& r) {
          missing = command == "status" && r.behaviors().empty();
          if (!missing) printListing(c, r, fleetBehaviorsTable);
        });
    if (missing) {
      std::fprintf(stderr, "behaviorctl: robot %s has no behavior '%s'\n", c.robot.c_str(),
                   behavior.c_str());
      return 1;
    }
    return code;
  }
  if (command == "systems") {
    v1::ListSystemsRequest request;
    request.set_robot_id(c.robot);
    return listAll<v1::ListSystemsResponse>(
        c, request,
        [&](auto* context, auto& q, auto* r) { return stub->ListSystems(context, q, r); },
        [&](const v1::ListSystemsResponse& r) {
          printListing(c, r, [](const auto& l, bool wide) {
            return systemsTable(l, wide, std::chrono::system_clock::now());
          });
        });
  }
  if (command == "activate") {
    v1::ActivateFleetBehaviorRequest request;
    request.set_robot_id(c.robot);
    request.set_behavior(behavior);
    request.set_request_id(c.request_id);
    request.set_dry_run(c.dry_run);
    request.set_skip_plan(c.skip_plan);
    if (!parseJson(c, 2, request.mutable_parameters(), kNotAnObject)) return 2;
    return unary<v1::ActivateFleetBehaviorResponse>(
        c, [&](auto* context, auto* r) { return stub->ActivateBehavior(context, request, r); });
  }
  if (command == "deactivate") {
    v1::DeactivateFleetBehaviorRequest request;
    request.set_robot_id(c.robot);
    request.set_behavior(behavior);
    if (c.args.size() > 2) request.set_activation_id(c.args[2]);
    return unary<v1::DeactivateFleetBehaviorResponse>(
        c, [&](auto* context, auto* r) { return stub->DeactivateBehavior(context, request, r); });
  }
  if (command == "situation") {
    v1::CheckFleetBehaviorSituationRequest request;
    request.set_robot_id(c.robot);
    request.set_behavior(behavior);
    return unary<v1::CheckFleetBehaviorSituationResponse>(c, [&](auto* context, auto* r) {
      return stub->CheckBehaviorSituation(context, request, r);
    });
  }
  if (command == "watch") {
    v1::WatchFleetEventsRequest request;
    request.set_since_seq(c.since_seq);
    request.set_incarnation(c.incarnation);
    if (!c.robot.empty()) request.add_robot_ids(c.robot);
    if (!c.behavior_filter.empty()) request.add_behaviors(c.behavior_filter);
    return watch<v1::WatchFleetEventsResponse>(
        c, [&](auto* context) { return stub->WatchEvents(context, request); },
        [&](const v1::WatchFleetEventsResponse& m) {
          const auto& e = m.event().behavior_event();
          return !c.until_finished.empty() && e.has_finished() && e.behavior() == c.until_finished;
        });
  }
  if (command == "belief") return beliefCommand(*stub, c);
  if (command == "mission") return missionCommand(*stub, c);
  if (command == "emergency-land" || command == "kill") {
    v1::SafetyActionRequest request;
    request.set_robot_id(c.robot);
    request.set_confirm(c.confirm);
    request.set_reason(c.args.size() > 1 ? c.args[1] : "requested with behaviorctl");
    return unary<v1::SafetyActionResponse>(c, [&](auto* context, auto* r) {
      return command == "kill" ? stub->Kill(context, request, r)
                               : stub->EmergencyLand(context, request, r);
    });
  }
  if (command == "pause") {
    v1::PauseFleetBehaviorRequest request;
    request.set_robot_id(c.robot);
    request.set_behavior(behavior);
    if (c.args.size() > 2) request.set_activation_id(c.args[2]);
    return unary<v1::PauseFleetBehaviorResponse>(
        c, [&](auto* context, auto* r) { return stub->PauseFleetBehavior(context, request, r); });
  }
  if (command == "resume") {
    v1::ResumeFleetBehaviorRequest request;
    request.set_robot_id(c.robot);
    request.set_behavior(behavior);
    if (c.args.size() > 2) request.set_activation_id(c.args[2]);
    return unary<v1::ResumeFleetBehaviorResponse>(
        c, [&](auto* context, auto* r) { return stub->ResumeFleetBehavior(context, request, r); });
  }
  if (command == "modify") {
    v1::ModifyFleetBehaviorRequest request;
    request.set_robot_id(c.robot);
    request.set_behavior(behavior);
    if (!parseJson(c, 2, request.mutable_parameters(), kNotAnObject)) return 2;
    return unary<v1::ModifyFleetBehaviorResponse>(
        c, [&](auto* context, auto* r) { return stub->ModifyFleetBehavior(context, request, r); });
  }
  if (command == "activation") {
    v1::CheckFleetBehaviorActivationRequest request;
    request.set_robot_id(c.robot);
    request.set_behavior(behavior);
    return unary<v1::CheckFleetBehaviorActivationResponse>(c, [&](auto* context, auto* r) {
      return stub->CheckFleetBehaviorActivation(context, request, r);
    });
  }
  return usageError();
}

// The commands to one behavior system (behaviorlib.v1.BehaviorSystem).
int runSystem(const CtlOptions& c) {
  auto stub = v1::BehaviorSystem::NewStub(behaviorlib::server_kit::makeChannel(c.target));
  const std::string& command = c.args[0];
  const std::string behavior = c.args.size() > 1 ? c.args[1] : "";
  if (command == "list") {
    return listAll<v1::ListBehaviorsResponse>(
        c, v1::ListBehaviorsRequest(),
        [&](auto* context, auto& q, auto* r) { return stub->ListBehaviors(context, q, r); },
        [&](const v1::ListBehaviorsResponse& r) { printListing(c, r, systemBehaviorsTable); });
  }
  if (command == "activate") {
    v1::ActivateBehaviorRequest request;
    request.set_behavior(behavior);
    request.set_request_id(c.request_id);
    if (!parseJson(c, 2, request.mutable_parameters(), kNotAnObject)) return 2;
    return unary<v1::ActivateResponse>(
        c, [&](auto* context, auto* r) { return stub->ActivateBehavior(context, request, r); });
  }
  if (command == "deactivate") {
    v1::DeactivateBehaviorRequest request;
    request.set_behavior(behavior);
    if (c.args.size() > 2) request.set_activation_id(c.args[2]);
    return unary<v1::DeactivateResponse>(
        c, [&](auto* context, auto* r) { return stub->DeactivateBehavior(context, request, r); });
  }
  if (command == "pause") {
    v1::PauseBehaviorRequest request;
    request.set_behavior(behavior);
    if (c.args.size() > 2) request.set_activation_id(c.args[2]);
    return unary<v1::PauseResponse>(
        c, [&](auto* context, auto* r) { return stub->PauseBehavior(context, request, r); });
  }
  if (command == "resume") {
    v1::ResumeBehaviorRequest request;
    request.set_behavior(behavior);
    if (c.args.size() > 2) request.set_activation_id(c.args[2]);
    return unary<v1::ResumeResponse>(
        c, [&](auto* context, auto* r) { return stub->ResumeBehavior(context, request, r); });
  }
  if (command == "modify") {
    v1::ModifyBehaviorRequest request;
    request.set_behavior(behavior);
    if (!parseJson(c, 2, request.mutable_parameters(), kNotAnObject)) return 2;
    return unary<v1::ModifyResponse>(
        c, [&](auto* context, auto* r) { return stub->ModifyBehavior(context, request, r); });
  }
  if (command == "status") {
    v1::CheckBehaviorActivationRequest request;
    request.set_behavior(behavior);
    return unary<v1::CheckActivationResponse>(
        c,
        [&](auto* context, auto* r) { return stub->CheckBehaviorActivation(context, request, r); },
        [&](const v1::CheckActivationResponse& r) {
          printListing(
              c, r, [&](const auto& a, bool wide) { return activationTable(behavior, a, wide); });
        });
  }
  if (command == "situation") {
    v1::CheckBehaviorSituationRequest request;
    request.set_behavior(behavior);
    return unary<v1::CheckSituationResponse>(c, [&](auto* context, auto* r) {
      return stub->CheckBehaviorSituation(context, request, r);
    });
  }
  if (command == "watch") {
    v1::WatchEventsRequest request;
    request.set_since_seq(c.since_seq);
    request.set_incarnation(c.incarnation);
    return watch<v1::WatchEventsResponse>(
        c, [&](auto* context) { return stub->WatchEvents(context, request); },
        [&](const v1::WatchEventsResponse& m) {
          return !c.until_finished.empty() && m.event().has_finished() &&
                 m.event().behavior() == c.until_finished;
        });
  }
  return usageError();
}

}  // namespace

int runHealth(const CtlOptions& c) {
  // The standard gRPC health service, for docker-compose health checks.
  const std::string address = c.coordinator.empty() ? c.target : c.coordinator;
  auto result = behaviorlib::coordinator::checkHealth(
      behaviorlib::server_kit::makeChannel(address), "",
      std::chrono::milliseconds(static_cast<int64_t>((c.timeout_s > 0 ? c.timeout_s : 3.0) * 1e3)));
  if (!result.serving) {
    std::fprintf(stderr, "behaviorctl: %s is not serving: %s\n", address.c_str(),
                 result.detail.c_str());
    return 1;
  }
  std::cout << "{\"status\":\"SERVING\"}" << std::endl;
  return 0;
}

int runCtl(const CtlOptions& options) {
  if (!options.args.empty() && (options.args[0] == "record" || options.args[0] == "replay")) {
    if (absl::Status s = server_kit::checkProcessTransport(); !s.ok()) {
      std::fprintf(stderr, "behaviorctl: %s\n", std::string(s.message()).c_str());
      return 2;
    }
    return options.args[0] == "record" ? runRecord(options) : runReplay(options);
  }
  if (options.args.empty() || options.target.empty() == options.coordinator.empty()) {
    std::fputs(
        "behaviorctl: give a command and one of --target (a behavior system) or --coordinator "
        "(the fleet); run with --help for the list\n",
        stderr);
    return 2;
  }
  if (absl::Status s = server_kit::checkProcessTransport(); !s.ok()) {
    std::fprintf(stderr, "behaviorctl: %s\n", std::string(s.message()).c_str());
    return 2;
  }
  if (auto format = parseOutputFormat(options.output, OutputFormat::kJson); !format.ok()) {
    std::fprintf(stderr, "behaviorctl: %s\n", std::string(format.status().message()).c_str());
    return 2;
  }
  if (options.args[0] == "health") return runHealth(options);
  return options.coordinator.empty() ? runSystem(options) : runCoordinator(options);
}

}  // namespace behaviorlib::behaviorctl
