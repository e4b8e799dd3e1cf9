#pragma once

// A shared-memory ring of one topic's samples: the broker writes each sample
// once, and every subscriber on the same host reads it from the ring instead
// of receiving its own copy over a gRPC stream (decision 20).
//
//   // Broker (the only writer of a ring):
//   auto ring = ShmRing::create(ShmRing::nameFor(getpid(), 7), 16, 4096);
//   ring->write(topic_seq, bytes);       // bytes: a serialized SubscribeResponse
//
//   // Subscriber:
//   auto reader = ShmRing::open(name);
//   uint64_t next = first_seq;
//   std::string bytes;
//   ShmRing::Read r = reader->read(next, /*latest_only=*/false, &bytes);
//
// Samples are numbered by their topic_seq, so numbering continues across
// ring generations: a sample larger than a slot makes the writer open a
// bigger ring and mark the old one superseded (with the new one's name), and
// readers move over without losing their place. A slot is guarded by a
// sequence lock: a reader that was lapped while copying sees it and counts
// the samples as dropped; a writer never waits for a reader. Readers sleep
// on a futex in the header; the writer makes a system call only while
// someone sleeps there.

#include <atomic>
#include <cstddef>
#include <cstdint>
#include <memory>
#include <string>

#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"

namespace behaviorlib::channel {

class ShmRing {
 public:
  /// The outcome of a read().
  enum class Read {
    kSample,      // `*bytes` holds sample number `*next - 1` (next was advanced)
    kEmpty,       // nothing at or after `next` yet
    kSuperseded,  // drained and replaced: open successor() and go on there
    kClosed,      // the writer closed the ring for good
  };

  /// "/behaviorlib-ch-<pid>-<n>": a writer's rings carry its pid, so that a
  /// restarted broker can remove what a killed one left (removeStale).
  static std::string nameFor(int64_t writer_pid, uint64_t n);

  /// Creates (replacing any stale one of the same name) a ring of
  /// `slot_count` slots of `slot_bytes` each. The caller is its only writer.
  static absl::StatusOr<std::unique_ptr<ShmRing>> create(const std::string& name,
                                                         uint32_t slot_count, uint64_t slot_bytes);
  /// Maps an existing ring for reading; FAILED_PRECONDITION when it is not
  /// one of ours (bad magic, version or size).
  static absl::StatusOr<std::unique_ptr<ShmRing>> open(const std::string& name);
  /// Unlinks the rings under /dev/shm whose writer pid no longer runs.
  /// Returns how many were removed.
  static int removeStale();
  /// Where this process's shared memory lives: "<boot id>/<IPC namespace
  /// inode>". Two processes can share a ring when their domains are equal
  /// (same host, same IPC namespace: containers included). Empty when it
  /// cannot be read.
  static const std::string& domain();

  ~ShmRing();
  ShmRing(const ShmRing&) = delete;
  ShmRing& operator=(const ShmRing&) = delete;

  const std::string& name() const { return name_; }
  uint32_t slotCount() const;
  uint64_t slotBytes() const;
  /// The highest sample number written so far (0 before the first).
  uint64_t written() const;

  // --- writer ---
  /// Whether `size` bytes fit into a slot.
  bool fits(std::size_t size) const { return size <= slotBytes(); }
  /// Writes sample number `seq` (greater than every earlier one; gaps are
  /// allowed). Requires fits(bytes.size()).
  void write(uint64_t seq, absl::string_view bytes);
  /// Marks the ring replaced by the ring `successor` and wakes the readers.
  void supersede(const std::string& successor);
  /// Marks the ring closed (the writer is going away) and wakes the readers.
  void close();
  /// Unlinks the ring's name (mapped readers keep their mapping).
  void unlink();

  // --- reader ---
  /// Reads the first sample numbered `*next` or later into `*bytes` and sets
  /// `*next` past it. With `latest_only`, skips to the newest sample. Samples
  /// skipped (overwritten before they were read, or by latest_only) are
  /// added to `*dropped`.
  Read read(uint64_t* next, bool latest_only, std::string* bytes, uint64_t* dropped) const;
  /// Sleeps until the ring changes after a read() returned kEmpty with
  /// `token` taken by notifyToken() before that read, or `timeout_ns` passes,
  /// or wake() is called.
  void wait(uint32_t token, int64_t timeout_ns) const;
  uint32_t notifyToken() const;
  /// Wakes every reader sleeping in wait() (e.g. a reader being stopped).
  void wake() const;
  /// The ring that superseded this one ("" until then).
  std::string successor() const;

 private:
  struct Header;
  ShmRing(std::string name, void* base, std::size_t size);
  Header& header() const;
  unsigned char* slot(uint64_t seq) const;

  std::string name_;
  void* base_;
  std::size_t size_;
};

}  // namespace behaviorlib::channel
