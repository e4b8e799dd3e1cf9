#include "behaviorlib/channel/sim_clock.h"

#include <algorithm>

#include "behaviorlib/channel/channel_client.h"
#include "behaviorlib/channel/topic.h"
#include "behaviorlib/v1/types.pb.h"

namespace behaviorlib::channel {
namespace {

// Upper bound of a waiter's sleep: listeners are notified on every sample,
// the bound only covers a missed notification or a dead simulator.
constexpr std::chrono::nanoseconds kMaxWallWait = std::chrono::milliseconds(50);
// Time scales below this are treated as this, so that a tiny scale cannot
// turn a short simulated wait into an overflowing wall wait.
constexpr double kMinTimeScale = 1e-3;
// A sample's wall_time older than this (or in the future) is taken as the
// time of arrival: the publisher's host clock disagrees with ours.
constexpr std::chrono::seconds kMaxSampleAge(5);

TimePoint toTimePoint(const google::protobuf::Timestamp& t) {
  return TimePoint(std::chrono::seconds(t.seconds()) + std::chrono::nanoseconds(t.nanos()));
}

}  // namespace

SimClock::SimClock() : SimClock(HostClocks{}) {}

SimClock::SimClock(HostClocks host) : host_(std::move(host)) {}

SimClock::SimClock(ChannelClient& client) : SimClock() { subscribe(client); }

SimClock::SimClock(const std::string& address)
    : host_(), own_client_(std::make_unique<ChannelClient>(address)) {
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

TimePoint SimClock::lineAtLocked(std::chrono::steady_clock::time_point at) const {
  if (paused_ || !(time_scale_ > 0.0) || at <= anchor_steady_) return anchor_time_;
  const double elapsed_ns =
      static_cast<double>(std::chrono::nanoseconds(at - anchor_steady_).count());
  return anchor_time_ + Duration(static_cast<int64_t>(elapsed_ns * time_scale_));
}

TimePoint SimClock::now() const {
  absl::MutexLock lock(&mutex_);
  if (!valid_) return TimePoint{};
  floor_ = std::max(floor_, lineAtLocked(host_.steady()));
  return floor_;
}

std::chrono::nanoseconds SimClock::wallWaitFor(Duration remaining) const {
  if (remaining <= Duration::zero()) return std::chrono::nanoseconds::zero();
  double scale = 0;
  {
    absl::MutexLock lock(&mutex_);
    scale = paused_ ? 0.0 : time_scale_;
  }
  if (scale <= 0) return kMaxWallWait;  // lock-step: time moves only with samples
  // Compare in double nanoseconds so that huge `remaining` values cannot
  // overflow before the min().
  const double wall_ns = static_cast<double>(remaining.count()) / std::max(scale, kMinTimeScale);
  if (wall_ns >= static_cast<double>(kMaxWallWait.count())) return kMaxWallWait;
  return std::chrono::nanoseconds(static_cast<int64_t>(wall_ns));
}

bool SimClock::valid() const {
  absl::MutexLock lock(&mutex_);
  return valid_;
}

void SimClock::onClockSample(const v1::Clock& sample) {
  const auto steady_now = host_.steady();
  const auto system_now = host_.system();
  // Where the sample's time held on our monotonic clock: its wall_time when
  // our host clock agrees, else now (a publisher of every tick sets none).
  auto anchor = steady_now;
  if (sample.has_wall_time()) {
    const auto age =
        system_now - std::chrono::system_clock::time_point(
                         std::chrono::duration_cast<std::chrono::system_clock::duration>(
                             std::chrono::seconds(sample.wall_time().seconds()) +
                             std::chrono::nanoseconds(sample.wall_time().nanos())));
    if (age > std::chrono::system_clock::duration::zero() && age <= kMaxSampleAge) {
      anchor = steady_now - std::chrono::duration_cast<std::chrono::steady_clock::duration>(age);
    }
  }
  {
    absl::MutexLock lock(&mutex_);
    if (!valid_ || sample.epoch() != epoch_) {
      floor_ = TimePoint{};  // time restarted
    } else {
      // The time reached so far stays reached, read or not: a late sample
      // of an older time (the channel's, after a time grant) moves nothing
      // back.
      floor_ = std::max(floor_, lineAtLocked(steady_now));
    }
    anchor_time_ = toTimePoint(sample.time());
    anchor_steady_ = anchor;
    time_scale_ = sample.time_scale();
    paused_ = sample.paused();
    epoch_ = sample.epoch();
    valid_ = true;
    ++samples_;
    last_wall_update_ =
        TimePoint(std::chrono::duration_cast<Duration>(system_now.time_since_epoch()));
    last_steady_update_ = steady_now;
  }
  // Outside mutex_: listeners typically call now() right away.
  notifyListeners();
}

TimePoint SimClock::lastWallUpdate() const {
  absl::MutexLock lock(&mutex_);
  return last_wall_update_;
}

bool SimClock::stale(std::chrono::nanoseconds wall_limit) const {
  absl::MutexLock lock(&mutex_);
  if (!valid_) return true;
  return host_.steady() - last_steady_update_ > wall_limit;
}

double SimClock::timeScale() const {
  absl::MutexLock lock(&mutex_);
  return time_scale_;
}

bool SimClock::paused() const {
  absl::MutexLock lock(&mutex_);
  return paused_;
}

uint64_t SimClock::sampleCount() const {
  absl::MutexLock lock(&mutex_);
  return samples_;
}

}  // namespace behaviorlib::channel
