// Fuzzes behavior parameters (services/behaviorlib/core/include/behaviorlib/
// parameters.h) as the generic BehaviorSystem API receives them: a
// google.protobuf.Struct off the wire (binary), converted into a parameter
// message (params::fromStruct), completed and checked
// (applyDefaultsAndValidate), merged as a Modify does (mergeUpdate), and
// turned back into a Struct (toStruct).
//
// Input: byte 0 picks the parameter message; the rest is the Struct's
// binary encoding.
//
// Besides sanitizer findings the target aborts when the documented contract
// breaks: fromStruct failing with anything but INVALID_ARGUMENT, toStruct's
// output refused by fromStruct or changed by a round trip, a validated
// message failing a second validation, or an update merged into the message
// it came from (then validated again, as Modify does) changing it.

#include <google/protobuf/message.h>
#include <google/protobuf/struct.pb.h>

#include <cstdint>

#include "fuzz_support.h"

BEHAVIORLIB_FUZZ_SILENCE_PROTOBUF_LOGS()

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  if (size < 1) return 0;
  const auto types = behaviorlib::fuzz::parameterTypes();
  const google::protobuf::Message& prototype = *types[data[0] % types.size()];
  google::protobuf::Struct in;
  if (!in.ParseFromArray(data + 1, static_cast<int>(size - 1))) return 0;
  behaviorlib::fuzz::exerciseParameters(in, prototype);
  return 0;
}
