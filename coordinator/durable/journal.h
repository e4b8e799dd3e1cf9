#pragma once

// Journal: the coordinator's append-only log on disk. Every change that must
// survive a restart (a belief written, a mission's state) is appended as one
// record; at start the file is replayed. Records are framed as
//   [u32 length, little endian][u32 CRC-32 of the payload][payload: JournalRecord]
// so that a record torn by a crash in the middle of a write is recognised
// and cut off (the records before it are kept). The file grows until
// compact() rewrites it from a snapshot (write to a temporary file, fsync,
// rename: a crash leaves either the old or the new journal).
//
//   auto journal = Journal::open("/var/lib/behaviorlib/coordinator.journal",
//                                [&](const durable::v1::JournalRecord& r) { restore(r); });
//   journal.value()->append(record);
//
// A process killed with SIGKILL loses nothing that append() returned for
// (the kernel holds the written bytes); with `fsync_each_append` a power
// loss does not either, at the cost of one fdatasync per record.
// Thread-safe.

#include <cstdint>
#include <functional>
#include <memory>
#include <string>
#include <string_view>
#include <vector>

#include "absl/base/thread_annotations.h"
#include "absl/status/statusor.h"
#include "absl/synchronization/mutex.h"
#include "behaviorlib/durable/v1/journal.pb.h"
#include "behaviorlib/v1/mission.pb.h"

namespace behaviorlib::coordinator {

struct JournalOptions {
  bool fsync_each_append = false;
};

class Journal {
 public:
  using Replay = std::function<void(const durable::v1::JournalRecord&)>;

  /// Opens or creates `path` and replays its records through `replay` in
  /// order. A torn or corrupt tail is truncated (see truncatedBytes()).
  static absl::StatusOr<std::unique_ptr<Journal>> open(const std::string& path,
                                                       const Replay& replay,
                                                       JournalOptions options = {});
  ~Journal();
  Journal(const Journal&) = delete;
  Journal& operator=(const Journal&) = delete;

  /// Appends one record (durable against a process crash once it returns).
  absl::Status append(const durable::v1::JournalRecord& record);
  /// Replaces the journal's content with `snapshot` atomically.
  absl::Status compact(const std::vector<durable::v1::JournalRecord>& snapshot);
  /// Compaction while records keep being appended. The journal first starts
  /// keeping a copy of every record appended; then `snapshot` is called (it
  /// reads the stores, which may append meanwhile); the new journal is the
  /// snapshot followed by the records appended since the copy began. Replay
  /// is last-writer-wins per belief, mission and system, so a record both in
  /// the snapshot and after it replays to the same state. The stores'
  /// locks are never taken under the journal's.
  absl::Status compactOnline(
      const std::function<std::vector<durable::v1::JournalRecord>()>& snapshot);

  const std::string& path() const { return path_; }
  /// Records replayed at open plus appended since (reset by compact()).
  uint64_t recordCount() const;
  uint64_t sizeBytes() const;
  /// Bytes cut off at open because the last record was torn or corrupt.
  uint64_t truncatedBytes() const { return truncated_bytes_; }

 private:
  Journal(std::string path, int fd, JournalOptions options);
  absl::Status writeAll(int fd, const std::string& bytes);
  absl::Status replaceLocked(const std::string& bytes, uint64_t records)
      ABSL_EXCLUSIVE_LOCKS_REQUIRED(mutex_);

  std::string path_;
  JournalOptions options_;
  mutable absl::Mutex mutex_;
  int fd_ ABSL_GUARDED_BY(mutex_) = -1;
  uint64_t records_ ABSL_GUARDED_BY(mutex_) = 0;
  uint64_t size_ ABSL_GUARDED_BY(mutex_) = 0;
  // While compactOnline() runs: a copy of each record appended.
  bool capturing_ ABSL_GUARDED_BY(mutex_) = false;
  std::string captured_ ABSL_GUARDED_BY(mutex_);
  uint64_t captured_records_ ABSL_GUARDED_BY(mutex_) = 0;
  // One compaction at a time.
  absl::Mutex compaction_mutex_;
  // Written by open() only, before the journal is shared.
  uint64_t truncated_bytes_ = 0;
};

/// Decodes the records of a journal's content (the framing above) from its
/// start and passes each to `replay`, in order, stopping at the first record
/// that is torn (fewer bytes than its length), longer than the 64 MiB a
/// record may be, fails its CRC or does not parse. Returns the length of the
/// valid prefix (what Journal::open keeps) and, when `records` is not null,
/// sets it to the number of records replayed. Reads nothing but `content`.
size_t decodeJournal(std::string_view content, const Journal::Replay& replay,
                     uint64_t* records = nullptr);

}  // namespace behaviorlib::coordinator
