#pragma once

// TimeFollower: a behavior system's side of the deterministic mode
// (simulator --time-scale max). It follows the simulator's time grants
// (Simulator.FollowTime): each granted time goes into the system's SimClock,
// and once every behavior has run everything due up to it (`caught_up`), the
// time is reported back, and only then does the simulator go on. So a
// starved system slows the simulation instead of missing its deadlines.
//
// With a channel client, grants are also a data barrier: before the clock
// moves, each subscription of the client waits for the sample the grant
// names for its topic (FollowTimeResponse.topic_seqs), and before the report,
// what the client published is synced to the broker. With a SetpointLedger,
// a report also names the setpoints the process wrote to the simulator, which
// applies them before it steps on (setpoint_ledger.h).
//
//   channel::SimClock clock(channel);
//   TimeFollower follower("127.0.0.1:50070", "basic_quadrotor_behaviors/drone1", clock,
//                         &channel);
//   BehaviorHost host({.before_command = [&] { follower.awaitTurn(); }}, clock);
//   ... host.start(config) ...
//   follower.start([&](TimePoint t) { return host.caughtUp(t); },
//                  [&] { return host.idle(); });
//   ...
//   follower.stop();   // leaves the barrier; awaitTurn() no longer waits
//
// A report also says whether the system is idle (no behavior active, no
// command queued): the simulator does not wait for an idle system, and sends
// it a grant only about once a simulated second, so its clock lags. A command
// from outside (an activation, a CheckSituation) therefore first waits in
// awaitTurn(): it wakes the system (FollowTimeRequest.wake), and runs once an
// "awaited" grant (one the simulator waits for) has moved the clock, so that
// it starts at the simulation's time and the simulator waits for the system
// from then on (without this an activation ran at the lagging time, and the
// next grant jumped its behaviors forward by as much as a second:
// stale-status and lost-lease failures under load).
//
// It reconnects (100 ms .. 2 s) while it lives; a simulator that is not in
// the deterministic mode refuses (FAILED_PRECONDITION) and is asked again.

#include <grpcpp/grpcpp.h>

#include <atomic>
#include <functional>
#include <memory>
#include <string>
#include <thread>

#include "absl/base/thread_annotations.h"
#include "absl/synchronization/mutex.h"
#include "behaviorlib/clock.h"

namespace behaviorlib::channel {
class ChannelClient;
class SimClock;
}  // namespace behaviorlib::channel

namespace behaviorlib::server {

class SetpointLedger;

class TimeFollower {
 public:
  /// `robot_id` names the vehicle whose broker `channel` is (the data
  /// barrier's numbers are that broker's; FollowTimeRequest.robot_id).
  /// `setpoints` (may be null) counts the setpoints the process streams to
  /// the simulator; each report names its counts.
  TimeFollower(const std::string& simulator_address, std::string participant,
               channel::SimClock& clock, channel::ChannelClient* channel, std::string robot_id = "",
               SetpointLedger* setpoints = nullptr);
  /// stop()s.
  ~TimeFollower();
  TimeFollower(const TimeFollower&) = delete;
  TimeFollower& operator=(const TimeFollower&) = delete;

  /// Joins the simulator's grants and follows them on a thread of its own;
  /// `caught_up(t)`: everything due up to t ran; `idle()`: nothing runs
  /// until a call from outside. At most once.
  void start(std::function<bool(TimePoint)> caught_up, std::function<bool()> idle);
  /// Cancels the stream and joins the thread; idempotent.
  void stop();

  /// The time gate of commands from outside (BehaviorContext::
  /// before_command): returns at once while the simulator waits for this
  /// system or no grants are followed; otherwise wakes the system (a
  /// FollowTimeRequest.wake) and waits (at most kTurnLimit of wall time, told
  /// once) until an "awaited" grant moved the clock. The caller must make
  /// idle() false before it calls (BehaviorExecutionManager does).
  void awaitTurn();

  /// Grants reported back so far.
  uint64_t reportedCount() const { return reported_.load(); }

 private:
  void run();
  bool isStopping();
  // Waits until done() (polling), or stop; false when stopping.
  bool awaitUntil(const std::function<bool()>& done);

  const std::string participant_;
  const std::string robot_id_;
  channel::SimClock& clock_;
  channel::ChannelClient* const data_;  // may be null
  SetpointLedger* const setpoints_;     // may be null
  std::function<bool(TimePoint)> caught_up_;
  std::function<bool()> idle_;
  std::shared_ptr<grpc::Channel> channel_;
  std::atomic<uint64_t> reported_{0};

  // awaitTurn() waits on mutex_ (Mutex::Await) for the gate or the stop.
  absl::Mutex mutex_;
  grpc::ClientContext* context_ ABSL_GUARDED_BY(mutex_) = nullptr;
  bool stopping_ ABSL_GUARDED_BY(mutex_) = false;
  // The gate (guarded by mutex_): a grant was applied on the current stream;
  // the applied grant was "awaited" and no idle report went since (the
  // simulator waits for us); a wake was sent since the last grant; how to
  // send one on the current stream.
  bool streaming_ ABSL_GUARDED_BY(mutex_) = false;
  bool awaited_ ABSL_GUARDED_BY(mutex_) = false;
  bool wake_sent_ ABSL_GUARDED_BY(mutex_) = false;
  std::function<void()> send_wake_ ABSL_GUARDED_BY(mutex_);
  bool told_turn_timeout_ ABSL_GUARDED_BY(mutex_) = false;
  // Serializes writes on the stream (reports from the thread, wakes from
  // awaitTurn); the stream generation whose writes are open.
  absl::Mutex write_mutex_;
  uint64_t open_stream_ ABSL_GUARDED_BY(write_mutex_) = 0;
  std::thread thread_;
};

}  // namespace behaviorlib::server
