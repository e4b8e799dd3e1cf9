#include "behaviorlib/clock.h"

#include <algorithm>

namespace behaviorlib {

void Clock::addListener(ClockListener* listener) const {
  absl::MutexLock lock(&listeners_mutex_);
  listeners_.push_back(listener);
}

void Clock::removeListener(ClockListener* listener) const {
  absl::MutexLock lock(&listeners_mutex_);
  listeners_.erase(std::remove(listeners_.begin(), listeners_.end(), listener), listeners_.end());
}

bool Clock::listenersCaughtUp(TimePoint t) const {
  absl::MutexLock lock(&listeners_mutex_);
  return std::all_of(listeners_.begin(), listeners_.end(),
                     [t](const ClockListener* listener) { return listener->caughtUp(t); });
}

void Clock::notifyListeners() {
  absl::MutexLock lock(&listeners_mutex_);
  for (auto* listener : listeners_) listener->onClockAdvanced();
}

SteadyClock::SteadyClock() {
  const auto wall =
      std::chrono::duration_cast<Duration>(std::chrono::system_clock::now().time_since_epoch());
  const auto steady =
      std::chrono::duration_cast<Duration>(std::chrono::steady_clock::now().time_since_epoch());
  offset_ = wall - steady;
}

TimePoint SteadyClock::now() const {
  return TimePoint(
      std::chrono::duration_cast<Duration>(std::chrono::steady_clock::now().time_since_epoch()) +
      offset_);
}

FakeClock::FakeClock(TimePoint start) : now_(start) {}

TimePoint FakeClock::now() const {
  absl::MutexLock lock(&mutex_);
  return now_;
}

std::chrono::nanoseconds FakeClock::wallWaitFor(Duration /*remaining*/) const {
  // Waiters are woken by advance(); the bound only guards against a missed
  // notification.
  return std::chrono::milliseconds(50);
}

void FakeClock::advance(Duration delta) {
  {
    absl::MutexLock lock(&mutex_);
    now_ += delta;
  }
  notifyListeners();
}

void FakeClock::set(TimePoint t) {
  {
    absl::MutexLock lock(&mutex_);
    if (t > now_) now_ = t;
  }
  notifyListeners();
}

}  // namespace behaviorlib
