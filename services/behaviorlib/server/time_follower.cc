#include "behaviorlib/server/time_follower.h"

#include <google/protobuf/util/time_util.h>

#include <algorithm>
#include <cstdio>
#include <optional>

#include "absl/time/time.h"
#include "behaviorlib/channel/channel_client.h"
#include "behaviorlib/channel/sim_clock.h"
#include "behaviorlib/server/setpoint_ledger.h"
#include "behaviorlib/server_kit/transport_security.h"
#include "behaviorlib/v1/simulator.grpc.pb.h"

namespace behaviorlib::server {
namespace {

constexpr std::chrono::milliseconds kInitialBackoff(100);
constexpr std::chrono::milliseconds kMaxBackoff(2000);
// How often the behaviors' progress is looked at while catching up.
constexpr std::chrono::microseconds kCatchUpPoll(100);
// How often a wait for data looks whether the follower is stopping.
constexpr std::chrono::milliseconds kStopPoll(50);
// The longest wait for a granted sample (wall time).
constexpr std::chrono::milliseconds kDataWaitLimit(2000);
// The longest wait of a command for its turn (wall time): the simulator may
// be held up by another follower, for at most its --follower-timeout-s.
constexpr std::chrono::milliseconds kTurnLimit(6000);

TimePoint toTimePoint(const google::protobuf::Timestamp& t) {
  return TimePoint(std::chrono::seconds(t.seconds()) + std::chrono::nanoseconds(t.nanos()));
}

}  // namespace

TimeFollower::TimeFollower(const std::string& simulator_address, std::string participant,
                           channel::SimClock& clock, channel::ChannelClient* channel,
                           std::string robot_id, SetpointLedger* setpoints)
    : participant_(std::move(participant)),
      robot_id_(std::move(robot_id)),
      clock_(clock),
      data_(channel),
      setpoints_(setpoints),
      channel_(behaviorlib::server_kit::makeChannel(simulator_address)) {}

TimeFollower::~TimeFollower() { stop(); }

void TimeFollower::start(std::function<bool(TimePoint)> caught_up, std::function<bool()> idle) {
  absl::MutexLock lock(&mutex_);
  if (thread_.joinable() || stopping_) return;
  caught_up_ = std::move(caught_up);
  idle_ = std::move(idle);
  thread_ = std::thread([this] { run(); });
}

void TimeFollower::stop() {
  {
    absl::MutexLock lock(&mutex_);
    stopping_ = true;
    if (context_ != nullptr) context_->TryCancel();
  }
  if (thread_.joinable()) thread_.join();
}

void TimeFollower::awaitTurn() {
  absl::MutexLock lock(&mutex_);
  const auto ready = [this]() ABSL_EXCLUSIVE_LOCKS_REQUIRED(mutex_) {
    return stopping_ || !streaming_ || awaited_;
  };
  if (ready()) return;
  if (!wake_sent_ && send_wake_) {
    // The simulator may not be sending us grants (idle): ask for one.
    wake_sent_ = true;
    const std::function<void()> send = send_wake_;
    mutex_.Unlock();
    send();
    mutex_.Lock();
  }
  const bool turn = mutex_.AwaitWithTimeout(absl::Condition(&ready), absl::FromChrono(kTurnLimit));
  if (!turn && !told_turn_timeout_) {
    told_turn_timeout_ = true;
    std::fprintf(stderr,
                 "%s: a command waited %lld ms for the simulator's next time grant; running it "
                 "at the last granted time (told once)\n",
                 participant_.c_str(), static_cast<long long>(kTurnLimit.count()));
  }
}

bool TimeFollower::isStopping() {
  absl::MutexLock lock(&mutex_);
  return stopping_;
}

bool TimeFollower::awaitUntil(const std::function<bool()>& done) {
  while (!done()) {
    absl::MutexLock lock(&mutex_);
    // Until stopped, at most kCatchUpPoll.
    mutex_.AwaitWithTimeout(absl::Condition(&stopping_), absl::FromChrono(kCatchUpPoll));
    if (stopping_) return false;
  }
  return true;
}

void TimeFollower::run() {
  auto stub = v1::Simulator::NewStub(channel_);
  std::chrono::milliseconds backoff = kInitialBackoff;
  bool told_refusal = false;
  bool told_sync_failure = false;
  bool told_data_timeout = false;
  while (true) {
    grpc::ClientContext context;
    {
      absl::MutexLock lock(&mutex_);
      if (stopping_) return;
      context_ = &context;
    }
    auto stream = stub->FollowTime(&context);
    uint64_t generation = 0;
    {
      absl::MutexLock write_lock(&write_mutex_);
      generation = ++open_stream_;
    }
    // Writes on this stream, one at a time (write_mutex_ held); none once it
    // is closed.
    const auto write_locked = [this, generation, raw = stream.get()](const v1::FollowTimeRequest& m)
                                  ABSL_EXCLUSIVE_LOCKS_REQUIRED(write_mutex_) -> bool {
      return open_stream_ == generation && raw->Write(m);
    };
    const auto write = [this, write_locked](const v1::FollowTimeRequest& m) {
      absl::MutexLock write_lock(&write_mutex_);
      return write_locked(m);
    };
    const auto set_streaming = [this, &write](bool streaming) {
      if (data_ != nullptr) {
        // While grants come, what the behaviors publish is read only after
        // the report that follows the sync: it may wait for that sync in
        // the stream's buffer (one socket write per quantum, not one per
        // sample). Without grants, every sample goes out at once again,
        // those waiting too.
        data_->bufferUntilSync(streaming);
        if (!streaming) data_->sync().IgnoreError();
      }
      {
        absl::MutexLock lock(&mutex_);
        streaming_ = streaming;
        awaited_ = false;
        wake_sent_ = false;
        send_wake_ = nullptr;
        if (streaming) {
          send_wake_ = [write] {
            v1::FollowTimeRequest wake;
            wake.set_wake(true);
            write(wake);
          };
        }
      }
    };
    v1::FollowTimeRequest join;
    join.set_participant(participant_);
    join.set_robot_id(robot_id_);
    // The topics the data barrier waits on, named in the join and again
    // whenever they changed: the grants name only theirs.
    std::vector<std::string> awaited_topics;
    const auto name_awaited_topics = [this, &awaited_topics](v1::FollowTimeRequest& message,
                                                             bool always) {
      std::vector<std::string> topics;
      if (data_ != nullptr) topics = data_->awaitedTopics();
      if (topics == awaited_topics && !always) return;
      awaited_topics = std::move(topics);
      auto* named = message.mutable_awaited_topics()->mutable_topics();
      named->Add(awaited_topics.begin(), awaited_topics.end());
    };
    name_awaited_topics(join, true);
    std::optional<v1::Clock> last_granted;
    if (write(join)) {
      v1::FollowTimeResponse grant;
      while (stream->Read(&grant)) {
        backoff = kInitialBackoff;
        // The data barrier: what was published up to the grant is in
        // before the behaviors run.
        if (data_ != nullptr && !grant.topic_seqs().empty()) {
          const auto& seqs = grant.topic_seqs();
          const auto topic_seq = [&seqs](const std::string& topic) -> uint64_t {
            const auto it = seqs.find(topic);
            return it == seqs.end() ? 0 : it->second;
          };
          // Bounded: a restarted broker numbers its topics anew, and a
          // sample it dropped never comes; the behaviors then see what is
          // there, as when free running.
          const auto give_up = std::chrono::steady_clock::now() + kDataWaitLimit;
          bool stopping = false;
          while (!data_->waitDelivered(topic_seq, kStopPoll)) {
            if ((stopping = isStopping())) break;
            if (std::chrono::steady_clock::now() >= give_up) {
              if (!told_data_timeout) {
                std::fprintf(stderr,
                             "%s: a granted sample did not arrive within %lld ms; going on "
                             "without it (told once)\n",
                             participant_.c_str(), static_cast<long long>(kDataWaitLimit.count()));
                told_data_timeout = true;
              }
              break;
            }
          }
          if (stopping) break;
        }
        // Time does not move under a command or a tick still running for the
        // previous grant (an idle system is not waited for, so grants may
        // arrive while an activation runs: its start and its first tick
        // would read different times).
        if (last_granted) {
          const TimePoint previous = toTimePoint(last_granted->time());
          if (!awaitUntil([&] { return caught_up_(previous); })) break;
        }
        clock_.onClockSample(grant.clock());
        if (!last_granted) set_streaming(true);
        last_granted = grant.clock();
        {
          // "Awaited": the simulator waits for our report of this grant, and
          // the clock is current; a command held in awaitTurn() may run.
          absl::MutexLock lock(&mutex_);
          awaited_ = grant.awaited();
          wake_sent_ = false;
        }
        const TimePoint granted = toTimePoint(grant.clock().time());
        if (!awaitUntil([&] { return caught_up_(granted); })) break;
        // What the behaviors published reaches the broker before the report,
        // so that the next grant's topic_seqs include it.
        if (data_ != nullptr) {
          if (absl::Status s = data_->sync(); !s.ok() && !told_sync_failure) {
            std::fprintf(stderr, "%s: publishing before a time report failed: %s\n",
                         participant_.c_str(), std::string(s.message()).c_str());
            told_sync_failure = true;
          }
        }
        // Every grant is reported (the simulator sends the next one then);
        // an idle system's reports are not waited for.
        v1::FollowTimeRequest report;
        *report.mutable_caught_up_to() = grant.clock().time();
        if (data_ != nullptr) {
          for (const auto& [topic, seq] : data_->acceptedSeqs()) {
            (*report.mutable_topic_seqs())[topic] = seq;
          }
        }
        // The setpoints the behaviors wrote are applied before the next step.
        if (setpoints_ != nullptr) setpoints_->fill(report.mutable_setpoints_written());
        name_awaited_topics(report, false);
        bool written = false;
        {
          // Decided and written as one with respect to the gate: a command
          // that checks awaitTurn() after this sees awaited_ false and wakes
          // the simulator, its wake written after this report; one that
          // checked before has made idle_() false.
          absl::MutexLock write_lock(&write_mutex_);
          {
            absl::MutexLock lock(&mutex_);
            const bool idle = idle_();
            if (idle) awaited_ = false;
            report.set_idle(idle);
          }
          written = write_locked(report);
        }
        if (!written) break;
        reported_.fetch_add(1, std::memory_order_relaxed);
      }
    }
    set_streaming(false);
    {
      // No wake is written once this returns.
      absl::MutexLock write_lock(&write_mutex_);
      ++open_stream_;
    }
    stream->WritesDone();
    const grpc::Status status = stream->Finish();
    if (last_granted && !isStopping()) {
      // The simulator went away: time runs on in real time from the last
      // grant (as SimClock runs on at the last scale when free running), so
      // that the behaviors' staleness checks notice (PROCESS_FAILURE)
      // instead of waiting for a grant that may never come.
      v1::Clock run_on = *last_granted;
      run_on.set_time_scale(1.0);
      *run_on.mutable_wall_time() = google::protobuf::util::TimeUtil::NanosecondsToTimestamp(
          std::chrono::duration_cast<std::chrono::nanoseconds>(
              std::chrono::system_clock::now().time_since_epoch())
              .count());
      clock_.onClockSample(run_on);
      std::fprintf(stderr, "%s: the time grants ended (%s); time runs on in real time\n",
                   participant_.c_str(), status.error_message().c_str());
    }
    if (status.error_code() == grpc::StatusCode::FAILED_PRECONDITION && !told_refusal) {
      std::fprintf(stderr, "%s: the simulator gives no time grants (%s); asking again\n",
                   participant_.c_str(), status.error_message().c_str());
      told_refusal = true;
    }
    absl::MutexLock lock(&mutex_);
    context_ = nullptr;
    // Until stopped, at most backoff.
    mutex_.AwaitWithTimeout(absl::Condition(&stopping_), absl::FromChrono(backoff));
    if (stopping_) return;
    backoff = std::min(backoff * 2, kMaxBackoff);
  }
}

}  // namespace behaviorlib::server
