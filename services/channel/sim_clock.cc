#include "channel/sim_clock.h"

#include <algorithm>

#include "behaviorlib/v1/types.pb.h"
#include "channel/channel_client.h"
#include "channel/topic.h"

namespace behaviorlib::channel {
namespace {

// Upper bound of a waiter's sleep: listeners are notified on every sample,
// the bound only covers a missed notification or a dead simulator.
constexpr std::chrono::nanoseconds kMaxWallWait = std::chrono::milliseconds(50);
// Time scales below this are treated as this, so that a tiny scale cannot
// turn a short simulated wait into an overflowing wall wait.
constexpr double kMinTimeScale = 1e-3;

TimePoint toTimePoint(const google::protobuf::Timestamp& t) {
  return TimePoint(std::chrono::seconds(t.seconds()) + std::chrono::nanoseconds(t.nanos()));
}

}  // namespace

SimClock::SimClock() = default;

SimClock::SimClock(ChannelClient& client) { subscribe(client); }

SimClock::SimClock(const std::string& address)
    : own_client_(std::make_unique<ChannelClient>(address)) {
  subscribe(*own_client_);
}

SimClock::~SimClock() {
  // Joins the reader thread, so no onClockSample runs past this point.
  subscription_.reset();
}

void SimClock::subscribe(ChannelClient& client) {
  SubscribeOptions options;
  options.mode = v1::DELIVERY_MODE_LATEST;
  options.send_latest_first = true;
  subscription_ =
      client.subscribeTyped<v1::Clock>(std::string(kClockTopic), options,
                                       [this](const v1::Clock& sample) { onClockSample(sample); });
}

TimePoint SimClock::now() const {
  std::lock_guard lock(mutex_);
  return now_;
}

std::chrono::nanoseconds SimClock::wallWaitFor(Duration remaining) const {
  if (remaining <= Duration::zero()) return std::chrono::nanoseconds::zero();
  double scale = 0;
  {
    std::lock_guard lock(mutex_);
    scale = time_scale_;
  }
  if (scale <= 0) return kMaxWallWait;  // lock-step: time moves only with samples
  // Compare in double nanoseconds so that huge `remaining` values cannot
  // overflow before the min().
  const double wall_ns = static_cast<double>(remaining.count()) / std::max(scale, kMinTimeScale);
  if (wall_ns >= static_cast<double>(kMaxWallWait.count())) return kMaxWallWait;
  return std::chrono::nanoseconds(static_cast<int64_t>(wall_ns));
}

bool SimClock::valid() const {
  std::lock_guard lock(mutex_);
  return valid_;
}

void SimClock::onClockSample(const v1::Clock& sample) {
  {
    std::lock_guard lock(mutex_);
    now_ = toTimePoint(sample.time());
    time_scale_ = sample.time_scale();
    paused_ = sample.paused();
    valid_ = true;
    last_wall_update_ = TimePoint(
        std::chrono::duration_cast<Duration>(std::chrono::system_clock::now().time_since_epoch()));
    last_steady_update_ = std::chrono::steady_clock::now();
  }
  // Outside mutex_: listeners typically call now() right away.
  notifyListeners();
}

TimePoint SimClock::lastWallUpdate() const {
  std::lock_guard lock(mutex_);
  return last_wall_update_;
}

bool SimClock::stale(std::chrono::nanoseconds wall_limit) const {
  std::lock_guard lock(mutex_);
  if (!valid_) return true;
  return std::chrono::steady_clock::now() - last_steady_update_ > wall_limit;
}

double SimClock::timeScale() const {
  std::lock_guard lock(mutex_);
  return time_scale_;
}

bool SimClock::paused() const {
  std::lock_guard lock(mutex_);
  return paused_;
}

}  // namespace behaviorlib::channel
