#pragma once

// MotionLink: the motion behaviors' side of the data channel — motion
// references one way, the motion controller's status the other (topics in
// motion_topics.h) — behind an interface, so that the behaviors' monitoring is
// unit-tested against an in-memory link on a FakeClock. RemoteMotionLink is
// the real one, over a ChannelClient.
//
//   RemoteMotionLink link(context.channel, context.robot_id);
//   link.followReferences(true);                 // while a controller is active
//   std::shared_ptr<const v1::MotionReference> r = link.latestReference();
//   link.publishStatus(status);

#include <memory>
#include <optional>
#include <string>

#include "absl/status/status.h"
#include "absl/synchronization/mutex.h"
#include "behaviorlib/channel/channel_client.h"
#include "behaviorlib/v1/motion.pb.h"

namespace behaviorlib::motion_behaviors {

class MotionLink {
 public:
  virtual ~MotionLink() = default;

  /// Publishes on robots/{id}/motion_reference.
  virtual absl::Status publishReference(const v1::MotionReference& reference) = 0;
  /// Publishes on robots/{id}/motion_control/status.
  virtual absl::Status publishStatus(const v1::MotionControlStatus& status) = 0;

  /// While at least one caller follows them, the newest reference (status)
  /// is kept by a subscription; latestReference() (latestStatus()) returns it.
  virtual void followReferences(bool follow) = 0;
  virtual void followStatus(bool follow) = 0;
  /// The newest sample seen since following began; null before any. Shared,
  /// never changed (a newer sample replaces it): read every tick, no copy.
  virtual std::shared_ptr<const v1::MotionReference> latestReference() = 0;
  virtual std::shared_ptr<const v1::MotionControlStatus> latestStatus() = 0;
  /// While followed: whether the status subscription has been established
  /// (from then on every status published reaches latestStatus()). A link
  /// with nothing to establish says true.
  virtual bool statusFollowed() { return true; }

  virtual std::string referenceTopic() const = 0;
  virtual std::string statusTopic() const = 0;
};

class RemoteMotionLink final : public MotionLink {
 public:
  /// `channel` may be null (no --channel): publishing then fails with
  /// FAILED_PRECONDITION and nothing is ever received.
  RemoteMotionLink(channel::ChannelClient* channel, std::string robot_id);
  ~RemoteMotionLink() override;

  absl::Status publishReference(const v1::MotionReference& reference) override;
  absl::Status publishStatus(const v1::MotionControlStatus& status) override;
  void followReferences(bool follow) override;
  void followStatus(bool follow) override;
  std::shared_ptr<const v1::MotionReference> latestReference() override;
  std::shared_ptr<const v1::MotionControlStatus> latestStatus() override;
  bool statusFollowed() override;
  std::string referenceTopic() const override;
  std::string statusTopic() const override;

 private:
  // One followed topic: its subscription while followed, and the newest
  // sample.
  template <class T>
  struct Followed {
    int followers = 0;
    std::shared_ptr<const T> latest;
    std::unique_ptr<channel::Subscription> subscription;
  };
  template <class T>
  void follow(bool follow, const std::string& topic, Followed<T>* followed);
  absl::Status publish(const std::string& topic, const google::protobuf::Message& message);

  channel::ChannelClient* channel_;
  const std::string robot_id_;
  absl::Mutex mutex_;
  // follow() reaches them through a pointer, which the analysis does not
  // follow; it holds mutex_ (and the subscription's callback takes it).
  Followed<v1::MotionReference> references_ ABSL_GUARDED_BY(mutex_);
  Followed<v1::MotionControlStatus> status_ ABSL_GUARDED_BY(mutex_);
};

}  // namespace behaviorlib::motion_behaviors
