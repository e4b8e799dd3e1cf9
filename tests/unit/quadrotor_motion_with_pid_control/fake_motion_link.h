#pragma once

// A MotionLink in memory: what the behaviors publish is kept (every
// reference, every status) and what they read is whatever the test (or the
// behaviors) published last, while followed.

#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <vector>

#include "behaviorlib/motion_behaviors/motion_link.h"

namespace behaviorlib::motion_behaviors::testing {

class FakeMotionLink final : public MotionLink {
 public:
  absl::Status publishReference(const v1::MotionReference& reference) override {
    std::lock_guard lock(mutex_);
    references_.push_back(reference);
    return absl::OkStatus();
  }
  absl::Status publishStatus(const v1::MotionControlStatus& status) override {
    std::lock_guard lock(mutex_);
    statuses_.push_back(status);
    return absl::OkStatus();
  }
  void followReferences(bool follow) override {
    std::lock_guard lock(mutex_);
    reference_followers_ += follow ? 1 : -1;
  }
  void followStatus(bool follow) override {
    std::lock_guard lock(mutex_);
    status_followers_ += follow ? 1 : -1;
  }
  std::shared_ptr<const v1::MotionReference> latestReference() override {
    std::lock_guard lock(mutex_);
    if (reference_followers_ <= 0 || references_.empty()) return nullptr;
    return std::make_shared<const v1::MotionReference>(references_.back());
  }
  std::shared_ptr<const v1::MotionControlStatus> latestStatus() override {
    std::lock_guard lock(mutex_);
    if (status_followers_ <= 0 || statuses_.empty()) return nullptr;
    return std::make_shared<const v1::MotionControlStatus>(statuses_.back());
  }
  bool statusFollowed() override {
    std::lock_guard lock(mutex_);
    return status_followed_;
  }
  /// Whether the status subscription counts as established (statusFollowed()).
  void setStatusFollowed(bool followed) {
    std::lock_guard lock(mutex_);
    status_followed_ = followed;
  }
  std::string referenceTopic() const override { return "robots/drone1/motion_reference"; }
  std::string statusTopic() const override { return "robots/drone1/motion_control/status"; }

  std::vector<v1::MotionReference> references() const {
    std::lock_guard lock(mutex_);
    return references_;
  }
  std::vector<v1::MotionControlStatus> statuses() const {
    std::lock_guard lock(mutex_);
    return statuses_;
  }
  int referenceFollowers() const {
    std::lock_guard lock(mutex_);
    return reference_followers_;
  }
  int statusFollowers() const {
    std::lock_guard lock(mutex_);
    return status_followers_;
  }

 private:
  mutable std::mutex mutex_;
  std::vector<v1::MotionReference> references_;
  std::vector<v1::MotionControlStatus> statuses_;
  int reference_followers_ = 0;
  bool status_followed_ = true;
  int status_followers_ = 0;
};

}  // namespace behaviorlib::motion_behaviors::testing
