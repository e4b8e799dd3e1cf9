#pragma once

// LogStreamWriter: the server side of one resumable event stream
// (BehaviorSystem.WatchEvents, Coordinator.WatchEvents): the start message,
// then the subscription's events, one write at a time. The log wakes it when
// events arrive; it never blocks the appending thread. A subscription that
// overflowed ends the stream RESOURCE_EXHAUSTED, and shutdown() ends it
// UNAVAILABLE once drained, both with the resume point.
//
// Subscription is a ResumableLog<...>::Subscription (start(), overflowed(),
// lastPoppedSeq(), cancel()); a subclass says how its messages are made:
//
//   class MyStream final : public LogStreamWriter<Sub, Response> {
//     MyStream(Log& log, ...) : LogStreamWriter("the behavior system") {
//       begin(log.subscribe(options, [this] { wake(); }));
//     }
//     void startMessage(const Sub& s, Response* out) override;  // the first message
//     bool eventsMessage(Sub& s, Response* out) override;  // false when nothing is queued
//     void streamDone() override;  // after the stream ended, before deletion
//   };

#include <grpcpp/grpcpp.h>

#include <memory>
#include <string>

#include "absl/base/thread_annotations.h"
#include "absl/synchronization/mutex.h"
#include "behaviorlib/error_details.h"
#include "behaviorlib/server_kit/reactor_order.h"

namespace behaviorlib::server_kit {

template <class Subscription, class Message>
class LogStreamWriter : public Ordered<grpc::ServerWriteReactor<Message>> {
 public:
  /// Ends the stream UNAVAILABLE (with the resume point) once what is queued
  /// has been written.
  void shutdown() {
    absl::MutexLock lock(&mutex_);
    shutting_down_ = true;
    if (!writing_) writeNextLocked();
  }

  void OnWriteDone(bool ok) override {
    this->ordered();
    absl::MutexLock lock(&mutex_);
    writing_ = false;
    if (!ok) {
      finishLocked(grpc::Status(grpc::StatusCode::CANCELLED, "stream broken"));
      return;
    }
    writeNextLocked();
  }

  void OnCancel() override {
    this->ordered();
    absl::MutexLock lock(&mutex_);
    cancelled_ = true;
    if (!writing_) finishLocked(grpc::Status(grpc::StatusCode::CANCELLED, "cancelled by client"));
  }

  void OnDone() override {
    this->ordered();
    Subscription* subscription = nullptr;
    {
      absl::MutexLock lock(&mutex_);
      subscription = subscription_.get();
    }
    // Outside the lock: cancel() waits for a running wake, which takes it.
    if (subscription) subscription->cancel();
    streamDone();
    delete this;
  }

 protected:
  /// `who` names the server in the shutdown status ("the coordinator").
  explicit LogStreamWriter(std::string who) : who_(std::move(who)) {}

  /// Starts the stream with a subscription whose wake callback calls wake().
  /// A wake before this has written the start message does nothing.
  void begin(std::unique_ptr<Subscription> subscription) {
    absl::MutexLock lock(&mutex_);
    subscription_ = std::move(subscription);
    startMessage(*subscription_, &message_);
    this->StartWrite(&message_);
  }

  /// The log's wake callback: writes the next message unless one is being
  /// written.
  void wake() {
    absl::MutexLock lock(&mutex_);
    if (!writing_ && subscription_) writeNextLocked();
  }

  virtual void startMessage(const Subscription& subscription, Message* out) = 0;
  virtual bool eventsMessage(Subscription& subscription, Message* out) = 0;
  virtual void streamDone() = 0;

 private:
  std::string resumeHint() const ABSL_EXCLUSIVE_LOCKS_REQUIRED(mutex_) {
    return "resume with since_seq=" + std::to_string(subscription_->lastPoppedSeq()) +
           " and incarnation=" + subscription_->start().incarnation();
  }

  void writeNextLocked() ABSL_EXCLUSIVE_LOCKS_REQUIRED(mutex_) {
    if (finished_) return;
    if (cancelled_) {
      finishLocked(grpc::Status(grpc::StatusCode::CANCELLED, "cancelled by client"));
      return;
    }
    if (eventsMessage(*subscription_, &message_)) {
      writing_ = true;
      this->StartWrite(&message_);
      return;
    }
    if (subscription_->overflowed()) {
      // The subscription's queue is full: a cap reached.
      finishLocked(errors::grpcError(
          grpc::StatusCode::RESOURCE_EXHAUSTED, v1::LIMIT_EXCEEDED,
          "subscriber too slow: events were produced faster than it read them; " + resumeHint()));
      return;
    }
    if (shutting_down_) {
      finishLocked(errors::grpcError(grpc::StatusCode::UNAVAILABLE, v1::SHUTTING_DOWN,
                                     who_ + " is shutting down; " + resumeHint()));
    }
  }

  void finishLocked(const grpc::Status& status) ABSL_EXCLUSIVE_LOCKS_REQUIRED(mutex_) {
    if (finished_) return;
    finished_ = true;
    this->Finish(status);
  }

  const std::string who_;
  absl::Mutex mutex_;
  std::unique_ptr<Subscription> subscription_ ABSL_GUARDED_BY(mutex_);
  Message message_ ABSL_GUARDED_BY(mutex_);
  bool writing_ ABSL_GUARDED_BY(mutex_) = true;  // true until the start message is written
  bool finished_ ABSL_GUARDED_BY(mutex_) = false;
  bool cancelled_ ABSL_GUARDED_BY(mutex_) = false;
  bool shutting_down_ ABSL_GUARDED_BY(mutex_) = false;
};

}  // namespace behaviorlib::server_kit
