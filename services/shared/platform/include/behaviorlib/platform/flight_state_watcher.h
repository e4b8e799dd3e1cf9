#pragma once

// FlightStateWatcher: follows a vehicle's FlightStatus through
// FlightController.WatchFlightState (the current status first, then every
// change) on a thread of its own, reconnecting with backoff (100 ms to 1 s)
// whenever the stream ends, until destroyed. A behavior system keeps one per
// vehicle for its whole life, so that checkSituation can answer at once and
// checkProcesses sees a flight controller that went away.
//
//   FlightStateWatcher watcher(fc);
//   absl::StatusOr<v1::FlightStatus> status = watcher.latest();
//   // UNAVAILABLE naming the address and the error while not connected.

#include <chrono>
#include <functional>
#include <memory>
#include <optional>
#include <thread>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/synchronization/mutex.h"
#include "behaviorlib/platform/flight_controller_client.h"

namespace behaviorlib::platform {

class FlightStateWatcher {
 public:
  /// Starts watching at once. `client` must outlive the watcher.
  explicit FlightStateWatcher(const FlightControllerClient& client);
  /// Cancels the stream and joins the thread.
  ~FlightStateWatcher();
  FlightStateWatcher(const FlightStateWatcher&) = delete;
  FlightStateWatcher& operator=(const FlightStateWatcher&) = delete;

  /// The latest status while the stream is up; otherwise UNAVAILABLE (or
  /// the code the stream ended with) saying why there is none.
  absl::StatusOr<v1::FlightStatus> latest() const;
  /// The same, shared: no copy (a reader every tick takes it so).
  absl::StatusOr<std::shared_ptr<const v1::FlightStatus>> latestShared() const;
  /// Whether a stream is up and has delivered the current status.
  bool connected() const;
  /// Statuses received so far (over all streams).
  uint64_t receivedCount() const;
  /// Waits (wall time) until connected or `timeout`; returns connected().
  bool waitConnected(std::chrono::milliseconds timeout) const;

 private:
  void run();

  const FlightControllerClient& client_;
  mutable absl::Mutex mutex_;
  bool stopping_ ABSL_GUARDED_BY(mutex_) = false;
  // The running stream's, for cancel.
  grpc::ClientContext* context_ ABSL_GUARDED_BY(mutex_) = nullptr;
  bool connected_ ABSL_GUARDED_BY(mutex_) = false;
  // Replaced, never changed.
  std::shared_ptr<const v1::FlightStatus> latest_ ABSL_GUARDED_BY(mutex_);
  absl::Status error_ ABSL_GUARDED_BY(mutex_);
  uint64_t received_ ABSL_GUARDED_BY(mutex_) = 0;
  std::thread thread_;
};

}  // namespace behaviorlib::platform
