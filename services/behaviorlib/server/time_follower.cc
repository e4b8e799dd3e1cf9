#include "behaviorlib/server/time_follower.h"

#include <google/protobuf/util/time_util.h>

#include <algorithm>
#include <cstdio>

#include "behaviorlib/v1/simulator.grpc.pb.h"
#include "channel/sim_clock.h"

namespace behaviorlib::server {
namespace {

constexpr std::chrono::milliseconds kInitialBackoff(100);
constexpr std::chrono::milliseconds kMaxBackoff(2000);
// How often the behaviors' progress is looked at while catching up.
constexpr std::chrono::microseconds kCatchUpPoll(100);

TimePoint toTimePoint(const google::protobuf::Timestamp& t) {
  return TimePoint(std::chrono::seconds(t.seconds()) + std::chrono::nanoseconds(t.nanos()));
}

}  // namespace

TimeFollower::TimeFollower(const std::string& simulator_address, std::string participant,
                           channel::SimClock& clock, std::function<bool(TimePoint)> caught_up)
    : participant_(std::move(participant)),
      clock_(clock),
      caught_up_(std::move(caught_up)),
      channel_(grpc::CreateChannel(simulator_address, grpc::InsecureChannelCredentials())),
      thread_([this] { run(); }) {}

TimeFollower::~TimeFollower() {
  {
    std::lock_guard lock(mutex_);
    stopping_ = true;
    if (context_ != nullptr) context_->TryCancel();
  }
  cv_.notify_all();
  thread_.join();
}

bool TimeFollower::awaitCaughtUp(TimePoint t) {
  while (!caught_up_(t)) {
    std::unique_lock lock(mutex_);
    if (cv_.wait_for(lock, kCatchUpPoll, [this] { return stopping_; })) return false;
  }
  return true;
}

void TimeFollower::run() {
  auto stub = v1::Simulator::NewStub(channel_);
  std::chrono::milliseconds backoff = kInitialBackoff;
  bool told_refusal = false;
  while (true) {
    grpc::ClientContext context;
    {
      std::lock_guard lock(mutex_);
      if (stopping_) return;
      context_ = &context;
    }
    auto stream = stub->FollowTime(&context);
    v1::FollowTimeRequest join;
    join.set_participant(participant_);
    if (stream->Write(join)) {
      v1::FollowTimeResponse grant;
      while (stream->Read(&grant)) {
        backoff = kInitialBackoff;
        clock_.onClockSample(grant.clock());
        if (!awaitCaughtUp(toTimePoint(grant.clock().time()))) break;
        v1::FollowTimeRequest report;
        *report.mutable_caught_up_to() = grant.clock().time();
        if (!stream->Write(report)) break;
        reported_.fetch_add(1, std::memory_order_relaxed);
      }
    }
    stream->WritesDone();
    const grpc::Status status = stream->Finish();
    if (status.error_code() == grpc::StatusCode::FAILED_PRECONDITION && !told_refusal) {
      std::fprintf(stderr, "%s: the simulator gives no time grants (%s); asking again\n",
                   participant_.c_str(), status.error_message().c_str());
      told_refusal = true;
    }
    std::unique_lock lock(mutex_);
    context_ = nullptr;
    if (cv_.wait_for(lock, backoff, [this] { return stopping_; })) return;
    backoff = std::min(backoff * 2, kMaxBackoff);
  }
}

}  // namespace behaviorlib::server
