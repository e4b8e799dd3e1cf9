#include "behaviorlib/resumable_log.h"

#include <random>

namespace behaviorlib {

namespace log_internal {
namespace {

// Wake slots whose callback runs on this thread (innermost last). A callback
// that cancels or destroys its own subscription, or appends and so wakes it
// again, already holds the slot's mutex and must not wait for itself.
thread_local std::vector<const void*> t_running_wakes;

bool runningOnThisThread(const void* slot) {
  return std::find(t_running_wakes.begin(), t_running_wakes.end(), slot) != t_running_wakes.end();
}

}  // namespace

void WakeSlot::fire() {
  if (runningOnThisThread(this)) {
    // Re-entered from our own callback: the outer frame holds the mutex.
    mutex_.AssertHeld();
    if (!cancelled_ && wake_) wake_();
    return;
  }
  absl::MutexLock lock(&mutex_);
  if (cancelled_ || !wake_) return;
  t_running_wakes.push_back(this);
  struct Pop {
    ~Pop() { t_running_wakes.pop_back(); }
  } pop;
  wake_();
}

void WakeSlot::cancel() {
  if (runningOnThisThread(this)) {
    mutex_.AssertHeld();  // by the outer frame, on this thread
    cancelled_ = true;
    return;
  }
  absl::MutexLock lock(&mutex_);
  cancelled_ = true;
}

void setWallTime(google::protobuf::Timestamp* timestamp) {
  const auto since_epoch = std::chrono::duration_cast<std::chrono::nanoseconds>(
      std::chrono::system_clock::now().time_since_epoch());
  const auto seconds = std::chrono::floor<std::chrono::seconds>(since_epoch);
  timestamp->set_seconds(seconds.count());
  timestamp->set_nanos(static_cast<int32_t>((since_epoch - seconds).count()));
}

std::chrono::nanoseconds steadyNow() { return std::chrono::steady_clock::now().time_since_epoch(); }

}  // namespace log_internal

std::string newIncarnationId() {
  std::random_device device;
  std::seed_seq seed{device(), device(), device(), device(),
                     device(), device(), device(), device()};
  std::mt19937_64 engine(seed);
  static constexpr char kHex[] = "0123456789abcdef";
  std::string id;
  id.reserve(32);
  for (int half = 0; half < 2; ++half) {
    const uint64_t value = engine();
    for (int shift = 60; shift >= 0; shift -= 4) id.push_back(kHex[(value >> shift) & 0xf]);
  }
  return id;
}

}  // namespace behaviorlib
