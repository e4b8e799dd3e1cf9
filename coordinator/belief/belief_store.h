#pragma once

// Belief memory: typed facts (a planned path, detected markers, a saved
// map's file, an operator's answer) written by behaviors, missions and
// people, read and watched by missions and people. Every write gets a
// store-wide version; a deletion is kept as a tombstone so that watchers
// see it. With a Journal every change is appended before it is visible, and
// a restarted coordinator restores the store by replaying the journal.
//
//   BeliefStore beliefs(journal);
//   beliefs.write("drone1/path", path_value, "drone1/GENERATE_PATH_WITH_OCCUPANCY_GRID");
//   beliefs.writeMessage("drone1/path", path_proto, writer);   // stored as JSON, type kept
//   Struct params = beliefs.resolve(step_params).value();      // "${belief.drone1/path}"
//
// Thread-safe.

#include <google/protobuf/message.h>
#include <google/protobuf/struct.pb.h>

#include <chrono>
#include <map>
#include <optional>
#include <set>
#include <string>
#include <vector>

#include "absl/base/thread_annotations.h"
#include "absl/status/statusor.h"
#include "absl/synchronization/mutex.h"
#include "behaviorlib/v1/mission.pb.h"

namespace behaviorlib::coordinator {

class Journal;

/// What belief memory may hold: a write beyond is RESOURCE_EXHAUSTED and
/// changes nothing.
struct BeliefLimits {
  size_t max_beliefs = 10'000;         ///< current beliefs
  size_t max_value_bytes = 256 << 10;  ///< one belief's value, serialized
  size_t max_total_bytes = 64 << 20;   ///< every current belief's value
  /// Deletions remembered for watchers; beyond, the oldest is forgotten (a
  /// watcher that far behind sees the key absent instead of deleted).
  size_t max_tombstones = 10'000;
};

class BeliefStore {
 public:
  /// `journal` may be null (memory only); it must outlive the store.
  /// The authenticated writer of the coordinator's own writes.
  static constexpr const char* kCoordinatorWriter = "coordinator";

  explicit BeliefStore(Journal* journal = nullptr, BeliefLimits limits = {});

  /// Restores one journal record's belief (replay at start; no new version).
  void restore(const v1::Belief& belief);

  /// Writes `key`. INVALID_ARGUMENT for a bad key; RESOURCE_EXHAUSTED past
  /// the limits; the journal's error when it cannot be recorded (then
  /// nothing changes). `writer` is who the writer says it is;
  /// `authenticated_writer` who the coordinator knows it is (the identity of
  /// an RPC's caller, empty without TLS; the coordinator's own writes by
  /// default).
  absl::StatusOr<v1::Belief> write(const std::string& key, const google::protobuf::Value& value,
                                   const std::string& writer, const std::string& type = "",
                                   const std::string& authenticated_writer = kCoordinatorWriter);
  /// Writes a typed message as its JSON form, keeping its type name.
  absl::StatusOr<v1::Belief> writeMessage(const std::string& key,
                                          const google::protobuf::Message& message,
                                          const std::string& writer);
  /// Deletes `key`; NOT_FOUND when absent.
  absl::Status erase(const std::string& key, const std::string& writer,
                     const std::string& authenticated_writer = kCoordinatorWriter);

  std::optional<v1::Belief> get(const std::string& key) const;
  /// Current beliefs whose key starts with `prefix`, sorted by key.
  std::vector<v1::Belief> list(const std::string& prefix = "") const;
  /// Latest version written so far.
  uint64_t version() const;
  /// Changes (writes and tombstones) newer than `since_version` under
  /// `prefix`, waiting up to `timeout` for one to happen; sorted by version.
  std::vector<v1::Belief> waitForChanges(uint64_t since_version, const std::string& prefix,
                                         std::chrono::milliseconds timeout) const;
  /// Wakes every waitForChanges() (shutdown).
  void wakeAll();

  /// Replaces "${belief.<key>}" in the strings of `parameters`: a string that
  /// is exactly one binding takes the belief's value (a number, a list, an
  /// object...); a binding inside a longer string is replaced by the value's
  /// text. FAILED_PRECONDITION naming the key when it is not in memory.
  absl::StatusOr<google::protobuf::Struct> resolve(
      const google::protobuf::Struct& parameters) const;

  /// Every current belief and tombstone, for journal compaction.
  std::vector<v1::Belief> snapshot() const;

  /// OK for a valid key; INVALID_ARGUMENT explaining the rule otherwise.
  static absl::Status checkKey(const std::string& key);
  /// The keys of the "${belief.<key>}" bindings in `text`, in order;
  /// INVALID_ARGUMENT for an unterminated or malformed binding.
  static absl::StatusOr<std::vector<std::string>> bindingsIn(const std::string& text);

 private:
  absl::StatusOr<google::protobuf::Value> resolveValue(const google::protobuf::Value& value) const;

  // Keeps the counts below when `key`'s entry becomes `now` (null: removed).
  void account(const v1::Belief* before, const v1::Belief* now)
      ABSL_EXCLUSIVE_LOCKS_REQUIRED(mutex_);
  void forgetOldTombstones() ABSL_EXCLUSIVE_LOCKS_REQUIRED(mutex_);

  Journal* journal_;
  const BeliefLimits limits_;
  // waitForChanges waits on mutex_ (Mutex::Await) for a new version_ or
  // wakeAll.
  mutable absl::Mutex mutex_;
  size_t live_count_ ABSL_GUARDED_BY(mutex_) = 0;
  size_t live_bytes_ ABSL_GUARDED_BY(mutex_) = 0;
  std::set<std::pair<uint64_t, std::string>> tombstones_ ABSL_GUARDED_BY(mutex_);  // by version
  std::map<std::string, v1::Belief> beliefs_ ABSL_GUARDED_BY(mutex_);  // tombstones included
  uint64_t version_ ABSL_GUARDED_BY(mutex_) = 0;
  bool woken_ ABSL_GUARDED_BY(mutex_) = false;
};

}  // namespace behaviorlib::coordinator
