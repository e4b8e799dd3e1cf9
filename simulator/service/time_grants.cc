#include "simulator/service/time_grants.h"

#include <google/protobuf/util/time_util.h>

#include <algorithm>
#include <cstdio>
#include <map>
#include <optional>
#include <vector>

#include "behaviorlib/error_details.h"
#include "behaviorlib/server_kit/reactor_order.h"

namespace behaviorlib::sim {
namespace {

using google::protobuf::util::TimeUtil;

// How often waits look at the stop flag.
constexpr std::chrono::milliseconds kStopPoll(100);
// An idle follower gets a grant when at least this much simulated time has
// passed since the last one it was sent (or when it wakes): its clock is only
// read by commands from outside, which first wake it and wait for a current
// grant.
constexpr int64_t kIdleGrantPeriodNs = 1'000'000'000;
// The longest wait for reported setpoints (wall time): a stream that a
// follower's report names may never arrive (its process died in between).
constexpr std::chrono::seconds kSetpointWaitLimit(2);
// The most setpoint streams one report may name.
constexpr int kMaxReportedSetpointStreams = 64;

}  // namespace

// One FollowTime stream: reads reports one at a time, writes the newest
// grant (one write in flight; a newer grant replaces an unsent one).
class TimeGrants::Follower final
    : public server_kit::Ordered<
          grpc::ServerBidiReactor<v1::FollowTimeRequest, v1::FollowTimeResponse>> {
 public:
  Follower(TimeGrants* owner, server_kit::RobotScope scope)
      : owner_(owner), scope_(std::move(scope)) {}

  void start() { StartRead(&request_); }

  // Guarded by the owner's mutex.
  std::string name;
  std::string domain;  // its broker's (TimeGrants::setDomainOf)
  bool joined = false;
  bool silent = false;  // left out of the waits until it reports again
  // Said so in its last report (and no wake since): not waited for. Written
  // under the owner's mutex; read when a grant is written.
  std::atomic<bool> idle{false};
  // What it published, from its last report (FollowTimeRequest.topic_seqs).
  std::map<std::string, uint64_t> topic_seqs;
  // The topics its data barrier waits on (FollowTimeRequest.awaited_topics),
  // sorted; unset: every topic.
  std::optional<std::vector<std::string>> awaited_topics;
  // The setpoints its reports said it wrote, per stream key, not yet waited
  // for (FollowTimeRequest.setpoints_written).
  std::map<std::string, uint64_t> setpoints_written;
  int64_t caught_up_ns = -1;

  const v1::FollowTimeRequest& request() const { return request_; }

  // One grant in flight: the next (the newest pending) goes once the
  // follower reported the previous one. A write completes when the message
  // is in the transport's buffers, not when the follower read it, so without
  // this an idle follower (not waited for) would fall behind by every grant
  // buffered on its stream. An idle follower's grant waits as pending until
  // a simulated second passed since its last one, or it wakes.
  void grant(v1::FollowTimeResponse grant) {
    std::lock_guard lock(mutex_);
    if (finished_) return;
    pending_.Swap(&grant);
    has_pending_ = true;
    if (!writing_ && !awaiting_report_ && dueLocked()) writeLocked();
  }

  // A wake: the newest pending grant goes now (it says "awaited").
  void woken() {
    std::lock_guard lock(mutex_);
    if (has_pending_ && !writing_ && !awaiting_report_ && !finished_) writeLocked();
  }

  void finish(const grpc::Status& status) {
    std::lock_guard lock(mutex_);
    if (finished_) return;
    finished_ = true;
    Finish(status);
  }

  void OnReadDone(bool ok) override {
    ordered();
    if (!ok) {
      finish(grpc::Status::OK);  // the follower half-closed or went away
      return;
    }
    if (!checked_) {
      // A caller bound to a robot follows the time only for its own (its
      // reports gate that robot's broker's grants).
      checked_ = true;
      if (absl::Status s = scope_.permits(request_.robot_id(), "follow the time"); !s.ok()) {
        finish(errors::toGrpc(s));
        return;
      }
    }
    const bool report = request_.has_caught_up_to();
    const bool wake = request_.wake();
    owner_->reported(this);
    if (report) {
      std::lock_guard lock(mutex_);
      awaiting_report_ = false;
      if (has_pending_ && !writing_ && !finished_ && dueLocked()) writeLocked();
    } else if (wake) {
      woken();
    }
    StartRead(&request_);
  }

  void OnWriteDone(bool ok) override {
    ordered();
    std::lock_guard lock(mutex_);
    writing_ = false;
    if (!ok) {
      if (!finished_) {
        finished_ = true;
        Finish(grpc::Status(grpc::StatusCode::CANCELLED, "the follower's stream broke"));
      }
      return;
    }
    if (has_pending_ && !finished_ && !awaiting_report_ && dueLocked()) writeLocked();
  }

  void OnDone() override {
    ordered();
    owner_->left(this);
    delete this;
  }

 private:
  // Whether the pending grant goes now: always to a busy follower, to an idle
  // one a simulated second after its last grant.
  bool dueLocked() const {
    if (!idle.load()) return true;
    return last_written_ns_ < 0 ||
           TimeUtil::TimestampToNanoseconds(pending_.clock().time()) - last_written_ns_ >=
               kIdleGrantPeriodNs;
  }

  void writeLocked() {
    current_.Swap(&pending_);
    // Read after the follower's last report or wake was applied: if it is
    // busy now, the simulator waits for its report of this grant.
    current_.set_awaited(!idle.load());
    last_written_ns_ = TimeUtil::TimestampToNanoseconds(current_.clock().time());
    has_pending_ = false;
    writing_ = true;
    awaiting_report_ = true;
    StartWrite(&current_);
  }

  TimeGrants* const owner_;
  v1::FollowTimeRequest request_;  // one read at a time
  std::mutex mutex_;
  v1::FollowTimeResponse pending_, current_;
  bool has_pending_ = false;
  bool writing_ = false;
  bool awaiting_report_ = false;  // a grant was written, its report not read yet
  bool finished_ = false;
  const server_kit::RobotScope scope_;  // the caller's
  bool checked_ = false;                // its first report's robot (OnReadDone only)
  int64_t last_written_ns_ = -1;        // the time of the last grant written
};

TimeGrants::TimeGrants(std::chrono::nanoseconds follower_timeout)
    : follower_timeout_(follower_timeout) {}

TimeGrants::~TimeGrants() { shutdown(); }

grpc::ServerBidiReactor<v1::FollowTimeRequest, v1::FollowTimeResponse>* TimeGrants::follow(
    server_kit::RobotScope scope) {
  auto* follower = new Follower(this, std::move(scope));
  bool refuse = false;
  {
    std::lock_guard lock(mutex_);
    refuse = shutting_down_;
  }
  if (refuse) {
    follower->finish(errors::grpcError(grpc::StatusCode::UNAVAILABLE, v1::SHUTTING_DOWN,
                                       "the simulator is stopping"));
  } else {
    follower->start();
  }
  return follower;
}

void TimeGrants::reported(Follower* follower) {
  std::optional<v1::FollowTimeResponse> catch_up;
  {
    std::lock_guard lock(mutex_);
    const bool joining = !follower->joined;
    if (joining) {
      follower->joined = true;
      follower->name = follower->request().participant();
      follower->domain = domain_of_ ? domain_of_(follower->request().robot_id()) : "";
      followers_.insert(follower);
      std::fprintf(stderr, "simulator: %s follows the time grants (%zu followers)\n",
                   follower->name.c_str(), followers_.size());
    }
    if (follower->request().has_awaited_topics()) {
      const auto& topics = follower->request().awaited_topics().topics();
      follower->awaited_topics.emplace(topics.begin(), topics.end());
      std::sort(follower->awaited_topics->begin(), follower->awaited_topics->end());
    }
    if (joining) {
      // It starts from the current grant.
      if (auto it = last_grants_.find(follower->domain); it != last_grants_.end()) {
        catch_up = grantFor(it->second, *follower);
      } else if (!last_grants_.empty()) {
        catch_up = last_grants_.begin()->second.grant;
      }
    }
    if (follower->request().wake()) {
      follower->idle = false;  // waited for from the next grant on
      follower->silent = false;
    } else if (follower->request().has_caught_up_to()) {
      follower->caught_up_ns = TimeUtil::TimestampToNanoseconds(follower->request().caught_up_to());
      follower->silent = false;
      follower->idle = follower->request().idle();
      follower->topic_seqs.clear();
      for (const auto& [topic, seq] : follower->request().topic_seqs()) {
        follower->topic_seqs[topic] = seq;
      }
      if (setpoint_barrier_ != nullptr) {
        int named = 0;
        for (const auto& [key, count] : follower->request().setpoints_written()) {
          if (++named > kMaxReportedSetpointStreams) break;
          uint64_t& written = follower->setpoints_written[key];
          written = std::max(written, count);
        }
      }
    }
  }
  cv_.notify_all();
  if (catch_up) follower->grant(std::move(*catch_up));
}

void TimeGrants::left(Follower* follower) {
  {
    std::lock_guard lock(mutex_);
    if (followers_.erase(follower) > 0) {
      std::fprintf(stderr, "simulator: %s stopped following the time grants\n",
                   follower->name.c_str());
    }
  }
  cv_.notify_all();
}

void TimeGrants::waitForFollowers(int count, const std::atomic<bool>& stop) {
  std::unique_lock lock(mutex_);
  while (!stop.load() && !shutting_down_ && static_cast<int>(followers_.size()) < count) {
    cv_.wait_for(lock, kStopPoll);
  }
}

void TimeGrants::setDomainOf(std::function<std::string(const std::string&)> domain_of) {
  std::lock_guard lock(mutex_);
  domain_of_ = std::move(domain_of);
}

int TimeGrants::grantAndWait(v1::FollowTimeResponse grant, const std::atomic<bool>& stop) {
  DomainSeqs seqs;
  auto& own = seqs[""];
  for (const auto& [topic, seq] : grant.topic_seqs()) own[topic] = seq;
  grant.clear_topic_seqs();
  return grantAndWait(std::move(grant), seqs, stop);
}

void TimeGrants::setSetpointBarrier(SetpointBarrier* barrier) {
  std::lock_guard lock(mutex_);
  setpoint_barrier_ = barrier;
}

int TimeGrants::grantAndWait(v1::FollowTimeResponse grant, const DomainSeqs& seqs,
                             const std::atomic<bool>& stop) {
  const int caught_up = awaitReports(std::move(grant), seqs, stop);
  awaitSetpoints();
  return caught_up;
}

void TimeGrants::awaitSetpoints() {
  std::map<std::string, uint64_t> written;
  {
    std::lock_guard lock(mutex_);
    if (setpoint_barrier_ == nullptr) return;
    for (Follower* follower : followers_) {
      for (const auto& [key, count] : follower->setpoints_written) {
        uint64_t& n = written[key];
        n = std::max(n, count);
      }
      follower->setpoints_written.clear();
    }
  }
  if (setpoint_barrier_->awaitRead(written, kSetpointWaitLimit) || told_setpoint_timeout_) return;
  told_setpoint_timeout_ = true;
  std::fprintf(stderr,
               "simulator: setpoints a follower reported did not arrive within %lld s of wall "
               "time; stepping on without them (told once)\n",
               static_cast<long long>(kSetpointWaitLimit.count()));
}

int TimeGrants::awaitReports(v1::FollowTimeResponse grant, const DomainSeqs& seqs,
                             const std::atomic<bool>& stop) {
  const int64_t t = TimeUtil::TimestampToNanoseconds(grant.clock().time());
  grant.clear_topic_seqs();
  std::unique_lock lock(mutex_);
  // Per domain: the simulator's numbers there, and what its followers
  // published before their last reports.
  std::map<std::string, DomainGrant> grants;
  for (const auto& [domain, topics] : seqs) {
    DomainGrant& g = grants[domain];
    g.grant = grant;
    g.seqs = topics;
  }
  for (const Follower* follower : followers_) {
    auto [it, added] = grants.try_emplace(follower->domain);
    if (added) it->second.grant = grant;
    for (const auto& [topic, seq] : follower->topic_seqs) {
      uint64_t& named = it->second.seqs[topic];
      named = std::max(named, seq);
    }
  }
  ++grants_;
  // Each follower is sent the numbers of the topics it awaits only.
  for (Follower* follower : followers_) {
    follower->grant(grantFor(grants.at(follower->domain), *follower));
  }
  last_grants_ = std::move(grants);
  const auto deadline = std::chrono::steady_clock::now() + follower_timeout_;
  while (true) {
    int caught_up = 0;
    int waiting = 0;
    for (const Follower* follower : followers_) {
      if (follower->caught_up_ns >= t) {
        ++caught_up;
      } else if (!follower->silent && !follower->idle) {
        ++waiting;
      }
    }
    if (waiting == 0 || stop.load() || shutting_down_) return caught_up;
    if (std::chrono::steady_clock::now() >= deadline) {
      for (Follower* follower : followers_) {
        if (follower->caught_up_ns >= t || follower->silent || follower->idle) continue;
        follower->silent = true;
        ++timeouts_;
        std::fprintf(stderr,
                     "simulator: %s did not catch up within %.1f s of wall time; time goes on "
                     "without waiting for it until it reports again\n",
                     follower->name.c_str(),
                     std::chrono::duration<double>(follower_timeout_).count());
      }
      return caught_up;
    }
    cv_.wait_until(lock, std::min(deadline, std::chrono::steady_clock::now() + kStopPoll));
  }
}

v1::FollowTimeResponse TimeGrants::grantFor(const DomainGrant& domain_grant,
                                            const Follower& follower) {
  v1::FollowTimeResponse grant = domain_grant.grant;
  auto& named = *grant.mutable_topic_seqs();
  if (!follower.awaited_topics) {
    for (const auto& [topic, seq] : domain_grant.seqs) named[topic] = seq;
    return grant;
  }
  for (const std::string& topic : *follower.awaited_topics) {
    if (auto it = domain_grant.seqs.find(topic); it != domain_grant.seqs.end()) {
      named[topic] = it->second;
    }
  }
  return grant;
}

void TimeGrants::shutdown() {
  {
    // Under mutex_: a follower's OnDone (which deletes it) waits for it in
    // left(), and Finish never runs a reaction inline.
    std::lock_guard lock(mutex_);
    shutting_down_ = true;
    for (Follower* follower : followers_) {
      follower->finish(errors::grpcError(grpc::StatusCode::UNAVAILABLE, v1::SHUTTING_DOWN,
                                         "the simulator is stopping"));
    }
  }
  cv_.notify_all();
}

bool TimeGrants::anyBusy() const {
  std::lock_guard lock(mutex_);
  return std::any_of(followers_.begin(), followers_.end(),
                     [](const Follower* f) { return !f->idle && !f->silent; });
}

int TimeGrants::followerCount() const {
  std::lock_guard lock(mutex_);
  return static_cast<int>(followers_.size());
}

}  // namespace behaviorlib::sim
