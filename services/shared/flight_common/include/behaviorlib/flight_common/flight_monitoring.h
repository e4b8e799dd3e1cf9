#pragma once

// Small, clock-driven pieces of the flight behaviors' monitoring, kept free of
// any I/O so that unit tests drive them with a FakeClock's times:
//
//   DwellTracker dwell(std::chrono::seconds(1));
//   if (dwell.update(now(), std::abs(z - target) <= 0.1)) -> goal held for 1 s
//
//   ProgressWindow climb(std::chrono::seconds(3));
//   climb.add(now(), z);
//   if (climb.full() && climb.change() < 0.1) -> no climb over the last 3 s

#include <deque>
#include <optional>
#include <string>
#include <utility>

#include "behaviorlib/clock.h"

namespace behaviorlib::flight {

/// Whether a condition has held without interruption for a dwell time.
class DwellTracker {
 public:
  explicit DwellTracker(Duration dwell) : dwell_(dwell) {}
  /// Feeds the condition's value at `now`; true once it has held
  /// continuously since at least `dwell` before `now`.
  bool update(TimePoint now, bool holds);
  /// Forgets the history (e.g. after the target changed).
  void reset() { since_.reset(); }
  /// How long the condition has held at `now` (zero if it does not).
  Duration heldFor(TimePoint now) const;
  Duration dwell() const { return dwell_; }
  void setDwell(Duration dwell) { dwell_ = dwell; }

 private:
  Duration dwell_;
  std::optional<TimePoint> since_;
};

/// A scalar's samples over a sliding time window, to tell how much it changed
/// over the last `window` (climb, descent).
class ProgressWindow {
 public:
  explicit ProgressWindow(Duration window) : window_(window) {}
  /// Adds a sample; samples must come in time order (an older one is
  /// ignored).
  void add(TimePoint t, double value);
  void reset() { samples_.clear(); }
  /// True once the samples span at least the window.
  bool full() const;
  /// The newest value minus the value one window earlier (the oldest kept
  /// sample); 0 without samples.
  double change() const;
  Duration window() const { return window_; }
  void setWindow(Duration window) { window_ = window; }

 private:
  Duration window_;
  std::deque<std::pair<TimePoint, double>> samples_;
};

/// The performance ratio a flight behavior reports for a battery state of
/// charge: 1 at or above `full_ratio`, falling linearly to 0.2 at
/// `min_ratio`, 0 below it.
double batteryPerformance(double battery_ratio, double min_ratio, double full_ratio);

/// Seconds as text for messages: "0.25 s".
std::string secondsText(Duration d);

/// A number with two decimals: "1.50".
std::string fixed2(double value);

}  // namespace behaviorlib::flight
