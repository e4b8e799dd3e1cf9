#include "behaviorlib/flight_common/flight_monitoring.h"

#include <algorithm>
#include <cstdio>

namespace behaviorlib::flight {

bool DwellTracker::update(TimePoint now, bool holds) {
  if (!holds) {
    since_.reset();
    return false;
  }
  if (!since_) since_ = now;
  return now - *since_ >= dwell_;
}

Duration DwellTracker::heldFor(TimePoint now) const {
  return since_ ? now - *since_ : Duration::zero();
}

void ProgressWindow::add(TimePoint t, double value) {
  if (!samples_.empty() && t < samples_.back().first) return;
  samples_.emplace_back(t, value);
  // Keep exactly one sample at or before t - window: the reference point.
  while (samples_.size() >= 2 && samples_[1].first <= t - window_) samples_.pop_front();
}

bool ProgressWindow::full() const {
  return !samples_.empty() && samples_.back().first - samples_.front().first >= window_;
}

double ProgressWindow::change() const {
  return samples_.empty() ? 0.0 : samples_.back().second - samples_.front().second;
}

double batteryPerformance(double battery_ratio, double min_ratio, double full_ratio) {
  if (battery_ratio < min_ratio) return 0.0;
  if (battery_ratio >= full_ratio || full_ratio <= min_ratio) return 1.0;
  return 0.2 + 0.8 * (battery_ratio - min_ratio) / (full_ratio - min_ratio);
}

std::string secondsText(Duration d) {
  char text[32];
  std::snprintf(text, sizeof(text), "%.3g s", std::chrono::duration<double>(d).count());
  return text;
}

std::string fixed2(double value) {
  char text[32];
  std::snprintf(text, sizeof(text), "%.2f", value);
  return text;
}

}  // namespace behaviorlib::flight
