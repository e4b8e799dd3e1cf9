// What the libFuzzer targets in tests/fuzz/ share: aborting with a message,
// the error contract of the file parsers, an LLVMFuzzerInitialize that
// silences protobuf's log, the registrations of the real behaviors
// (fuzz_support.cc) and the checks of behavior parameters
// (fuzz_support_parameters.cc).
//
// This header names no generated type, so that every target can include it;
// the parts defined in the .cc files come with behaviorlib_fuzz_support
// (tests/fuzz/CMakeLists.txt).

#pragma once

#include <google/protobuf/stubs/logging.h>

#include <cstdio>
#include <cstdlib>
#include <map>
#include <span>
#include <string>
#include <string_view>

#include "absl/status/status.h"

namespace google::protobuf {
class Descriptor;
class Message;
class Struct;
}  // namespace google::protobuf

namespace behaviorlib::v1 {
class BehaviorDescription;
}  // namespace behaviorlib::v1

namespace behaviorlib::fuzz {

// A broken contract: the message, then abort() (libFuzzer saves the input).
[[noreturn]] inline void broken(const char* what) {
  std::fprintf(stderr, "%s\n", what);
  std::abort();
}

[[noreturn]] inline void broken(const char* what, std::string_view detail) {
  std::fprintf(stderr, "%s: %.*s\n", what, static_cast<int>(detail.size()), detail.data());
  std::abort();
}

// The name the targets give the text they parse.
inline constexpr char kFileName[] = "fuzz.yaml";

// The documented contract of the file parsers (parseMission, parseWorld,
// parseSensorConfig, Catalog::parse, parseSystemsConfig) when they refuse a
// text: INVALID_ARGUMENT with a message that names the file,
// "<file>:<line>: ..." (or "<file>: ..." for the whole text).
inline void checkParseError(const absl::Status& status, const char* parser) {
  if (status.code() != absl::StatusCode::kInvalidArgument ||
      status.message().rfind(kFileName, 0) != 0) {
    broken((std::string(parser) + " broke its error contract").c_str(), status.ToString());
  }
}

// fuzz_support.cc: every behavior declared in proto/behaviorlib/v1/behaviors/,
// described as its system registers it (BehaviorSystemService::ListBehaviors),
// by name.
const std::map<std::string, v1::BehaviorDescription>& behaviorDescriptions();

// The parameter message of the declared behavior `name`; nullptr for a name
// no behavior declares.
const google::protobuf::Descriptor* parameterTypeOf(const std::string& name);

// fuzz_support_parameters.cc: real parameter messages of different shapes,
// and the test messages that have the field kinds no shipped one uses
// (behaviorlib_test_params_proto).
std::span<const google::protobuf::Message* const> parameterTypes();

// broken(), with the message's type and contents.
[[noreturn]] void broken(const char* what, const google::protobuf::Message& m);

// `in` as the behavior system takes it: params::fromStruct into a message of
// the prototype's type, applyDefaultsAndValidate, mergeUpdate (Modify) and
// toStruct. Aborts when the documented contract breaks: fromStruct failing
// with anything but INVALID_ARGUMENT, toStruct's output refused by fromStruct
// or changed by a round trip, a validated message failing a second
// validation, or an update merged into the message it came from (then
// validated again, as Modify does) changing it.
void exerciseParameters(const google::protobuf::Struct& in,
                        const google::protobuf::Message& prototype);

}  // namespace behaviorlib::fuzz

// Defines the target's LLVMFuzzerInitialize (one per executable: a target
// that needs more at start writes its own), which silences protobuf's log.
// Invalid UTF-8 in a string field is a parse failure the target expects, but
// protobuf also logs each one, which would drown libFuzzer's output.
// Non-fatal logs only: a failed GOOGLE_CHECK still aborts.
#define BEHAVIORLIB_FUZZ_SILENCE_PROTOBUF_LOGS()                         \
  extern "C" int LLVMFuzzerInitialize(int* /*argc*/, char*** /*argv*/) { \
    google::protobuf::SetLogHandler(nullptr);                            \
    return 0;                                                            \
  }
