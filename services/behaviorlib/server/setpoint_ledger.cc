#include "behaviorlib/server/setpoint_ledger.h"

#include <random>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"

namespace behaviorlib::server {
namespace {

// Keys of different processes (and of a restarted one) must not meet at the
// simulator, which remembers the keys of ended streams for a while.
std::string randomPrefix() {
  std::random_device device;
  const uint64_t bits = (static_cast<uint64_t>(device()) << 32) ^ device();
  return absl::StrFormat("%016x-", bits);
}

}  // namespace

SetpointLedger::SetpointLedger() : prefix_(randomPrefix()) {}

std::string SetpointLedger::open() {
  absl::MutexLock lock(&mutex_);
  std::string key = absl::StrCat(prefix_, next_++);
  streams_[key];
  return key;
}

void SetpointLedger::wrote(const std::string& key) {
  absl::MutexLock lock(&mutex_);
  if (auto it = streams_.find(key); it != streams_.end()) ++it->second.written;
}

void SetpointLedger::closed(const std::string& key) {
  absl::MutexLock lock(&mutex_);
  if (auto it = streams_.find(key); it != streams_.end()) it->second.closed = true;
}

void SetpointLedger::fill(google::protobuf::Map<std::string, uint64_t>* counts) {
  absl::MutexLock lock(&mutex_);
  for (auto it = streams_.begin(); it != streams_.end();) {
    if (it->second.written > 0) (*counts)[it->first] = it->second.written;
    it = it->second.closed ? streams_.erase(it) : std::next(it);
  }
}

}  // namespace behaviorlib::server
