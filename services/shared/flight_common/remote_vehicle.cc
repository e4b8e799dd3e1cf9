#include "behaviorlib/flight_common/remote_vehicle.h"

#include "behaviorlib/flight_common/flight_support.h"
#include "behaviorlib/flight_common/setpoint_stream.h"
#include "behaviorlib/flight_common/topics.h"
#include "behaviorlib/platform/lease_keeper.h"

namespace behaviorlib::flight {
namespace {

class RemoteLease final : public VehicleLease {
 public:
  RemoteLease(const platform::FlightControllerClient& client,
              std::unique_ptr<platform::LeaseKeeper> keeper, server::SetpointLedger* setpoints)
      : client_(client), keeper_(std::move(keeper)), setpoints_(setpoints) {}

  absl::Status status() const override { return keeper_->status(); }
  absl::StatusOr<v1::FlightState> execute(v1::FlightAction action,
                                          double takeoff_altitude_m) override {
    return client_.executeFlightAction(keeper_->id(), action, takeoff_altitude_m);
  }
  absl::StatusOr<v1::FlightState> goTo(double x_m, double y_m, double z_m,
                                       double yaw_rad) override {
    return client_.sendPositionSetpoint(keeper_->id(), x_m, y_m, z_m, yaw_rad);
  }
  absl::Status send(v1::SetpointRequest setpoint) override {
    if (!stream_) stream_ = std::make_unique<SetpointStream>(client_, keeper_->id(), setpoints_);
    return stream_->send(std::move(setpoint));
  }
  absl::Status release() override {
    stream_.reset();  // the stream ends before the lease is released
    return keeper_->release();
  }

 private:
  const platform::FlightControllerClient& client_;
  std::unique_ptr<platform::LeaseKeeper> keeper_;
  server::SetpointLedger* const setpoints_;  // may be null
  std::unique_ptr<SetpointStream> stream_;
};

}  // namespace

TimePoint stampTime(const v1::Header& header) {
  return TimePoint(std::chrono::seconds(header.stamp().seconds()) +
                   std::chrono::nanoseconds(header.stamp().nanos()));
}

RemoteVehicle::RemoteVehicle(const server::SystemContext& context)
    : robot_id_(context.robot_id),
      clock_(*context.clock),
      channel_(context.channel),
      setpoints_(context.setpoints) {
  if (!context.flight_controller.empty()) {
    flight_controller_ =
        std::make_unique<platform::FlightControllerClient>(context.flight_controller, robot_id_);
    watcher_ = std::make_unique<platform::FlightStateWatcher>(*flight_controller_);
  }
}

RemoteVehicle::~RemoteVehicle() {
  std::unique_ptr<channel::Subscription> pose, twist;
  {
    absl::MutexLock lock(&mutex_);
    pose = std::move(pose_subscription_);
    twist = std::move(twist_subscription_);
  }
}

absl::StatusOr<v1::FlightStatus> RemoteVehicle::flightStatus() const {
  if (!watcher_) {
    return absl::FailedPreconditionError(
        "no flight controller configured: start the behavior system with --flight-controller "
        "HOST:PORT (the simulator's address)");
  }
  return watcher_->latest();
}

absl::StatusOr<std::unique_ptr<VehicleLease>> RemoteVehicle::acquireLease(const std::string& holder,
                                                                          Duration ttl,
                                                                          bool preempt) {
  if (!flight_controller_) return flightStatus().status();
  auto keeper = platform::LeaseKeeper::acquire(*flight_controller_, clock_, holder,
                                               {.ttl = ttl, .preempt = preempt});
  if (!keeper.ok()) return keeper.status();
  return std::unique_ptr<VehicleLease>(
      new RemoteLease(*flight_controller_, std::move(*keeper), setpoints_));
}

void RemoteVehicle::followEstimate(bool follow) {
  if (!channel_) return;
  // Declared first: a dropped subscription is destroyed (its reader joined)
  // after the lock is released, since its callback takes the lock.
  std::unique_ptr<channel::Subscription> old_pose, old_twist;
  absl::MutexLock lock(&mutex_);
  if (follow) {
    if (followers_++ > 0) return;
    const channel::SubscribeOptions options{.mode = v1::DELIVERY_MODE_LATEST,
                                            .send_latest_first = true};
    pose_subscription_ = channel_->subscribeTyped<v1::PoseStamped>(
        poseEstimateTopic(robot_id_), options, [this](const v1::PoseStamped& pose) {
          auto sample = std::make_shared<const v1::PoseStamped>(pose);
          absl::MutexLock inner(&mutex_);
          // A sample delivered while the last follower is leaving must not
          // stay behind as the cache (nothing would refresh it).
          if (followers_ > 0) pose_.swap(sample);  // the old one is freed outside the lock
        });
    twist_subscription_ = channel_->subscribeTyped<v1::TwistStamped>(
        twistEstimateTopic(robot_id_), options, [this](const v1::TwistStamped& twist) {
          auto sample = std::make_shared<const v1::TwistStamped>(twist);
          absl::MutexLock inner(&mutex_);
          if (followers_ > 0) twist_.swap(sample);  // the old one is freed outside the lock
        });
    return;
  }
  if (followers_ == 0 || --followers_ > 0) return;
  old_pose = std::move(pose_subscription_);
  old_twist = std::move(twist_subscription_);
  pose_.reset();
  twist_.reset();
}

template <class T>
absl::StatusOr<T> RemoteVehicle::latest(const std::string& topic, std::shared_ptr<const T>* cache) {
  if (!channel_) {
    return absl::FailedPreconditionError(
        "no data channel configured: start the behavior system with --channel HOST:PORT");
  }
  {
    absl::MutexLock lock(&mutex_);
    if (*cache) return **cache;
  }
  auto sample = channel_->getLatest(topic, flight::kChannelReadTimeout);
  if (!sample.ok()) {
    if (sample.status().code() == absl::StatusCode::kNotFound) {
      return absl::NotFoundError("nothing published on " + topic +
                                 " yet: activate a localization behavior such as "
                                 "SELF_LOCALIZE_WITH_GROUND_TRUTH");
    }
    return absl::Status(sample.status().code(), "cannot read " + topic + " from the channel at " +
                                                    channel_->address() + ": " +
                                                    std::string(sample.status().message()));
  }
  T message;
  if (!sample->sample().UnpackTo(&message)) {
    return absl::FailedPreconditionError(topic + " carries " + sample->sample().type_url() +
                                         ", not " + T::descriptor()->full_name());
  }
  // Not cached: until the subscription delivers (it sends the newest sample
  // first once established), each read asks the channel. A sample cached
  // here would stay while the subscription is being established, and age:
  // in the deterministic mode, simulated time runs ahead of the wall clock,
  // and LAND once ended PROCESS_FAILURE on a 1.01 s old pose estimate exactly
  // 1 s after its activation.
  return message;
}

absl::StatusOr<v1::PoseStamped> RemoteVehicle::poseEstimate() {
  return latest(poseEstimateTopic(robot_id_), &pose_);
}

absl::StatusOr<v1::TwistStamped> RemoteVehicle::twistEstimate() {
  return latest(twistEstimateTopic(robot_id_), &twist_);
}

std::string RemoteVehicle::poseTopic() const { return poseEstimateTopic(robot_id_); }

absl::Status RemoteVehicle::readFlightStatus(Held<v1::FlightStatus>* out) const {
  if (!watcher_) return flightStatus().status();
  auto status = watcher_->latestShared();
  if (!status.ok()) return status.status();
  out->hold(*std::move(status));
  return absl::OkStatus();
}

template <class T>
bool RemoteVehicle::holdCached(const std::shared_ptr<const T>* cache, Held<T>* out) {
  std::shared_ptr<const T> sample;
  {
    absl::MutexLock lock(&mutex_);
    sample = *cache;
  }
  if (!sample) return false;
  out->hold(std::move(sample));
  return true;
}

absl::Status RemoteVehicle::readPoseEstimate(Held<v1::PoseStamped>* out) {
  if (holdCached(&pose_, out)) return absl::OkStatus();
  return holdInto(poseEstimate(), out);
}

absl::Status RemoteVehicle::readTwistEstimate(Held<v1::TwistStamped>* out) {
  if (holdCached(&twist_, out)) return absl::OkStatus();
  return holdInto(twistEstimate(), out);
}

}  // namespace behaviorlib::flight
