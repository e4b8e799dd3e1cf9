#pragma once

// LatestWriter<R>: a server-streaming reactor that always sends the newest
// value offered to it, one write at a time. A slow reader skips intermediate
// values; the producer (the physics step) never waits.

#include <grpcpp/grpcpp.h>

#include <functional>
#include <mutex>
#include <string>

#include "behaviorlib/server_kit/reactor_order.h"

namespace behaviorlib::sim {

template <class R>
class LatestWriter final : public server_kit::Ordered<grpc::ServerWriteReactor<R>> {
 public:
  /// `key` says what the stream watches (e.g. a robot id); `on_done` runs
  /// once when the stream is over, just before the reactor deletes itself.
  LatestWriter(std::string key, std::function<void(LatestWriter*)> on_done)
      : key_(std::move(key)), on_done_(std::move(on_done)) {}

  const std::string& key() const { return key_; }

  /// Replaces the value to send next; starts a write if none is in flight.
  void offer(const R& value) {
    std::lock_guard lock(mutex_);
    if (ending_) return;
    pending_ = value;
    has_pending_ = true;
    if (!writing_) writeLocked();
  }
  /// Ends the stream with `status` once the write in flight (if any) is done.
  void end(const grpc::Status& status) {
    std::lock_guard lock(mutex_);
    if (ending_) return;
    ending_ = true;
    end_status_ = status;
    if (!writing_) finishLocked();
  }

  void OnWriteDone(bool ok) override {
    this->ordered();
    std::lock_guard lock(mutex_);
    writing_ = false;
    if (!ok && !ending_) {
      ending_ = true;
      end_status_ = grpc::Status(grpc::StatusCode::CANCELLED, "stream broken");
    }
    if (ending_) {
      finishLocked();
    } else if (has_pending_) {
      writeLocked();
    }
  }
  void OnCancel() override {
    this->ordered();
    end(grpc::Status(grpc::StatusCode::CANCELLED, "cancelled by client"));
  }
  void OnDone() override {
    this->ordered();
    if (on_done_) on_done_(this);
    delete this;
  }

 private:
  void writeLocked() {
    current_ = pending_;
    has_pending_ = false;
    writing_ = true;
    this->StartWrite(&current_);
  }
  void finishLocked() {
    if (finished_) return;
    finished_ = true;
    this->Finish(end_status_);
  }

  const std::string key_;
  std::function<void(LatestWriter*)> on_done_;
  std::mutex mutex_;
  R pending_, current_;
  bool has_pending_ = false, writing_ = false, ending_ = false, finished_ = false;
  grpc::Status end_status_;
};

}  // namespace behaviorlib::sim
