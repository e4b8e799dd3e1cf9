#pragma once

// LeaseKeeper: holds a vehicle's command-source lease for as long as it
// lives. It acquires the lease, renews it from a thread of its own every
// quarter of its ttl (on the behavior's clock, since the platform's lease
// times are simulated time under a simulator), and releases it when
// destroyed. It listens to the clock: woken when simulated time moves, and
// in the deterministic mode a granted time is reported only once the
// renewals due up to it are done (ClockListener::caughtUp), so a starved
// renewal thread slows the simulation instead of losing the lease.
//
//   auto lease = LeaseKeeper::acquire(fc, clock, "drone1/TAKE_OFF", {.ttl = 2s});
//   if (!lease.ok()) return lease.status();
//   fc.executeFlightAction((*lease)->id(), v1::FLIGHT_ACTION_HOVER);
//   if (absl::Status s = (*lease)->status(); !s.ok()) { /* lost: preempted or unreachable */ }
//   lease->reset();   // releases

#include <chrono>
#include <memory>
#include <string>
#include <thread>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/synchronization/mutex.h"
#include "behaviorlib/clock.h"
#include "behaviorlib/platform/flight_controller_client.h"

namespace behaviorlib::platform {

struct LeaseOptions {
  /// How long the lease lives without a renewal (platform's clock); the
  /// platform's limits are 0.05..10 s.
  std::chrono::nanoseconds ttl = std::chrono::seconds(2);
  /// Take the lease even if another holder has it.
  bool preempt = false;
};

class LeaseKeeper {
 public:
  /// Acquires the lease (one blocking call) and starts renewing it. The
  /// client and the clock must outlive the keeper.
  static absl::StatusOr<std::unique_ptr<LeaseKeeper>> acquire(const FlightControllerClient& client,
                                                              const Clock& clock,
                                                              std::string holder,
                                                              LeaseOptions options = {});
  /// Stops renewing and releases the lease (best effort, one call).
  ~LeaseKeeper();
  LeaseKeeper(const LeaseKeeper&) = delete;
  LeaseKeeper& operator=(const LeaseKeeper&) = delete;

  const std::string& id() const { return lease_id_; }
  const std::string& holder() const { return holder_; }

  /// OK while the lease is held. FAILED_PRECONDITION once the platform
  /// refused a renewal (another holder took it, or it expired);
  /// UNAVAILABLE (or DEADLINE_EXCEEDED) once renewals have failed for
  /// longer than the ttl (the flight controller is unreachable).
  absl::Status status() const;
  /// Renewals that succeeded so far.
  uint64_t renewals() const;
  /// Stops renewing and releases the lease; its status afterwards.
  absl::Status release();

 private:
  LeaseKeeper(const FlightControllerClient& client, const Clock& clock, std::string holder,
              std::string lease_id, LeaseOptions options);
  class Listener;
  void run();
  void stopThread();
  bool caughtUp(TimePoint t) const;

  const FlightControllerClient& client_;
  const Clock& clock_;
  const std::string holder_;
  const std::string lease_id_;
  const LeaseOptions options_;

  // The renewal thread waits on mutex_ (Mutex::Await) for stopping_ or a
  // wake from the clock (wakes_ counts them).
  mutable absl::Mutex mutex_;
  bool stopping_ ABSL_GUARDED_BY(mutex_) = false;
  bool released_ ABSL_GUARDED_BY(mutex_) = false;
  uint64_t wakes_ ABSL_GUARDED_BY(mutex_) = 0;
  absl::Status lost_ ABSL_GUARDED_BY(mutex_);          // set once the lease is known lost
  absl::Status last_failure_ ABSL_GUARDED_BY(mutex_);  // the last failed renewal
  TimePoint last_renewed_ ABSL_GUARDED_BY(mutex_){};   // clock time of the last acquire/renew
  TimePoint next_ ABSL_GUARDED_BY(mutex_){};           // when the next renewal is due
  bool renewing_ ABSL_GUARDED_BY(mutex_) = false;      // a renewal call is under way
  uint64_t renewals_ ABSL_GUARDED_BY(mutex_) = 0;
  std::unique_ptr<Listener> listener_;
  std::thread thread_;
};

}  // namespace behaviorlib::platform
