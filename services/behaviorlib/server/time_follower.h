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
// what the client published is synced to the broker.
//
//   channel::SimClock clock(channel);
//   TimeFollower follower("127.0.0.1:50070", "basic_quadrotor_behaviors/drone1", clock,
//                         &channel, [&](TimePoint t) { return host.caughtUp(t); },
//                         [&] { return host.idle(); });
//
// A report also says whether the system is idle (no behavior active): the
// simulator does not wait for idle systems.
//
// It reconnects (100 ms .. 2 s) while it lives; a simulator that is not in
// the deterministic mode refuses (FAILED_PRECONDITION) and is asked again.

#include <grpcpp/grpcpp.h>

#include <atomic>
#include <condition_variable>
#include <functional>
#include <memory>
#include <mutex>
#include <string>
#include <thread>

#include "behaviorlib/clock.h"

namespace behaviorlib::channel {
class ChannelClient;
class SimClock;
}  // namespace behaviorlib::channel

namespace behaviorlib::server {

class TimeFollower {
 public:
  TimeFollower(const std::string& simulator_address, std::string participant,
               channel::SimClock& clock, channel::ChannelClient* channel,
               std::function<bool(TimePoint)> caught_up, std::function<bool()> idle);
  /// Cancels the stream and joins the thread.
  ~TimeFollower();
  TimeFollower(const TimeFollower&) = delete;
  TimeFollower& operator=(const TimeFollower&) = delete;

  /// Grants reported back so far.
  uint64_t reportedCount() const { return reported_.load(); }

 private:
  void run();
  bool isStopping();
  // Waits until done() (polling), or stop; false when stopping.
  bool awaitUntil(const std::function<bool()>& done);

  const std::string participant_;
  channel::SimClock& clock_;
  channel::ChannelClient* const data_;  // may be null
  const std::function<bool(TimePoint)> caught_up_;
  const std::function<bool()> idle_;
  std::shared_ptr<grpc::Channel> channel_;
  std::atomic<uint64_t> reported_{0};

  std::mutex mutex_;
  std::condition_variable cv_;
  grpc::ClientContext* context_ = nullptr;
  bool stopping_ = false;
  std::thread thread_;  // last
};

}  // namespace behaviorlib::server
