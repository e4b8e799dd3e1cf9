#include "behaviorlib/server/link_loss.h"

#include <google/protobuf/message.h>

#include <cstdio>
#include <memory>
#include <utility>

#include "absl/time/time.h"

namespace behaviorlib::server {
namespace {

constexpr std::chrono::milliseconds kPoll(100);
constexpr std::chrono::seconds kRetry(1);

}  // namespace

LinkLossWatch::LinkLossWatch(LinkLossOptions options, const Clock& clock,
                             std::function<bool()> registered, BehaviorHost& host,
                             std::string log_prefix)
    : options_(std::move(options)),
      clock_(clock),
      registered_(std::move(registered)),
      host_(host),
      log_prefix_(std::move(log_prefix)) {
  thread_ = std::thread([this] { run(); });
}

LinkLossWatch::~LinkLossWatch() {
  {
    absl::MutexLock lock(&mutex_);
    stopping_ = true;
  }
  thread_.join();
  // An activation under way answers on the behavior's worker: wait for it.
  absl::MutexLock lock(&mutex_);
  mutex_.AwaitWithTimeout(absl::Condition(
                              +[](bool* activating) { return !*activating; }, &activating_),
                          absl::Seconds(10));
}

int LinkLossWatch::actedCount() const {
  absl::MutexLock lock(&mutex_);
  return acted_count_;
}

void LinkLossWatch::run() {
  bool ever_registered = false;
  bool lost = false;
  TimePoint lost_since{};
  auto next_try = std::chrono::steady_clock::time_point{};
  absl::MutexLock lock(&mutex_);
  while (!stopping_) {
    mutex_.AwaitWithTimeout(absl::Condition(&stopping_), absl::FromChrono(kPoll));
    if (stopping_) break;
    mutex_.Unlock();
    const bool registered = registered_();
    const TimePoint now = clock_.now();
    mutex_.Lock();
    if (registered) {
      if (lost && acted_) {
        std::fprintf(stderr, "%s: the coordinator is back after the link loss\n",
                     log_prefix_.c_str());
      }
      ever_registered = true;
      lost = false;
      acted_ = false;
      told_refusal_ = false;
      continue;
    }
    if (!ever_registered) continue;  // not lost: never had it
    if (!lost) {
      lost = true;
      lost_since = now;
    }
    if (acted_ || activating_ || now - lost_since < options_.timeout) continue;
    if (std::chrono::steady_clock::now() < next_try) continue;
    next_try = std::chrono::steady_clock::now() + kRetry;
    activating_ = true;
    mutex_.Unlock();
    act();
    mutex_.Lock();
  }
}

void LinkLossWatch::act() {
  BehaviorExecutionManager* behavior = host_.find(options_.action);
  if (behavior == nullptr) {
    absl::MutexLock lock(&mutex_);
    activating_ = false;
    acted_ = true;  // nothing to do; said at start-up
    return;
  }
  const auto* prototype = google::protobuf::MessageFactory::generated_factory()->GetPrototype(
      &behavior->parametersType());
  std::unique_ptr<google::protobuf::Message> parameters(prototype->New());
  const std::string request_id =
      "link-loss-" + std::to_string(actedCount() + 1) + "-" +
      std::to_string(std::chrono::steady_clock::now().time_since_epoch().count());
  behavior->activate(
      std::move(parameters), request_id, [this](absl::StatusOr<v1::ActivateResponse> reply) {
        absl::MutexLock lock(&mutex_);
        activating_ = false;
        if (reply.ok()) {
          acted_ = true;
          ++acted_count_;
          std::fprintf(stderr,
                       "%s: no coordinator for %.1f s of the vehicle's time: %s activated (the "
                       "link-loss action)\n",
                       log_prefix_.c_str(), std::chrono::duration<double>(options_.timeout).count(),
                       options_.action.c_str());
        } else if (!told_refusal_) {
          told_refusal_ = true;
          std::fprintf(stderr, "%s: the link-loss action %s was refused (%s); retrying every s\n",
                       log_prefix_.c_str(), options_.action.c_str(),
                       std::string(reply.status().message()).c_str());
        }
      });
}

}  // namespace behaviorlib::server
