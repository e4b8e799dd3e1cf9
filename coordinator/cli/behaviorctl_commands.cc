#include "coordinator/cli/behaviorctl_commands.h"

#include <google/protobuf/util/json_util.h>
#include <grpcpp/grpcpp.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <fstream>
#include <iostream>
#include <sstream>

#include "behaviorlib/v1/behavior.grpc.pb.h"
#include "behaviorlib/v1/coordinator.grpc.pb.h"
#include "coordinator/service/health_check.h"

namespace behaviorlib::coordinator {

namespace {

int usageError() {
  std::fputs("behaviorctl: unknown command; run with --help for the list\n", stderr);
  return 2;
}

std::string toJson(const google::protobuf::Message& message) {
  std::string out;
  google::protobuf::util::JsonPrintOptions options;
  options.preserve_proto_field_names = true;
  (void)google::protobuf::util::MessageToJsonString(message, &out, options);
  return out;
}

int fail(const grpc::Status& status) {
  std::fprintf(stderr, "behaviorctl: %d %s\n", static_cast<int>(status.error_code()),
               status.error_message().c_str());
  return 1;
}

// One line per change of a mission's status, on stderr (the last status is
// printed as JSON on stdout by the caller).
void printProgress(const v1::MissionStatus& status, int* printed_steps) {
  const int n = status.steps_size();
  for (int i = std::max(0, *printed_steps - 1); i < n; ++i) {
    const auto& step = status.steps(i);
    std::string cause;
    if (step.cause() != v1::TERMINATION_CAUSE_UNSPECIFIED) {
      cause = v1::TerminationCause_Name(step.cause());
    }
    std::fprintf(stderr, "mission %s: %-16s %-36s attempt %d  %s%s%s\n",
                 status.mission_id().c_str(), step.name().c_str(), step.behavior().c_str(),
                 step.attempt(), v1::MissionStepState_Name(step.state()).c_str(),
                 cause.empty() ? "" : " ", cause.c_str());
  }
  *printed_steps = n;
  if (status.has_end_time() || status.state() == v1::MISSION_STATE_SUCCEEDED) {
    std::fprintf(stderr, "mission %s: %s%s%s\n", status.mission_id().c_str(),
                 v1::MissionState_Name(status.state()).c_str(),
                 status.message().empty() ? "" : ": ", status.message().c_str());
  }
}

// Follows a mission until it ends; 0 when it SUCCEEDED.
int followMission(v1::Coordinator::Stub& stub, const std::string& mission_id) {
  grpc::ClientContext context;
  v1::WatchMissionRequest request;
  request.set_mission_id(mission_id);
  auto reader = stub.WatchMission(&context, request);
  v1::WatchMissionResponse message;
  v1::MissionStatus last;
  int printed = 0;
  while (reader->Read(&message)) {
    last = message.status();
    printProgress(last, &printed);
  }
  auto s = reader->Finish();
  if (!s.ok()) return fail(s);
  std::cout << toJson(last) << std::endl;
  return last.state() == v1::MISSION_STATE_SUCCEEDED ? 0 : 1;
}

// The commands through the coordinator (behaviorlib.v1.Coordinator).
int runCoordinator(const CtlOptions& c) {
  auto stub = v1::Coordinator::NewStub(
      grpc::CreateChannel(c.coordinator, grpc::InsecureChannelCredentials()));
  const std::string& command = c.args[0];
  const std::string behavior = c.args.size() > 1 ? c.args[1] : "";
  auto needRobot = [&]() -> bool {
    if (!c.robot.empty()) return true;
    std::fprintf(stderr, "behaviorctl: '%s' through the coordinator needs --robot ID\n",
                 command.c_str());
    return false;
  };
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(10));

  if (command == "list" || command == "status") {
    if (command == "status" && !needRobot()) return 2;
    v1::ListFleetBehaviorsRequest request;
    request.set_robot_id(c.robot);
    if (command == "status") request.set_behavior(behavior);
    v1::ListFleetBehaviorsResponse response;
    auto s = stub->ListBehaviors(&context, request, &response);
    if (!s.ok()) return fail(s);
    if (command == "status" && response.behaviors().empty()) {
      std::fprintf(stderr, "behaviorctl: robot %s has no behavior '%s'\n", c.robot.c_str(),
                   behavior.c_str());
      return 1;
    }
    std::cout << toJson(response) << std::endl;
  } else if (command == "systems") {
    v1::ListSystemsRequest request;
    request.set_robot_id(c.robot);
    v1::ListSystemsResponse response;
    auto s = stub->ListSystems(&context, request, &response);
    if (!s.ok()) return fail(s);
    std::cout << toJson(response) << std::endl;
  } else if (command == "activate") {
    if (!needRobot()) return 2;
    v1::ActivateFleetBehaviorRequest request;
    request.set_robot_id(c.robot);
    request.set_behavior(behavior);
    request.set_request_id(c.request_id);
    request.set_dry_run(c.dry_run);
    request.set_skip_plan(c.skip_plan);
    if (c.args.size() > 2) {
      auto status =
          google::protobuf::util::JsonStringToMessage(c.args[2], request.mutable_parameters());
      if (!status.ok()) {
        std::fprintf(stderr, "behaviorctl: parameters are not a JSON object: %s\n",
                     std::string(status.message()).c_str());
        return 2;
      }
    }
    v1::ActivateFleetBehaviorResponse response;
    auto s = stub->ActivateBehavior(&context, request, &response);
    if (!s.ok()) return fail(s);
    std::cout << toJson(response) << std::endl;
  } else if (command == "deactivate") {
    if (!needRobot()) return 2;
    v1::DeactivateFleetBehaviorRequest request;
    request.set_robot_id(c.robot);
    request.set_behavior(behavior);
    if (c.args.size() > 2) request.set_activation_id(c.args[2]);
    v1::DeactivateFleetBehaviorResponse response;
    auto s = stub->DeactivateBehavior(&context, request, &response);
    if (!s.ok()) return fail(s);
    std::cout << toJson(response) << std::endl;
  } else if (command == "situation") {
    if (!needRobot()) return 2;
    v1::CheckFleetBehaviorSituationRequest request;
    request.set_robot_id(c.robot);
    request.set_behavior(behavior);
    v1::CheckFleetBehaviorSituationResponse response;
    auto s = stub->CheckBehaviorSituation(&context, request, &response);
    if (!s.ok()) return fail(s);
    std::cout << toJson(response) << std::endl;
  } else if (command == "watch") {
    grpc::ClientContext watch_context;
    if (c.timeout_s > 0) {
      watch_context.set_deadline(
          std::chrono::system_clock::now() +
          std::chrono::milliseconds(static_cast<int64_t>(c.timeout_s * 1e3)));
    }
    v1::WatchFleetEventsRequest request;
    request.set_since_seq(c.since_seq);
    request.set_incarnation(c.incarnation);
    if (!c.robot.empty()) request.add_robot_ids(c.robot);
    if (!c.behavior_filter.empty()) request.add_behaviors(c.behavior_filter);
    auto reader = stub->WatchEvents(&watch_context, request);
    v1::WatchFleetEventsResponse message;
    while (reader->Read(&message)) {
      std::cout << toJson(message) << std::endl;
      if (!c.until_finished.empty() && message.has_event() &&
          message.event().has_behavior_event() && message.event().behavior_event().has_finished() &&
          message.event().behavior_event().behavior() == c.until_finished) {
        watch_context.TryCancel();
        reader->Finish();
        return 0;
      }
    }
    auto s = reader->Finish();
    if (!s.ok()) return fail(s);
  } else if (command == "belief") {
    // belief list [PREFIX] | get KEY | set KEY JSON | delete KEY
    const std::string verb = c.args.size() > 1 ? c.args[1] : "";
    const std::string key = c.args.size() > 2 ? c.args[2] : "";
    if (verb == "list") {
      v1::ListBeliefsRequest request;
      request.set_prefix(key);
      v1::ListBeliefsResponse response;
      if (auto s = stub->ListBeliefs(&context, request, &response); !s.ok()) return fail(s);
      std::cout << toJson(response) << std::endl;
    } else if (verb == "get" && !key.empty()) {
      v1::ReadBeliefRequest request;
      request.set_key(key);
      v1::ReadBeliefResponse response;
      if (auto s = stub->ReadBelief(&context, request, &response); !s.ok()) return fail(s);
      std::cout << toJson(response.belief()) << std::endl;
    } else if (verb == "set" && c.args.size() > 3) {
      v1::WriteBeliefRequest request;
      request.set_key(key);
      request.set_writer("operator");
      if (!google::protobuf::util::JsonStringToMessage(c.args[3], request.mutable_value()).ok()) {
        std::fprintf(stderr,
                     "behaviorctl: the value must be JSON (a string needs quotes: '\"yes\"')\n");
        return 2;
      }
      v1::WriteBeliefResponse response;
      if (auto s = stub->WriteBelief(&context, request, &response); !s.ok()) return fail(s);
      std::cout << toJson(response.belief()) << std::endl;
    } else if (verb == "delete" && !key.empty()) {
      v1::DeleteBeliefRequest request;
      request.set_key(key);
      request.set_writer("operator");
      v1::DeleteBeliefResponse response;
      if (auto s = stub->DeleteBelief(&context, request, &response); !s.ok()) return fail(s);
    } else {
      std::fputs(
          "usage: behaviorctl --coordinator ADDR belief list [PREFIX] | get KEY | set KEY JSON | "
          "delete KEY\n",
          stderr);
      return 2;
    }
  } else if (command == "mission") {
    const std::string verb = c.args.size() > 1 ? c.args[1] : "";
    const std::string arg = c.args.size() > 2 ? c.args[2] : "";
    if (verb == "run" && !arg.empty()) {
      std::ifstream in(arg);
      if (!in) {
        std::fprintf(stderr, "behaviorctl: cannot read mission file %s\n", arg.c_str());
        return 2;
      }
      std::stringstream text;
      text << in.rdbuf();
      v1::StartMissionRequest request;
      request.set_text(text.str());
      request.set_robot_id(c.robot);
      request.set_mission_id(c.mission_id);
      v1::StartMissionResponse response;
      if (auto s = stub->StartMission(&context, request, &response); !s.ok()) return fail(s);
      if (c.detach) {
        std::cout << toJson(response.status()) << std::endl;
        return 0;
      }
      return followMission(*stub, response.status().mission_id());
    } else if (verb == "watch" && !arg.empty()) {
      return followMission(*stub, arg);
    } else if (verb == "status" && !arg.empty()) {
      v1::GetMissionRequest request;
      request.set_mission_id(arg);
      v1::GetMissionResponse response;
      if (auto s = stub->GetMission(&context, request, &response); !s.ok()) return fail(s);
      std::cout << toJson(response.status()) << std::endl;
    } else if (verb == "list") {
      v1::ListMissionsResponse response;
      if (auto s = stub->ListMissions(&context, v1::ListMissionsRequest(), &response); !s.ok()) {
        return fail(s);
      }
      std::cout << toJson(response) << std::endl;
    } else if ((verb == "pause" || verb == "resume" || verb == "abort") && !arg.empty()) {
      v1::MissionControlRequest request;
      request.set_mission_id(arg);
      request.set_reason(c.args.size() > 3 ? c.args[3] : "requested with behaviorctl");
      v1::MissionControlResponse response;
      grpc::Status s = verb == "pause"    ? stub->PauseMission(&context, request, &response)
                       : verb == "resume" ? stub->ResumeMission(&context, request, &response)
                                          : stub->AbortMission(&context, request, &response);
      if (!s.ok()) return fail(s);
      std::cout << toJson(response.status()) << std::endl;
    } else {
      std::fputs(
          "usage: behaviorctl --coordinator ADDR mission run FILE [--robot ID] [--mission-id ID] "
          "[--detach] | status ID | list | watch ID | pause ID | resume ID | abort ID [REASON]\n",
          stderr);
      return 2;
    }
  } else if (command == "emergency-land" || command == "kill") {
    if (!needRobot()) return 2;
    v1::SafetyActionRequest request;
    request.set_robot_id(c.robot);
    request.set_confirm(c.confirm);
    request.set_reason(c.args.size() > 1 ? c.args[1] : "requested with behaviorctl");
    v1::SafetyActionResponse response;
    grpc::Status s = command == "kill" ? stub->Kill(&context, request, &response)
                                       : stub->EmergencyLand(&context, request, &response);
    if (!s.ok()) return fail(s);
    std::cout << toJson(response) << std::endl;
  } else if (command == "pause" || command == "resume" || command == "modify") {
    std::fprintf(stderr,
                 "behaviorctl: '%s' is not routed by the coordinator; use --target with the "
                 "hosting system's address (see 'behaviorctl --coordinator ... list')\n",
                 command.c_str());
    return 2;
  } else {
    return usageError();
  }
  return 0;
}

// The commands to one behavior system (behaviorlib.v1.BehaviorSystem).
int runSystem(const CtlOptions& c) {
  auto stub = v1::BehaviorSystem::NewStub(
      grpc::CreateChannel(c.target, grpc::InsecureChannelCredentials()));
  const std::string& command = c.args[0];
  auto behavior = [&]() -> std::string { return c.args.size() > 1 ? c.args[1] : ""; };
  auto parseStruct = [&](size_t index, google::protobuf::Struct* out) -> bool {
    if (c.args.size() <= index) return true;
    auto status = google::protobuf::util::JsonStringToMessage(c.args[index], out);
    if (!status.ok()) {
      std::fprintf(stderr, "behaviorctl: parameters are not a JSON object: %s\n",
                   std::string(status.message()).c_str());
      return false;
    }
    return true;
  };
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(10));

  if (command == "list") {
    v1::ListBehaviorsResponse response;
    auto s = stub->ListBehaviors(&context, v1::ListBehaviorsRequest(), &response);
    if (!s.ok()) return fail(s);
    std::cout << toJson(response) << std::endl;
  } else if (command == "activate") {
    v1::ActivateBehaviorRequest request;
    request.set_behavior(behavior());
    request.set_request_id(c.request_id);
    if (!parseStruct(2, request.mutable_parameters())) return 2;
    v1::ActivateResponse response;
    auto s = stub->ActivateBehavior(&context, request, &response);
    if (!s.ok()) return fail(s);
    std::cout << toJson(response) << std::endl;
  } else if (command == "deactivate") {
    v1::DeactivateBehaviorRequest request;
    request.set_behavior(behavior());
    if (c.args.size() > 2) request.set_activation_id(c.args[2]);
    v1::DeactivateResponse response;
    auto s = stub->DeactivateBehavior(&context, request, &response);
    if (!s.ok()) return fail(s);
    std::cout << toJson(response) << std::endl;
  } else if (command == "pause" || command == "resume") {
    grpc::Status s;
    std::string out;
    if (command == "pause") {
      v1::PauseBehaviorRequest request;
      request.set_behavior(behavior());
      v1::PauseResponse response;
      s = stub->PauseBehavior(&context, request, &response);
      out = toJson(response);
    } else {
      v1::ResumeBehaviorRequest request;
      request.set_behavior(behavior());
      v1::ResumeResponse response;
      s = stub->ResumeBehavior(&context, request, &response);
      out = toJson(response);
    }
    if (!s.ok()) return fail(s);
    std::cout << out << std::endl;
  } else if (command == "modify") {
    v1::ModifyBehaviorRequest request;
    request.set_behavior(behavior());
    if (!parseStruct(2, request.mutable_parameters())) return 2;
    v1::ModifyResponse response;
    auto s = stub->ModifyBehavior(&context, request, &response);
    if (!s.ok()) return fail(s);
    std::cout << toJson(response) << std::endl;
  } else if (command == "status") {
    v1::CheckBehaviorActivationRequest request;
    request.set_behavior(behavior());
    v1::CheckActivationResponse response;
    auto s = stub->CheckBehaviorActivation(&context, request, &response);
    if (!s.ok()) return fail(s);
    std::cout << toJson(response) << std::endl;
  } else if (command == "situation") {
    v1::CheckBehaviorSituationRequest request;
    request.set_behavior(behavior());
    v1::CheckSituationResponse response;
    auto s = stub->CheckBehaviorSituation(&context, request, &response);
    if (!s.ok()) return fail(s);
    std::cout << toJson(response) << std::endl;
  } else if (command == "watch") {
    grpc::ClientContext watch_context;
    if (c.timeout_s > 0) {
      watch_context.set_deadline(
          std::chrono::system_clock::now() +
          std::chrono::milliseconds(static_cast<int64_t>(c.timeout_s * 1e3)));
    }
    v1::WatchEventsRequest request;
    request.set_since_seq(c.since_seq);
    request.set_incarnation(c.incarnation);
    auto reader = stub->WatchEvents(&watch_context, request);
    v1::WatchEventsResponse message;
    while (reader->Read(&message)) {
      std::cout << toJson(message) << std::endl;
      if (!c.until_finished.empty() && message.has_event() && message.event().has_finished() &&
          message.event().behavior() == c.until_finished) {
        watch_context.TryCancel();
        reader->Finish();
        return 0;
      }
    }
    auto s = reader->Finish();
    if (!s.ok()) return fail(s);
  } else {
    return usageError();
  }
  return 0;
}

}  // namespace

int runHealth(const CtlOptions& c) {
  // The standard gRPC health service, for docker-compose health checks.
  const std::string address = c.coordinator.empty() ? c.target : c.coordinator;
  auto result = behaviorlib::coordinator::checkHealth(
      grpc::CreateChannel(address, grpc::InsecureChannelCredentials()), "",
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
  if (options.args.empty() || options.target.empty() == options.coordinator.empty()) {
    std::fputs(
        "behaviorctl: give a command and one of --target (a behavior system) or --coordinator "
        "(the fleet); run with --help for the list\n",
        stderr);
    return 2;
  }
  if (options.args[0] == "health") return runHealth(options);
  return options.coordinator.empty() ? runSystem(options) : runCoordinator(options);
}

}  // namespace behaviorlib::coordinator
