#pragma once

// SetpointLedger: the deterministic mode's barrier for setpoints. A behavior
// system streams setpoints to the simulator's FlightController on streams of
// their own, beside its FollowTime stream; the two are read by different
// threads of the simulator, so a setpoint written before a report could be
// applied after the simulator stepped on (a quantum late, depending on which
// thread ran first). So each setpoint stream carries a key (metadata
// kSetpointStreamMetadataKey), the ledger counts what was written on each,
// and the TimeFollower's report names those counts
// (FollowTimeRequest.setpoints_written): the simulator applies them all
// before it steps.
//
//   SetpointLedger ledger;                       // one per process
//   const std::string key = ledger.open();       // a new stream's key
//   ... context.AddMetadata(kSetpointStreamMetadataKey, key); Write(setpoint) ...
//   ledger.wrote(key);
//   ledger.closed(key);                          // once the stream is done with
//   ledger.fill(report.mutable_setpoints_written());  // the follower, per report
//
// Thread-safe.

#include <google/protobuf/map.h>

#include <cstdint>
#include <map>
#include <string>

#include "absl/base/thread_annotations.h"
#include "absl/synchronization/mutex.h"
#include "behaviorlib/server_kit/barrier_metadata.h"

namespace behaviorlib::server {

class SetpointLedger {
 public:
  SetpointLedger();

  /// A key for a new stream, unique to this process and run.
  std::string open();
  /// A setpoint was written on `key`'s stream.
  void wrote(const std::string& key);
  /// `key`'s stream is done with (finished or cancelled): the next fill()
  /// names its final count once more, then forgets it.
  void closed(const std::string& key);
  /// The count of every open stream, and of those closed since the last call.
  void fill(google::protobuf::Map<std::string, uint64_t>* counts);

 private:
  const std::string prefix_;
  absl::Mutex mutex_;
  uint64_t next_ ABSL_GUARDED_BY(mutex_) = 0;
  struct Stream {
    uint64_t written = 0;
    bool closed = false;
  };
  std::map<std::string, Stream> streams_ ABSL_GUARDED_BY(mutex_);
};

}  // namespace behaviorlib::server
