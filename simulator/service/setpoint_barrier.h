#pragma once

// SetpointBarrier: the simulator's side of the deterministic mode's barrier
// for setpoints (the follower's side: behaviorlib/server/setpoint_ledger.h).
// A follower streams setpoints on StreamSetpoints calls of their own, each
// naming a key in its metadata ("behaviorlib-setpoint-stream"); its time
// reports say how many it wrote on each (FollowTimeRequest.
// setpoints_written). The FlightController counts what it read on each keyed
// stream here, and before the simulator steps on, TimeGrants waits until every
// reported setpoint was read (applied or refused) or its stream ended. So a
// setpoint written before a report is applied at the time it was meant for,
// whichever of the simulator's threads ran first.
//
// Bounded: keys longer than kMaxKeyBytes are not counted (their streams are
// not waited for), the keys of ended streams are remembered up to
// kEndedKeysKept (so a report that names a stream after its end does not
// wait), and a wait gives up after its limit; a stream it gave up on that
// never began then counts as ended (it is not waited for again).
//
// Thread-safe.

#include <chrono>
#include <cstdint>
#include <deque>
#include <map>
#include <string>

#include "absl/base/thread_annotations.h"
#include "absl/synchronization/mutex.h"

namespace behaviorlib::sim {

class SetpointBarrier {
 public:
  static constexpr size_t kMaxKeyBytes = 64;
  static constexpr size_t kEndedKeysKept = 4096;

  /// A keyed stream began; false (not counted) for a key that is empty, too
  /// long, or already in use.
  bool opened(const std::string& key);
  /// One setpoint was read on `key`'s stream (applied or refused).
  void read(const std::string& key);
  /// `key`'s stream ended.
  void ended(const std::string& key);

  /// Waits until every setpoint in `written` (key → count) was read, or its
  /// stream ended, for at most `limit` of wall time. True when all were;
  /// counts the waits that had to block (waitCount()).
  bool awaitRead(const std::map<std::string, uint64_t>& written, std::chrono::nanoseconds limit);

  /// Waits that found a reported setpoint not read yet, and waits that gave up.
  uint64_t waitCount() const;
  uint64_t timeoutCount() const;

 private:
  bool doneLocked(const std::map<std::string, uint64_t>& written) const
      ABSL_SHARED_LOCKS_REQUIRED(mutex_);
  void keepEndedLocked(const std::string& key) ABSL_EXCLUSIVE_LOCKS_REQUIRED(mutex_);

  mutable absl::Mutex mutex_;
  std::map<std::string, uint64_t> open_ ABSL_GUARDED_BY(mutex_);  // key → read
  std::map<std::string, bool> ended_ ABSL_GUARDED_BY(mutex_);     // kept keys
  std::deque<std::string> ended_order_ ABSL_GUARDED_BY(mutex_);   // oldest first
  uint64_t waits_ ABSL_GUARDED_BY(mutex_) = 0;
  uint64_t timeouts_ ABSL_GUARDED_BY(mutex_) = 0;
};

}  // namespace behaviorlib::sim
