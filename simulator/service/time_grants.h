#pragma once

// TimeGrants: the deterministic mode's barrier (simulator --time-scale max).
// The simulator advances time by a quantum, then grantAndWait() sends the new
// time to every follower (Simulator.FollowTime streams, one per behavior
// system) and waits until each has reported that it did everything due up to
// it. A starved follower slows the simulation instead of missing deadlines; a
// follower silent for `follower_timeout` of wall time after a grant is left
// out of the waits until it reports again (a frozen or dead process must not
// stop the world), and one whose stream ends is forgotten. A follower whose
// last report said it is idle (no behavior active) is granted but not waited
// for.
//
//   TimeGrants grants(std::chrono::seconds(5));
//   SimulatorService::setTimeGrants(&grants);   // serves FollowTime
//   grants.waitForFollowers(9, stop);
//   while (!stop) { simulation.advance(10ms); grants.grantAndWait(grant, stop); }

#include <grpcpp/grpcpp.h>

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <functional>
#include <map>
#include <mutex>
#include <optional>
#include <set>
#include <string>
#include <vector>

#include "behaviorlib/server_kit/access_policy.h"
#include "behaviorlib/v1/simulator.pb.h"
#include "simulator/service/setpoint_barrier.h"

namespace behaviorlib::sim {

class TimeGrants {
 public:
  explicit TimeGrants(std::chrono::nanoseconds follower_timeout);
  /// Ends every stream (shutdown() must have been called, or no stream is
  /// left).
  ~TimeGrants();
  TimeGrants(const TimeGrants&) = delete;
  TimeGrants& operator=(const TimeGrants&) = delete;

  /// The FollowTime handler.
  /// A FollowTime stream of a caller whose robot scope is `scope`: refused
  /// (ROBOT_NOT_PERMITTED) when it reports for another robot.
  grpc::ServerBidiReactor<v1::FollowTimeRequest, v1::FollowTimeResponse>* follow(
      server_kit::RobotScope scope = {});

  /// Waits until at least `count` followers joined (or `stop`).
  void waitForFollowers(int count, const std::atomic<bool>& stop);
  /// Grants `grant` (its clock a lock-step sample; the data barrier's
  /// topic_seqs of the simulator's own samples, to which the followers' last
  /// reported topic_seqs are added) to every follower and waits until each
  /// has caught up with it, left, or timed out (or `stop`). Returns the
  /// number of followers that caught up.
  int grantAndWait(v1::FollowTimeResponse grant, const std::atomic<bool>& stop);
  /// The same, where followers read different brokers (a broker per
  /// vehicle): `seqs` holds the simulator's numbers per domain, and a
  /// follower's grant names those of its domain and what the followers of
  /// its domain reported, nothing of another broker's numbering.
  using DomainSeqs = std::map<std::string, std::map<std::string, uint64_t>>;
  int grantAndWait(v1::FollowTimeResponse grant, const DomainSeqs& seqs,
                   const std::atomic<bool>& stop);
  /// The domain (the broker) of a follower of `robot_id` (FollowTimeRequest.
  /// robot_id); by default every follower shares one (""). Set before the
  /// first follower joins.
  void setDomainOf(std::function<std::string(const std::string& robot_id)> domain_of);
  /// The setpoints the followers report (FollowTimeRequest.
  /// setpoints_written) are waited for in `barrier` before grantAndWait()
  /// returns, so the next step applies them (at most kSetpointWaitLimit of
  /// wall time, told once). Set before the first follower joins.
  void setSetpointBarrier(SetpointBarrier* barrier);

  /// Whether a follower is busy now (its last report or wake said so, and
  /// it is not left out for silence): the simulator waits for it.
  bool anyBusy() const;

  /// Ends every FollowTime stream (UNAVAILABLE) and refuses new ones.
  void shutdown();

  /// Followers connected now; grants waited on so far; followers dropped
  /// from a wait for silence.
  int followerCount() const;
  uint64_t grantCount() const { return grants_.load(); }
  uint64_t timeoutCount() const { return timeouts_.load(); }

 private:
  class Follower;
  void joined(Follower* follower);
  void reported(Follower* follower);
  void left(Follower* follower);
  // The reports' part of grantAndWait (under mutex_).
  int awaitReports(v1::FollowTimeResponse grant, const DomainSeqs& seqs,
                   const std::atomic<bool>& stop);
  // The setpoints reported since the last call, waited for in the barrier.
  void awaitSetpoints();

  const std::chrono::nanoseconds follower_timeout_;
  mutable std::mutex mutex_;
  std::condition_variable cv_;
  std::set<Follower*> followers_;
  // A grant of one domain: the time, and every topic's number there (the
  // simulator's and what that domain's followers reported).
  struct DomainGrant {
    v1::FollowTimeResponse grant;  // without topic_seqs
    std::map<std::string, uint64_t> seqs;
  };
  // What `follower` is sent of `domain_grant`: the numbers of the topics it
  // awaits (all of them when it did not say which).
  static v1::FollowTimeResponse grantFor(const DomainGrant& domain_grant, const Follower& follower);
  // The last grant of each domain (a follower that joins starts from it).
  std::map<std::string, DomainGrant> last_grants_;
  std::function<std::string(const std::string&)> domain_of_;
  bool shutting_down_ = false;
  SetpointBarrier* setpoint_barrier_ = nullptr;
  bool told_setpoint_timeout_ = false;  // the stepping thread's
  std::atomic<uint64_t> grants_{0};
  std::atomic<uint64_t> timeouts_{0};
};

}  // namespace behaviorlib::sim
