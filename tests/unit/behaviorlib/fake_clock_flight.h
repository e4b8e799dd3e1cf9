#pragma once

// Flies behaviors on a FakeClock: advances the clock step by step and, after
// each step, waits (wall time, bounded) until every behavior of the host ran
// everything due by the new time (BehaviorHost::caughtUp). A busy machine
// makes a test slower; it never makes a behavior skip a tick (a late tick
// moves the schedule instead of bursting, so a fixed wall-time pause per
// step lost ticks under load: 5 setpoints in 200 ms of a 100 Hz behavior).
//
//   flyOnFakeClock(clock_, host_, std::chrono::seconds(2), milliseconds(10), controller_);

#include <gtest/gtest.h>

#include <chrono>
#include <functional>
#include <thread>

#include "behaviorlib/behavior_execution_manager.h"
#include "behaviorlib/behavior_host.h"
#include "behaviorlib/clock.h"

namespace behaviorlib::testing {

/// Advances `clock` by `step` until `total` passed or `behavior` ended,
/// waiting after each step for `host`'s behaviors to catch up, then calling
/// `each`.
inline void flyOnFakeClock(FakeClock& clock, const BehaviorHost& host, Duration total,
                           Duration step, const BehaviorExecutionManager* behavior,
                           const std::function<void()>& each = nullptr) {
  for (Duration done{0}; done < total; done += step) {
    clock.advance(step);
    const auto limit = std::chrono::steady_clock::now() + std::chrono::seconds(10);
    while (!host.caughtUp(clock.now())) {
      if (std::chrono::steady_clock::now() > limit) {
        ADD_FAILURE() << "the behaviors did not catch up with the fake clock in 10 s";
        return;
      }
      std::this_thread::sleep_for(std::chrono::microseconds(100));
    }
    if (each) each();
    if (behavior->state() == v1::BEHAVIOR_STATE_INACTIVE) return;
  }
}

}  // namespace behaviorlib::testing
