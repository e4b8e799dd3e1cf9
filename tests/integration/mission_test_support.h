#pragma once

// Helpers of the mission integration tests: a message as JSON, a
// WatchMission stream kept in order, and a behavior system's own event
// history.

#include <google/protobuf/util/json_util.h>
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>

#include <chrono>
#include <condition_variable>
#include <functional>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include "behaviorlib/v1/behavior.grpc.pb.h"
#include "behaviorlib/v1/coordinator.grpc.pb.h"
#include "coordinator_test_support.h"

namespace coordinator_test {

inline std::string json(const google::protobuf::Message& message) {
  std::string out;
  (void)google::protobuf::util::MessageToJsonString(message, &out);
  return out;
}

/// A WatchMission stream: every status received, kept in order.
class MissionWatcher {
 public:
  MissionWatcher(const std::string& address, const std::string& mission_id)
      : stub_(v1::Coordinator::NewStub(
            grpc::CreateChannel(address, grpc::InsecureChannelCredentials()))) {
    context_.set_deadline(std::chrono::system_clock::now() + seconds(120));
    v1::WatchMissionRequest request;
    request.set_mission_id(mission_id);
    reader_ = stub_->WatchMission(&context_, request);
    thread_ = std::thread([this] {
      v1::WatchMissionResponse message;
      while (reader_->Read(&message)) {
        std::lock_guard lock(mutex_);
        statuses_.push_back(message.status());
        cv_.notify_all();
      }
      grpc::Status status = reader_->Finish();
      std::lock_guard lock(mutex_);
      end_status_ = status;
      ended_ = true;
      cv_.notify_all();
    });
  }
  ~MissionWatcher() {
    context_.TryCancel();
    thread_.join();
  }
  MissionWatcher(const MissionWatcher&) = delete;
  MissionWatcher& operator=(const MissionWatcher&) = delete;

  /// The first status received that matches `predicate`.
  std::optional<v1::MissionStatus> waitFor(
      const std::function<bool(const v1::MissionStatus&)>& predicate, milliseconds timeout) {
    std::unique_lock lock(mutex_);
    std::optional<v1::MissionStatus> found;
    cv_.wait_for(lock, timeout, [&] {
      for (const auto& s : statuses_) {
        if (predicate(s)) {
          found = s;
          return true;
        }
      }
      return ended_;
    });
    return found;
  }
  /// Waits until the stream ends (it ends after the mission has ended); the
  /// last status, or nullopt on timeout or an error status.
  std::optional<v1::MissionStatus> waitEnd(milliseconds timeout) {
    std::unique_lock lock(mutex_);
    if (!cv_.wait_for(lock, timeout, [&] { return ended_; })) {
      ADD_FAILURE() << "the mission did not end within " << timeout.count()
                    << " ms; last: " << (statuses_.empty() ? "none" : json(statuses_.back()));
      return std::nullopt;
    }
    EXPECT_TRUE(end_status_.ok()) << describe(end_status_);
    if (statuses_.empty()) return std::nullopt;
    return statuses_.back();
  }
  std::vector<v1::MissionStatus> statuses() {
    std::lock_guard lock(mutex_);
    return statuses_;
  }
  /// The stream's final status, once it ended (within `timeout`).
  std::optional<grpc::Status> endStatus(milliseconds timeout) {
    std::unique_lock lock(mutex_);
    if (!cv_.wait_for(lock, timeout, [&] { return ended_; })) return std::nullopt;
    return end_status_;
  }

 private:
  std::unique_ptr<v1::Coordinator::Stub> stub_;
  grpc::ClientContext context_;
  std::unique_ptr<grpc::ClientReader<v1::WatchMissionResponse>> reader_;
  std::thread thread_;
  std::mutex mutex_;
  std::condition_variable cv_;
  std::vector<v1::MissionStatus> statuses_;
  bool ended_ = false;
  grpc::Status end_status_;
};

/// Every event a behavior system retains (its own WatchEvents from
/// since_seq 0, up to its latest seq at the time of the call).
inline std::vector<v1::BehaviorEvent> systemHistory(const std::string& address) {
  auto stub =
      v1::BehaviorSystem::NewStub(grpc::CreateChannel(address, grpc::InsecureChannelCredentials()));
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + kCallTimeout);
  v1::WatchEventsRequest request;
  request.set_since_seq(0);
  auto reader = stub->WatchEvents(&context, request);
  v1::WatchEventsResponse message;
  std::vector<v1::BehaviorEvent> events;
  if (!reader->Read(&message) || !message.has_start()) {
    ADD_FAILURE() << "no WatchEventsStart from " << address;
    return events;
  }
  const uint64_t latest = message.start().latest_seq();
  EXPECT_FALSE(message.start().events_dropped()) << "the history is complete";
  while (events.size() < latest && reader->Read(&message)) {
    if (message.has_event()) events.push_back(message.event());
    if (message.has_event() && message.event().seq() >= latest) break;
  }
  context.TryCancel();
  reader->Finish();
  return events;
}

}  // namespace coordinator_test
