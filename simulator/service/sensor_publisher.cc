#include "simulator/service/sensor_publisher.h"

#include <set>
#include <string>
#include <string_view>

#include "simulator/service/sensor_messages.h"

namespace behaviorlib::sim {
namespace {

constexpr std::string_view kRobotsPrefix = "robots/";
constexpr std::string_view kCameraSuffix = "/camera/image";

}  // namespace

SensorPublisher::SensorPublisher(ChannelRoutes& client, Simulation& simulation,
                                 const TimeControl& time, SensorConfig config,
                                 SensorSystem::FrameTimer frame_timer,
                                 std::chrono::milliseconds poll_period)
    : client_(client),
      poll_period_(poll_period),
      queue_(client, PublishQueueLimits{}, time.deterministic.load()),
      sensors_(
          std::move(config),
          [this](SensorSample sample) {
            std::string topic = sensorTopic(sample);
            queue_.push(std::move(topic), sensorMessage(std::move(sample)));
          },
          std::move(frame_timer)) {
  simulation.addStepListener([this, &time](SimTime now, const std::vector<VehicleReport>& v) {
    sensors_.onStep(now, v, time.lock_step.load());
  });
  if (sensors_.config().camera.rate_hz > 0.0) poller_ = std::thread([this] { pollSubscribers(); });
}

SensorPublisher::~SensorPublisher() {
  {
    std::lock_guard lock(poll_mutex_);
    stopping_ = true;
  }
  poll_cv_.notify_all();
  if (poller_.joinable()) poller_.join();
}

void SensorPublisher::setInterest(const ChannelRoutes* interest) {
  {
    std::lock_guard lock(poll_mutex_);
    interest_ = interest;
  }
  queue_.setInterest(interest);
  camerasFromInterest();
}

void SensorPublisher::interestChanged() {
  queue_.interestChanged();
  if (!camerasFromInterest()) poll_cv_.notify_all();  // the poller asks the broker
}

bool SensorPublisher::camerasFromInterest() {
  std::lock_guard lock(poll_mutex_);
  if (interest_ == nullptr || !interest_->known()) return false;
  std::set<std::string> wanted;
  for (const std::string& name : interest_->wantedTopics()) {
    if (name.size() > kRobotsPrefix.size() + kCameraSuffix.size() &&
        name.compare(0, kRobotsPrefix.size(), kRobotsPrefix) == 0 &&
        name.compare(name.size() - kCameraSuffix.size(), kCameraSuffix.size(), kCameraSuffix) ==
            0) {
      wanted.insert(name.substr(kRobotsPrefix.size(),
                                name.size() - kRobotsPrefix.size() - kCameraSuffix.size()));
    }
  }
  sensors_.setWantedCameras(std::move(wanted));
  return true;
}

void SensorPublisher::pollSubscribers() {
  std::unique_lock lock(poll_mutex_);
  while (!stopping_) {
    if (interest_ != nullptr && interest_->known()) {  // interestChanged() keeps them
      poll_cv_.wait_for(lock, poll_period_, [this] { return stopping_; });
      continue;
    }
    lock.unlock();
    std::set<std::string> wanted;
    // When the broker cannot be asked, nobody can be subscribed either.
    const std::vector<v1::TopicInfo> topics =
        client_.listTopics(std::string(kRobotsPrefix), std::chrono::seconds(1));
    {
      for (const auto& topic : topics) {
        const std::string& name = topic.name();
        if (topic.subscriber_count() == 0 ||
            name.size() <= kRobotsPrefix.size() + kCameraSuffix.size() ||
            name.compare(name.size() - kCameraSuffix.size(), kCameraSuffix.size(), kCameraSuffix) !=
                0) {
          continue;
        }
        wanted.insert(name.substr(kRobotsPrefix.size(),
                                  name.size() - kRobotsPrefix.size() - kCameraSuffix.size()));
      }
    }
    sensors_.setWantedCameras(std::move(wanted));
    lock.lock();
    poll_cv_.wait_for(lock, poll_period_, [this] { return stopping_; });
  }
}

}  // namespace behaviorlib::sim
