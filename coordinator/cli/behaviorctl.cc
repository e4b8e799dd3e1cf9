// behaviorctl: a command-line client of a behavior-system process (the generic
// behaviorlib.v1.BehaviorSystem service).
//
//   behaviorctl --target 127.0.0.1:50061 list
//   behaviorctl --target 127.0.0.1:50061 activate WAIT '{"duration_s": 2}'
//   behaviorctl --target 127.0.0.1:50061 watch [--since-seq N] [--until-finished WAIT]
//   behaviorctl --target 127.0.0.1:50061 deactivate WAIT [activation_id]
//   behaviorctl --target 127.0.0.1:50061 status WAIT
//
// Output is one JSON object per line, so it can be piped into other tools.
// The coordinator (a later part of the project) will extend it.

#include <google/protobuf/util/json_util.h>
#include <grpcpp/grpcpp.h>

#include <chrono>
#include <cstdio>
#include <iostream>
#include <string>
#include <vector>

#include "behaviorlib/v1/behavior.grpc.pb.h"

namespace {

namespace v1 = behaviorlib::v1;

std::string toJson(const google::protobuf::Message& message) {
  std::string out;
  google::protobuf::util::JsonPrintOptions options;
  options.preserve_proto_field_names = true;
  (void)google::protobuf::util::MessageToJsonString(message, &out, options);
  return out;
}

int usage() {
  std::fputs(
      "usage: behaviorctl --target HOST:PORT COMMAND ...\n"
      "commands:\n"
      "  list                                 behaviors and their parameter schemas\n"
      "  activate BEHAVIOR [JSON] [--request-id ID]\n"
      "  deactivate BEHAVIOR [ACTIVATION_ID]\n"
      "  pause BEHAVIOR | resume BEHAVIOR\n"
      "  modify BEHAVIOR JSON\n"
      "  status BEHAVIOR                      CheckActivation\n"
      "  situation BEHAVIOR                   CheckSituation\n"
      "  watch [--since-seq N] [--incarnation ID] [--until-finished BEHAVIOR] [--timeout-s S]\n",
      stderr);
  return 2;
}

int fail(const grpc::Status& status) {
  std::fprintf(stderr, "behaviorctl: %d %s\n", static_cast<int>(status.error_code()),
               status.error_message().c_str());
  return 1;
}

}  // namespace

int main(int argc, char** argv) {
  std::string target;
  std::vector<std::string> args;
  std::string request_id, incarnation, until_finished;
  uint64_t since_seq = 0;
  double timeout_s = 0;
  for (int i = 1; i < argc; ++i) {
    std::string a = argv[i];
    auto value = [&]() -> std::string { return i + 1 < argc ? argv[++i] : ""; };
    if (a == "--target") {
      target = value();
    } else if (a == "--request-id") {
      request_id = value();
    } else if (a == "--since-seq") {
      since_seq = std::stoull(value());
    } else if (a == "--incarnation") {
      incarnation = value();
    } else if (a == "--until-finished") {
      until_finished = value();
    } else if (a == "--timeout-s") {
      timeout_s = std::stod(value());
    } else if (a == "--help" || a == "-h") {
      return usage();
    } else {
      args.push_back(a);
    }
  }
  if (target.empty() || args.empty()) return usage();
  auto stub =
      v1::BehaviorSystem::NewStub(grpc::CreateChannel(target, grpc::InsecureChannelCredentials()));
  const std::string& command = args[0];
  auto behavior = [&]() -> std::string { return args.size() > 1 ? args[1] : ""; };
  auto parseStruct = [&](size_t index, google::protobuf::Struct* out) -> bool {
    if (args.size() <= index) return true;
    auto status = google::protobuf::util::JsonStringToMessage(args[index], out);
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
    request.set_request_id(request_id);
    if (!parseStruct(2, request.mutable_parameters())) return 2;
    v1::ActivateResponse response;
    auto s = stub->ActivateBehavior(&context, request, &response);
    if (!s.ok()) return fail(s);
    std::cout << toJson(response) << std::endl;
  } else if (command == "deactivate") {
    v1::DeactivateBehaviorRequest request;
    request.set_behavior(behavior());
    if (args.size() > 2) request.set_activation_id(args[2]);
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
    if (timeout_s > 0) {
      watch_context.set_deadline(std::chrono::system_clock::now() +
                                 std::chrono::milliseconds(static_cast<int64_t>(timeout_s * 1e3)));
    }
    v1::WatchEventsRequest request;
    request.set_since_seq(since_seq);
    request.set_incarnation(incarnation);
    auto reader = stub->WatchEvents(&watch_context, request);
    v1::WatchEventsResponse message;
    while (reader->Read(&message)) {
      std::cout << toJson(message) << std::endl;
      if (!until_finished.empty() && message.has_event() && message.event().has_finished() &&
          message.event().behavior() == until_finished) {
        watch_context.TryCancel();
        reader->Finish();
        return 0;
      }
    }
    auto s = reader->Finish();
    if (!s.ok()) return fail(s);
  } else {
    return usage();
  }
  return 0;
}
