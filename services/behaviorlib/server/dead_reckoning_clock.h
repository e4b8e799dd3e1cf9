#pragma once

// DeadReckoningClock: simulated time that keeps running when its source goes
// silent. It follows a SimClock (the simulator's `clock` topic) exactly while
// samples arrive; when none has arrived for `grace` of wall time although the
// last one said the simulation was running (time scale > 0, not paused), it
// advances at that time scale from where it stopped. So a behavior system
// whose simulator died still ticks, and its staleness checks (pose older
// than a few periods, all on this clock) report PROCESS_FAILURE instead of
// freezing with the dead simulator's time. In lock-step or while paused the
// clock stays put: there simulated time legitimately stands still.
//
//   channel::SimClock sim(channel_client);
//   DeadReckoningClock clock(sim, std::chrono::seconds(1));
//   clock.now();   // sim.now() while fresh; extrapolated after 1 s of silence
//
// When samples come back the clock follows them again (a restarted simulator
// starts its time anew, as after Simulator.Reset).

#include <chrono>
#include <mutex>

#include "behaviorlib/clock.h"

namespace behaviorlib::channel {
class SimClock;
}  // namespace behaviorlib::channel

namespace behaviorlib::server {

class DeadReckoningClock final : public Clock, private ClockListener {
 public:
  /// `source` must outlive this clock.
  DeadReckoningClock(channel::SimClock& source, std::chrono::nanoseconds grace);
  ~DeadReckoningClock() override;

  TimePoint now() const override;
  /// The source's bound (at most 50 ms), so that waiters re-read now() while
  /// dead reckoning, when no sample wakes them.
  std::chrono::nanoseconds wallWaitFor(Duration remaining) const override;
  bool valid() const override;

  /// Whether time is being extrapolated (the source has been silent for
  /// longer than the grace while the simulation was running).
  bool deadReckoning() const;

 private:
  void onClockAdvanced() override;
  // Wall time the source has been silent beyond the grace (zero if not), and
  // the scale to extrapolate with.
  std::chrono::nanoseconds silenceBeyondGrace(double* scale) const;

  channel::SimClock& source_;
  const std::chrono::nanoseconds grace_;
  mutable std::mutex mutex_;
  std::chrono::steady_clock::time_point last_sample_;
};

}  // namespace behaviorlib::server
