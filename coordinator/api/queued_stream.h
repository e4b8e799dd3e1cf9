#pragma once

// QueuedStream: a server-streaming reactor fed from other threads (the
// coordinator's WatchMission, WatchBeliefs and WatchVehicle).
//
//   class MyStream final : public QueuedStream<v1::MyResponse> { ... };
//   auto core = stream->core();            // kept by the producer
//   absl::MutexLock lock(&core->mutex);
//   if (core->stream != nullptr) { ...->pushLocked(message, /*last=*/false); }

#include <grpcpp/grpcpp.h>

#include <cstddef>
#include <cstdint>
#include <deque>
#include <memory>
#include <utility>

#include "absl/base/thread_annotations.h"
#include "absl/synchronization/mutex.h"
#include "behaviorlib/server_kit/reactor_order.h"

namespace behaviorlib::coordinator {

// A server stream fed from other threads: messages are queued and written
// one at a time; end() finishes once the queue is written. The queue and
// the reactor's liveness live in a shared Core, so that a producer holding
// the core never touches a reactor that is gone.
template <class Response>
class QueuedStream : public server_kit::Ordered<grpc::ServerWriteReactor<Response>> {
 public:
  struct Core {
    absl::Mutex mutex;
    QueuedStream* stream ABSL_GUARDED_BY(mutex) = nullptr;  // null once the call is done
  };

  QueuedStream() : core_(std::make_shared<Core>()) { core_->stream = this; }

  std::shared_ptr<Core> core() const { return core_; }

  /// Queues `message`; with `last`, finishes OK after it. Call with
  /// core()->mutex held and core()->stream non-null. Past the bound set by
  /// boundQueue(), the oldest queued message is dropped.
  void pushLocked(Response message, bool last) ABSL_EXCLUSIVE_LOCKS_REQUIRED(core_->mutex) {
    if (ending_) return;
    if (max_queued_ != 0 && queue_.size() >= max_queued_) {
      queue_.pop_front();
      ++dropped_;
    }
    queue_.push_back(std::move(message));
    if (last) end_status_ = grpc::Status::OK, ending_ = true;
    if (!writing_) writeNextLocked();
  }
  /// Finishes with `status` once the queue is written (core mutex held).
  void endLocked(const grpc::Status& status) ABSL_EXCLUSIVE_LOCKS_REQUIRED(core_->mutex) {
    if (ending_) return;
    ending_ = true;
    end_status_ = status;
    if (!writing_) writeNextLocked();
  }
  /// Keeps at most `max_queued` unsent messages (0: no bound), for a stream
  /// whose newest message matters more than every message.
  void boundQueueLocked(size_t max_queued) ABSL_EXCLUSIVE_LOCKS_REQUIRED(core_->mutex) {
    max_queued_ = max_queued;
  }
  /// Messages dropped by the bound so far.
  uint64_t droppedLocked() const ABSL_EXCLUSIVE_LOCKS_REQUIRED(core_->mutex) { return dropped_; }
  /// For a producer that holds core()->mutex and reached this stream through
  /// core()->stream: tells the thread-safety analysis, which cannot see that
  /// it is this stream's core mutex, that it is held (and checks it).
  void assertLocked() const ABSL_ASSERT_EXCLUSIVE_LOCK(core_->mutex) { core_->mutex.AssertHeld(); }

  void OnWriteDone(bool ok) override {
    this->ordered();
    absl::MutexLock lock(&core_->mutex);
    writing_ = false;
    if (!ok) {
      finishLocked(grpc::Status(grpc::StatusCode::CANCELLED, "stream broken"));
      return;
    }
    writeNextLocked();
  }
  void OnCancel() override {
    this->ordered();
    absl::MutexLock lock(&core_->mutex);
    cancelled_ = true;
    if (!writing_) finishLocked(grpc::Status(grpc::StatusCode::CANCELLED, "cancelled by client"));
  }
  void OnDone() override {
    this->ordered();
    {
      absl::MutexLock lock(&core_->mutex);
      core_->stream = nullptr;
    }
    onDone();
    delete this;
  }

 protected:
  virtual void onDone() {}

 private:
  void writeNextLocked() ABSL_EXCLUSIVE_LOCKS_REQUIRED(core_->mutex) {
    if (finished_) return;
    if (cancelled_) {
      finishLocked(grpc::Status(grpc::StatusCode::CANCELLED, "cancelled by client"));
      return;
    }
    if (!queue_.empty()) {
      current_ = std::move(queue_.front());
      queue_.pop_front();
      writing_ = true;
      this->StartWrite(&current_);
      return;
    }
    if (ending_) finishLocked(end_status_);
  }
  void finishLocked(const grpc::Status& status) ABSL_EXCLUSIVE_LOCKS_REQUIRED(core_->mutex) {
    if (finished_) return;
    finished_ = true;
    this->Finish(status);
  }

  std::shared_ptr<Core> core_;
  std::deque<Response> queue_ ABSL_GUARDED_BY(core_->mutex);
  Response current_ ABSL_GUARDED_BY(core_->mutex);
  bool writing_ ABSL_GUARDED_BY(core_->mutex) = false;
  bool finished_ ABSL_GUARDED_BY(core_->mutex) = false;
  bool cancelled_ ABSL_GUARDED_BY(core_->mutex) = false;
  bool ending_ ABSL_GUARDED_BY(core_->mutex) = false;
  size_t max_queued_ ABSL_GUARDED_BY(core_->mutex) = 0;
  uint64_t dropped_ ABSL_GUARDED_BY(core_->mutex) = 0;
  grpc::Status end_status_ ABSL_GUARDED_BY(core_->mutex);
};

}  // namespace behaviorlib::coordinator
