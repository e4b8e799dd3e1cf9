#include "behaviorlib/motion_behaviors/motion_link.h"

#include "behaviorlib/motion_behaviors/motion_topics.h"

namespace behaviorlib::motion_behaviors {

RemoteMotionLink::RemoteMotionLink(channel::ChannelClient* channel, std::string robot_id)
    : channel_(channel), robot_id_(std::move(robot_id)) {}

RemoteMotionLink::~RemoteMotionLink() {
  // Joined outside the lock: their callbacks take it.
  std::unique_ptr<channel::Subscription> a, b;
  {
    absl::MutexLock lock(&mutex_);
    a = std::move(references_.subscription);
    b = std::move(status_.subscription);
  }
}

absl::Status RemoteMotionLink::publish(const std::string& topic,
                                       const google::protobuf::Message& message) {
  if (!channel_) {
    return absl::FailedPreconditionError(
        "no data channel configured: start the behavior system with --channel HOST:PORT");
  }
  return channel_->publish(topic, message);
}

absl::Status RemoteMotionLink::publishReference(const v1::MotionReference& reference) {
  return publish(referenceTopic(), reference);
}

absl::Status RemoteMotionLink::publishStatus(const v1::MotionControlStatus& status) {
  return publish(statusTopic(), status);
}

template <class T>
void RemoteMotionLink::follow(bool follow, const std::string& topic, Followed<T>* followed) {
  if (!channel_) return;
  // Declared before the lock: a dropped subscription is joined after the
  // lock is released (its callback takes the lock).
  std::unique_ptr<channel::Subscription> old;
  absl::MutexLock lock(&mutex_);
  if (follow) {
    if (followed->followers++ > 0) return;
    followed->latest.reset();
    followed->subscription = channel_->subscribeTyped<T>(
        topic, {.mode = v1::DELIVERY_MODE_LATEST, .send_latest_first = true},
        [this, followed](const T& sample) {
          auto latest = std::make_shared<const T>(sample);
          absl::MutexLock inner(&mutex_);
          followed->latest.swap(latest);  // the old one is freed outside the lock
        });
    return;
  }
  if (followed->followers == 0 || --followed->followers > 0) return;
  old = std::move(followed->subscription);
  followed->latest.reset();
}

void RemoteMotionLink::followReferences(bool follow) {
  this->follow(follow, referenceTopic(), &references_);
}

void RemoteMotionLink::followStatus(bool follow) { this->follow(follow, statusTopic(), &status_); }

std::shared_ptr<const v1::MotionReference> RemoteMotionLink::latestReference() {
  absl::MutexLock lock(&mutex_);
  return references_.latest;
}

std::shared_ptr<const v1::MotionControlStatus> RemoteMotionLink::latestStatus() {
  absl::MutexLock lock(&mutex_);
  return status_.latest;
}

bool RemoteMotionLink::statusFollowed() {
  if (!channel_) return true;  // nothing will come: the checks say why
  absl::MutexLock lock(&mutex_);
  return status_.subscription && status_.subscription->connectCount() > 0;
}

std::string RemoteMotionLink::referenceTopic() const { return motionReferenceTopic(robot_id_); }

std::string RemoteMotionLink::statusTopic() const { return motionControlStatusTopic(robot_id_); }

}  // namespace behaviorlib::motion_behaviors
