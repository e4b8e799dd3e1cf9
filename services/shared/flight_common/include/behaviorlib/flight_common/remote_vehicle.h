#pragma once

// RemoteVehicle: the Vehicle of a behavior-system process — the platform
// through behaviorlib::platform_client (--flight-controller; its flight state
// followed by a WatchFlightState stream for the process's whole life) and the
// pose estimate through the data channel (--channel).
//
//   auto& vehicle = builder.own(std::make_unique<RemoteVehicle>(builder.context()));

#include <memory>
#include <optional>
#include <string>

#include "absl/synchronization/mutex.h"
#include "behaviorlib/channel/channel_client.h"
#include "behaviorlib/flight_common/vehicle.h"
#include "behaviorlib/platform/flight_controller_client.h"
#include "behaviorlib/platform/flight_state_watcher.h"
#include "behaviorlib/server/behavior_system_main.h"

namespace behaviorlib::flight {

class RemoteVehicle final : public Vehicle {
 public:
  explicit RemoteVehicle(const server::SystemContext& context);
  ~RemoteVehicle() override;

  const std::string& robotId() const override { return robot_id_; }
  absl::StatusOr<v1::FlightStatus> flightStatus() const override;
  absl::StatusOr<std::unique_ptr<VehicleLease>> acquireLease(const std::string& holder,
                                                             Duration ttl, bool preempt) override;
  void followEstimate(bool follow) override;
  absl::StatusOr<v1::PoseStamped> poseEstimate() override;
  absl::StatusOr<v1::TwistStamped> twistEstimate() override;
  std::string poseTopic() const override;
  absl::Status readFlightStatus(Held<v1::FlightStatus>* out) const override;
  absl::Status readPoseEstimate(Held<v1::PoseStamped>* out) override;
  absl::Status readTwistEstimate(Held<v1::TwistStamped>* out) override;

 private:
  template <class T>
  absl::StatusOr<T> latest(const std::string& topic, std::shared_ptr<const T>* cache);
  // The followed estimate shared into `out` (true), or false when none is
  // cached (the caller reads the channel).
  template <class T>
  bool holdCached(const std::shared_ptr<const T>* cache, Held<T>* out);

  const std::string robot_id_;
  const Clock& clock_;
  channel::ChannelClient* channel_;
  server::SetpointLedger* setpoints_;  // may be null
  std::unique_ptr<platform::FlightControllerClient> flight_controller_;
  std::unique_ptr<platform::FlightStateWatcher> watcher_;

  absl::Mutex mutex_;
  int followers_ ABSL_GUARDED_BY(mutex_) = 0;
  // The followed estimates, each sample a new one (readers may hold the
  // old). latest() and holdCached() reach them through a pointer, which the
  // analysis does not follow; they hold mutex_.
  std::shared_ptr<const v1::PoseStamped> pose_ ABSL_GUARDED_BY(mutex_);
  std::shared_ptr<const v1::TwistStamped> twist_ ABSL_GUARDED_BY(mutex_);
  std::unique_ptr<channel::Subscription> pose_subscription_ ABSL_GUARDED_BY(mutex_);
  std::unique_ptr<channel::Subscription> twist_subscription_ ABSL_GUARDED_BY(mutex_);
};

}  // namespace behaviorlib::flight
