#pragma once

// The vehicles' samples for the coordinator's telemetry calls
// (GetVehicleSample, WatchVehicle): the newest sample of one of a robot's
// topics, or a rate-limited stream of them, read from the data channel. A
// request names a robot and a VehicleSampleKind, never a topic, and the robot
// must be one the coordinator knows; watches are bounded in all and per
// caller (decision 47).
//
//   VehicleTelemetry telemetry(channel, &sim_clock, known, {.max_watches = 64});
//   absl::StatusOr<v1::VehicleSample> pose =
//       telemetry.latest("drone1", v1::VEHICLE_SAMPLE_KIND_POSE, 1.0);
//   auto watch = telemetry.watch("alice", request, [](v1::WatchVehicleResponse r) { ... });
//   watch->reset();   // ends the subscription and frees the slot

#include <cstddef>
#include <functional>
#include <map>
#include <memory>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "absl/base/thread_annotations.h"
#include "absl/status/statusor.h"
#include "absl/synchronization/mutex.h"
#include "behaviorlib/channel/channel_client.h"
#include "behaviorlib/clock.h"
#include "behaviorlib/v1/coordinator.pb.h"

namespace behaviorlib::coordinator {

struct VehicleTelemetryLimits {
  /// Watches open at once, in all.
  size_t max_watches = 64;
  /// Watches open at once by one caller (its identity, else its address).
  size_t max_watches_per_caller = 16;
  /// The default and the largest WatchVehicleRequest.max_rate_hz.
  double default_rate_hz = 10.0;
  double max_rate_hz = 200.0;
  /// How long a GetVehicleSample waits for the broker.
  std::chrono::milliseconds read_timeout{500};
};

/// Thread-safe.
class VehicleTelemetry {
 public:
  /// `channel` and `vehicle_clock` (the vehicles' time, for ages; null when
  /// the coordinator does not follow it) must outlive this object.
  /// `known_robot` tells whether a robot id is one of the fleet's;
  /// `watches_changed`, if set, is told the number of open watches after
  /// each change (a gauge).
  VehicleTelemetry(channel::ChannelClient& channel, const Clock* vehicle_clock,
                   std::function<bool(const std::string&)> known_robot,
                   VehicleTelemetryLimits limits = {},
                   std::function<void(size_t)> watches_changed = nullptr);
  ~VehicleTelemetry();
  VehicleTelemetry(const VehicleTelemetry&) = delete;
  VehicleTelemetry& operator=(const VehicleTelemetry&) = delete;

  /// The robot's topic of `kind`, or INVALID_ARGUMENT for an unknown kind.
  static absl::StatusOr<std::string> topicOf(const std::string& robot_id,
                                             v1::VehicleSampleKind kind);

  /// The newest sample. INVALID_ARGUMENT (a bad robot id or kind), NOT_FOUND
  /// (UNKNOWN_ROBOT; TOPIC_EMPTY when nothing was published), FAILED_PRECONDITION
  /// (SAMPLE_STALE: older than `max_age_s` in the vehicles' time; 0 means 1 s,
  /// negative no limit), UNAVAILABLE (the channel).
  absl::StatusOr<v1::VehicleSample> latest(const std::string& robot_id, v1::VehicleSampleKind kind,
                                           double max_age_s);

  /// An open watch: its subscription runs until it is destroyed (which must
  /// not happen inside its callback). Destroying it does not wait: the
  /// subscription is ended, and its place freed, on the telemetry's own
  /// thread, because ending a channel subscription joins its reader, which
  /// must never block a gRPC callback thread (the cancellation it waits for
  /// may need that thread).
  class Watch {
   public:
    virtual ~Watch() = default;
  };
  /// Subscribes to the robot's topic of `request.kind`; `on_sample` runs on
  /// the subscription's thread for each sample. Errors as latest(), and
  /// RESOURCE_EXHAUSTED (LIMIT_EXCEEDED) past the limits.
  absl::StatusOr<std::unique_ptr<Watch>> watch(
      const std::string& caller, const v1::WatchVehicleRequest& request,
      std::function<void(v1::WatchVehicleResponse)> on_sample);

  /// Watches open now (for tests and the metrics).
  size_t openWatches() const;

 private:
  class WatchImpl;
  absl::Status checkRobot(const std::string& robot_id) const;
  /// The sample of `response` as a VehicleSample (its stamp and age).
  absl::StatusOr<v1::VehicleSample> toSample(const std::string& robot_id,
                                             v1::VehicleSampleKind kind,
                                             const v1::SubscribeResponse& response) const;
  /// Ends `subscription` and frees the caller's place, on the reaper thread.
  void retire(std::unique_ptr<channel::Subscription> subscription, std::string caller);
  void reap();

  channel::ChannelClient& channel_;
  const Clock* const vehicle_clock_;
  const std::function<bool(const std::string&)> known_robot_;
  const VehicleTelemetryLimits limits_;
  const std::function<void(size_t)> watches_changed_;
  mutable absl::Mutex mutex_;
  size_t open_ ABSL_GUARDED_BY(mutex_) = 0;
  std::map<std::string, size_t> per_caller_ ABSL_GUARDED_BY(mutex_);
  // Subscriptions to end, with their callers; the reaper ends them in order.
  std::vector<std::pair<std::unique_ptr<channel::Subscription>, std::string>> retired_
      ABSL_GUARDED_BY(mutex_);
  bool stopping_ ABSL_GUARDED_BY(mutex_) = false;
  std::thread reaper_;
};

}  // namespace behaviorlib::coordinator
