#include "simulator/service/setpoint_barrier.h"

#include "absl/time/time.h"

namespace behaviorlib::sim {

bool SetpointBarrier::opened(const std::string& key) {
  if (key.empty() || key.size() > kMaxKeyBytes) return false;
  absl::MutexLock lock(&mutex_);
  if (ended_.count(key) > 0) return false;
  return open_.emplace(key, 0).second;
}

void SetpointBarrier::read(const std::string& key) {
  absl::MutexLock lock(&mutex_);
  if (auto it = open_.find(key); it != open_.end()) ++it->second;
}

void SetpointBarrier::ended(const std::string& key) {
  absl::MutexLock lock(&mutex_);
  if (open_.erase(key) == 0) return;
  keepEndedLocked(key);
}

void SetpointBarrier::keepEndedLocked(const std::string& key) {
  if (!ended_.emplace(key, true).second) return;
  ended_order_.push_back(key);
  if (ended_order_.size() > kEndedKeysKept) {
    ended_.erase(ended_order_.front());
    ended_order_.pop_front();
  }
}

bool SetpointBarrier::doneLocked(const std::map<std::string, uint64_t>& written) const {
  for (const auto& [key, count] : written) {
    // A key too long is never counted, so never waited for.
    if (key.size() > kMaxKeyBytes || ended_.count(key) > 0) continue;
    // A stream not opened yet (its first message is on its way) is waited for.
    const auto it = open_.find(key);
    if (it == open_.end() || it->second < count) return false;
  }
  return true;
}

bool SetpointBarrier::awaitRead(const std::map<std::string, uint64_t>& written,
                                std::chrono::nanoseconds limit) {
  if (written.empty()) return true;
  absl::MutexLock lock(&mutex_);
  if (doneLocked(written)) return true;
  ++waits_;
  const auto done = [this, &written]()
                        ABSL_SHARED_LOCKS_REQUIRED(mutex_) { return doneLocked(written); };
  if (mutex_.AwaitWithTimeout(absl::Condition(&done), absl::FromChrono(limit))) return true;
  ++timeouts_;
  // A stream that never came (its process died, or its setpoints went to
  // another platform) is not waited for again, as if it had ended.
  for (const auto& [key, count] : written) {
    if (key.size() <= kMaxKeyBytes && open_.count(key) == 0) keepEndedLocked(key);
  }
  return false;
}

uint64_t SetpointBarrier::waitCount() const {
  absl::MutexLock lock(&mutex_);
  return waits_;
}

uint64_t SetpointBarrier::timeoutCount() const {
  absl::MutexLock lock(&mutex_);
  return timeouts_;
}

}  // namespace behaviorlib::sim
