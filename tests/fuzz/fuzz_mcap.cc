// Fuzzes the flight recorder's MCAP reader (formats/mcap/mcap.h), which
// the console runs on any *.mcap file of its recordings directory and
// `behaviorctl replay` on any file it is given: mcap::scanBytes over the
// input, then, for each message, the broker topic a replay would publish it
// on (replayTopic, which parses the coordinator's messages).
//
// Besides sanitizer findings the target aborts when the reader's contract
// breaks: a message handed on whose channel (or the channel's schema) the
// summary does not know, or an error that is not one of the documented
// codes.

#include <cstdint>
#include <string_view>

#include "behaviorlib/recorder/recorder.h"
#include "formats/mcap/mcap.h"
#include "fuzz_support.h"

BEHAVIORLIB_FUZZ_SILENCE_PROTOBUF_LOGS()

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  namespace mcap = behaviorlib::recorder::mcap;
  mcap::ReadLimits limits;
  limits.max_record_bytes = 1 << 20;
  limits.max_schemas = 64;
  limits.max_channels = 64;
  const auto summary = mcap::scanBytes(
      std::string_view(reinterpret_cast<const char*>(data), size), limits,
      [](const mcap::ScanSummary& known, const mcap::Message& message) {
        const auto channel = known.channels.find(message.channel_id);
        if (channel == known.channels.end()) behaviorlib::fuzz::broken("message without channel");
        std::string type;
        if (channel->second.schema_id != 0) {
          const auto schema = known.schemas.find(channel->second.schema_id);
          if (schema == known.schemas.end()) behaviorlib::fuzz::broken("channel without schema");
          type = schema->second.name;
        }
        (void)behaviorlib::recorder::replayTopic(channel->second.topic, type, message.data);
        return true;
      });
  if (!summary.ok()) {
    const auto code = summary.status().code();
    if (code != absl::StatusCode::kInvalidArgument &&
        code != absl::StatusCode::kResourceExhausted &&
        code != absl::StatusCode::kFailedPrecondition) {
      behaviorlib::fuzz::broken("an undocumented error code");
    }
  }
  return 0;
}
