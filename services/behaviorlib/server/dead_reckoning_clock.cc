#include "behaviorlib/server/dead_reckoning_clock.h"

#include <algorithm>

#include "channel/sim_clock.h"

namespace behaviorlib::server {

DeadReckoningClock::DeadReckoningClock(channel::SimClock& source, std::chrono::nanoseconds grace)
    : source_(source), grace_(grace), last_sample_(std::chrono::steady_clock::now()) {
  source_.addListener(this);
}

DeadReckoningClock::~DeadReckoningClock() { source_.removeListener(this); }

void DeadReckoningClock::onClockAdvanced() {
  {
    std::lock_guard lock(mutex_);
    last_sample_ = std::chrono::steady_clock::now();
  }
  notifyListeners();
}

std::chrono::nanoseconds DeadReckoningClock::silenceBeyondGrace(double* scale) const {
  *scale = source_.timeScale();
  if (!source_.valid() || source_.paused() || !(*scale > 0.0)) return {};
  std::lock_guard lock(mutex_);
  const auto silent = std::chrono::steady_clock::now() - last_sample_;
  return silent > grace_ ? std::chrono::duration_cast<std::chrono::nanoseconds>(silent - grace_)
                         : std::chrono::nanoseconds::zero();
}

TimePoint DeadReckoningClock::now() const {
  double scale = 0.0;
  const auto beyond = silenceBeyondGrace(&scale);
  const TimePoint t = source_.now();
  if (beyond <= std::chrono::nanoseconds::zero()) return t;
  return t + std::chrono::duration_cast<Duration>(std::chrono::duration<double, std::nano>(
                 static_cast<double>(beyond.count()) * scale));
}

std::chrono::nanoseconds DeadReckoningClock::wallWaitFor(Duration remaining) const {
  return std::min<std::chrono::nanoseconds>(source_.wallWaitFor(remaining),
                                            std::chrono::milliseconds(50));
}

bool DeadReckoningClock::valid() const { return source_.valid(); }

bool DeadReckoningClock::deadReckoning() const {
  double scale = 0.0;
  return silenceBeyondGrace(&scale) > std::chrono::nanoseconds::zero();
}

}  // namespace behaviorlib::server
