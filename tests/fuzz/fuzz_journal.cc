// Fuzzes the coordinator's journal (coordinator/durable/journal.h):
// decodeJournal, the replay Journal::open runs over the file's bytes, with
// no file. The replayed records go where the coordinator sends them
// (ReplayedState, coordinator/process/replayed_state.h): beliefs restored into belief
// memory (BeliefStore::restore, then copied into the live store from its
// snapshot), mission statuses kept, the last record of each system kept;
// then, as MissionManager::resumeOne does for a mission that had not ended,
// the mission text the status carries is parsed again (parseMission), and
// each restored belief is read back and bound into parameters.
//
// Input: byte 0 picks the mode, the rest is the content.
//   mode 0  the content as the journal file's bytes;
//   mode 1  the content framed as one valid record (length, CRC-32), so that
//           the payload reaches the protobuf parser past the checksum;
//   mode 2  the content cut into several records (FuzzedDataProvider: each
//           length is taken from the end of the data), each framed.

#include <fuzzer/FuzzedDataProvider.h>
#include <google/protobuf/struct.pb.h>
#include <zlib.h>

#include <cstdint>
#include <string>
#include <string_view>

#include "behaviorlib/durable/v1/journal.pb.h"
#include "behaviorlib/v1/mission.pb.h"
#include "coordinator/belief/belief_store.h"
#include "coordinator/durable/journal.h"
#include "coordinator/mission/mission_file.h"
#include "coordinator/process/replayed_state.h"
#include "fuzz_support.h"

namespace {

namespace v1 = behaviorlib::v1;
using behaviorlib::coordinator::BeliefStore;
using behaviorlib::coordinator::ReplayedState;
using behaviorlib::fuzz::broken;

// The framing of journal.cc: [u32 length LE][u32 CRC-32 LE][payload].
void frame(std::string_view payload, std::string* out) {
  const auto put = [&](uint32_t v) {
    for (int i = 0; i < 4; ++i) out->push_back(static_cast<char>((v >> (8 * i)) & 0xff));
  };
  put(static_cast<uint32_t>(payload.size()));
  put(static_cast<uint32_t>(crc32(0L, reinterpret_cast<const Bytef*>(payload.data()),
                                  static_cast<uInt>(payload.size()))));
  out->append(payload);
}

void replay(const std::string& content) {
  // The coordinator's replay target.
  ReplayedState replayed;
  uint64_t seen = 0;
  uint64_t records = 0;
  const size_t valid = behaviorlib::coordinator::decodeJournal(
      content,
      [&](const behaviorlib::durable::v1::JournalRecord& record) {
        ++seen;
        (void)record.ByteSizeLong();
        replayed.apply(record);
      },
      &records);
  if (valid > content.size() || records != seen) broken("decodeJournal miscounted");
  if (records > 0 && valid < 8 * records) broken("decodeJournal: prefix shorter than its records");

  // The live store, filled from the snapshot of the replayed one.
  BeliefStore beliefs;
  for (const auto& belief : replayed.beliefs.snapshot()) beliefs.restore(belief);
  (void)beliefs.version();
  for (const auto& belief : beliefs.list()) {
    (void)beliefs.get(belief.key());
    google::protobuf::Struct bound;
    (*bound.mutable_fields())["p"].set_string_value("${belief." + belief.key() + "}");
    (void)beliefs.resolve(bound);
  }
  // Resuming a mission that had not ended parses its text again.
  int parsed = 0;
  for (const auto& status : replayed.missions) {
    const bool ended = status.has_end_time() || status.state() == v1::MISSION_STATE_SUCCEEDED;
    if (ended || status.source().empty() || ++parsed > 4) continue;
    (void)behaviorlib::coordinator::parseMission(status.source(), status.file());
  }
}

}  // namespace

BEHAVIORLIB_FUZZ_SILENCE_PROTOBUF_LOGS()

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  if (size < 1) return 0;
  const std::string_view rest(reinterpret_cast<const char*>(data + 1), size - 1);
  switch (data[0] % 3) {
    case 0:
      replay(std::string(rest));
      break;
    case 1: {
      std::string content;
      frame(rest, &content);
      // A valid frame: all of it is kept exactly when the payload parses.
      behaviorlib::durable::v1::JournalRecord record;
      const bool parses = record.ParseFromArray(rest.data(), static_cast<int>(rest.size()));
      uint64_t records = 0;
      const size_t valid = behaviorlib::coordinator::decodeJournal(
          content, [](const behaviorlib::durable::v1::JournalRecord&) {}, &records);
      if (valid != (parses ? content.size() : 0) || records != (parses ? 1u : 0u)) {
        broken("decodeJournal disagrees with the record's parser on a valid frame");
      }
      replay(content);
      break;
    }
    default: {
      FuzzedDataProvider provider(data + 1, size - 1);
      std::string content;
      while (provider.remaining_bytes() > 0) {
        const size_t length = provider.ConsumeIntegralInRange<size_t>(0, 4096);
        frame(provider.ConsumeBytesAsString(length), &content);
      }
      replay(content);
      break;
    }
  }
  return 0;
}
