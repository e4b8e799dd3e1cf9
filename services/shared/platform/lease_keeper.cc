#include "behaviorlib/platform/lease_keeper.h"

#include <algorithm>

namespace behaviorlib::platform {

absl::StatusOr<std::unique_ptr<LeaseKeeper>> LeaseKeeper::acquire(
    const FlightControllerClient& client, const Clock& clock, std::string holder,
    LeaseOptions options) {
  auto response = client.acquireLease(holder, options.ttl, options.preempt);
  if (!response.ok()) return response.status();
  return std::unique_ptr<LeaseKeeper>(
      new LeaseKeeper(client, clock, std::move(holder), response->lease_id(), options));
}

// Wakes the renewal thread when the clock moves, and tells the clock whether
// the renewals due are done.
class LeaseKeeper::Listener final : public ClockListener {
 public:
  explicit Listener(LeaseKeeper* owner) : owner_(owner) {}
  void onClockAdvanced() override {
    absl::MutexLock lock(&owner_->mutex_);
    ++owner_->wakes_;
  }
  bool caughtUp(TimePoint t) const override { return owner_->caughtUp(t); }

 private:
  LeaseKeeper* const owner_;
};

LeaseKeeper::LeaseKeeper(const FlightControllerClient& client, const Clock& clock,
                         std::string holder, std::string lease_id, LeaseOptions options)
    : client_(client),
      clock_(clock),
      holder_(std::move(holder)),
      lease_id_(std::move(lease_id)),
      options_(options),
      last_renewed_(clock.now()) {
  next_ = last_renewed_ + std::max<Duration>(options_.ttl / 4, std::chrono::milliseconds(10));
  listener_ = std::make_unique<Listener>(this);
  clock_.addListener(listener_.get());
  thread_ = std::thread([this] { run(); });
}

bool LeaseKeeper::caughtUp(TimePoint t) const {
  absl::MutexLock lock(&mutex_);
  return stopping_ || !lost_.ok() || (!renewing_ && next_ > t);
}

LeaseKeeper::~LeaseKeeper() { release().IgnoreError(); }

void LeaseKeeper::stopThread() {
  {
    absl::MutexLock lock(&mutex_);
    stopping_ = true;
  }
  if (thread_.joinable()) thread_.join();
  if (listener_) clock_.removeListener(listener_.get());
}

absl::Status LeaseKeeper::release() {
  stopThread();
  {
    absl::MutexLock lock(&mutex_);
    if (released_ || !lost_.ok()) return lost_;
    released_ = true;
  }
  return client_.releaseLease(lease_id_);
}

absl::Status LeaseKeeper::status() const {
  absl::MutexLock lock(&mutex_);
  if (!lost_.ok()) return lost_;
  if (!last_failure_.ok() && clock_.now() - last_renewed_ > options_.ttl) {
    return absl::Status(last_failure_.code(),
                        "lease " + lease_id_ + " of " + client_.robotId() +
                            " not renewed within its ttl: " + std::string(last_failure_.message()));
  }
  return absl::OkStatus();
}

uint64_t LeaseKeeper::renewals() const {
  absl::MutexLock lock(&mutex_);
  return renewals_;
}

void LeaseKeeper::run() {
  const Duration period = std::max<Duration>(options_.ttl / 4, std::chrono::milliseconds(10));
  // After a failed renewal, retry sooner (still on the clock).
  const Duration retry = std::max<Duration>(options_.ttl / 10, std::chrono::milliseconds(5));
  absl::MutexLock lock(&mutex_);
  while (!stopping_) {
    const TimePoint now = clock_.now();
    if (now < next_) {
      // Woken when simulated time moves (the listener); re-read it at least
      // every 20 ms of wall time anyway.
      const uint64_t seen = wakes_;
      const auto woken = [this, seen]() ABSL_EXCLUSIVE_LOCKS_REQUIRED(mutex_) {
        return stopping_ || wakes_ != seen;
      };
      mutex_.AwaitWithTimeout(absl::Condition(&woken),
                              absl::FromChrono(std::min<std::chrono::nanoseconds>(
                                  clock_.wallWaitFor(next_ - now), std::chrono::milliseconds(20))));
      continue;
    }
    renewing_ = true;
    mutex_.Unlock();
    auto renewed = client_.renewLease(lease_id_);
    mutex_.Lock();
    renewing_ = false;
    if (renewed.ok()) {
      last_renewed_ = clock_.now();
      last_failure_ = absl::OkStatus();
      ++renewals_;
      next_ = last_renewed_ + period;
    } else if (renewed.status().code() == absl::StatusCode::kFailedPrecondition) {
      lost_ = absl::FailedPreconditionError("lost the lease of " + client_.robotId() + ": " +
                                            std::string(renewed.status().message()));
      break;
    } else {
      last_failure_ = renewed.status();
      next_ = clock_.now() + retry;
    }
  }
}

}  // namespace behaviorlib::platform
