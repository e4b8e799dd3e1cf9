#include "behaviorlib/platform/flight_state_watcher.h"

#include <algorithm>

namespace behaviorlib::platform {

FlightStateWatcher::FlightStateWatcher(const FlightControllerClient& client)
    : client_(client),
      error_(absl::UnavailableError("no flight state yet from the flight controller at " +
                                    client.address() + " (connecting)")) {
  thread_ = std::thread([this] { run(); });
}

FlightStateWatcher::~FlightStateWatcher() {
  {
    absl::MutexLock lock(&mutex_);
    stopping_ = true;
    if (context_) context_->TryCancel();
  }
  thread_.join();
}

absl::StatusOr<v1::FlightStatus> FlightStateWatcher::latest() const {
  absl::MutexLock lock(&mutex_);
  if (connected_ && latest_) return *latest_;
  return error_;
}

absl::StatusOr<std::shared_ptr<const v1::FlightStatus>> FlightStateWatcher::latestShared() const {
  absl::MutexLock lock(&mutex_);
  if (connected_ && latest_) return latest_;
  return error_;
}

bool FlightStateWatcher::connected() const {
  absl::MutexLock lock(&mutex_);
  return connected_ && latest_ != nullptr;
}

uint64_t FlightStateWatcher::receivedCount() const {
  absl::MutexLock lock(&mutex_);
  return received_;
}

bool FlightStateWatcher::waitConnected(std::chrono::milliseconds timeout) const {
  absl::MutexLock lock(&mutex_);
  const auto ready = [this]() ABSL_EXCLUSIVE_LOCKS_REQUIRED(mutex_) {
    return connected_ && latest_ != nullptr;
  };
  return mutex_.AwaitWithTimeout(absl::Condition(&ready), absl::FromChrono(timeout));
}

void FlightStateWatcher::run() {
  constexpr std::chrono::milliseconds kInitialBackoff(100);
  constexpr std::chrono::milliseconds kMaxBackoff(1000);
  std::chrono::milliseconds backoff = kInitialBackoff;
  while (true) {
    grpc::ClientContext context;
    {
      absl::MutexLock lock(&mutex_);
      if (stopping_) return;
      context_ = &context;
    }
    v1::WatchFlightStateRequest request;
    request.set_robot_id(client_.robotId());
    auto reader = client_.stub().WatchFlightState(&context, request);
    v1::WatchFlightStateResponse message;
    while (reader->Read(&message)) {
      auto status = std::make_shared<const v1::FlightStatus>(std::move(*message.mutable_status()));
      absl::MutexLock lock(&mutex_);
      latest_ = std::move(status);
      connected_ = true;
      ++received_;
      backoff = kInitialBackoff;
    }
    const grpc::Status status = reader->Finish();
    absl::MutexLock lock(&mutex_);
    context_ = nullptr;
    connected_ = false;
    if (stopping_) return;
    error_ = client_.describe(
        status.ok() ? grpc::Status(grpc::StatusCode::UNAVAILABLE, "the flight-state stream ended")
                    : status,
        "WatchFlightState");
    mutex_.AwaitWithTimeout(absl::Condition(&stopping_), absl::FromChrono(backoff));
    backoff = std::min(backoff * 2, kMaxBackoff);
  }
}

}  // namespace behaviorlib::platform
