#pragma once

// Vehicle: what the flight behaviors (basic_quadrotor_behaviors and the
// motion behavior systems) need from the robot — the platform's flight status, its command lease
// and flight actions, and the pose estimate on the data channel — behind an interface, so that
// their monitoring logic is unit-tested against a fake vehicle on a FakeClock. RemoteVehicle
// (remote_vehicle.h) is the real one: the FlightController over gRPC and the data channel.

#include <memory>
#include <string>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "behaviorlib/clock.h"
#include "behaviorlib/v1/platform.pb.h"
#include "behaviorlib/v1/types.pb.h"

namespace behaviorlib::flight {

/// The vehicle's command-source lease, held while the object lives (it is
/// renewed in the background and released on destruction).
class VehicleLease {
 public:
  virtual ~VehicleLease() = default;
  /// OK while held; FAILED_PRECONDITION once lost to another holder or
  /// expired; UNAVAILABLE once the flight controller stopped answering the
  /// renewals for longer than the lease's ttl.
  virtual absl::Status status() const = 0;
  /// Performs a flight action under the lease (TAKE_OFF, LAND, HOVER).
  virtual absl::StatusOr<v1::FlightState> execute(v1::FlightAction action,
                                                  double takeoff_altitude_m = 0.0) = 0;
  /// A position + yaw setpoint under the lease (world frame ENU).
  virtual absl::StatusOr<v1::FlightState> goTo(double x_m, double y_m, double z_m,
                                               double yaw_rad) = 0;
  /// Streams a setpoint at any level (thrust + rates, attitude + thrust,
  /// velocity + yaw rate, position + yaw) under the lease, without waiting
  /// for an answer: the robot id and lease id are filled in. The platform
  /// ends the stream at the first refused setpoint; that refusal
  /// (INVALID_ARGUMENT, FAILED_PRECONDITION naming the reason) is returned
  /// by this call or the next one, which opens a new stream.
  virtual absl::Status send(v1::SetpointRequest setpoint) = 0;
  /// Releases the lease now (the vehicle keeps hovering).
  virtual absl::Status release() = 0;
};

/// A vehicle input as a behavior keeps it between ticks: the latest sample,
/// shared with the cache that received it and never changed, so taking the
/// newest costs a reference count where a copy would allocate every
/// sub-message and string again. Reads as the message (`status_->state()`,
/// `*pose_`); the empty message until the first sample.
template <class T>
class Held {
 public:
  const T& operator*() const { return sample_ ? *sample_ : T::default_instance(); }
  const T* operator->() const { return &**this; }
  void hold(std::shared_ptr<const T> sample) { sample_ = std::move(sample); }
  void reset() { sample_.reset(); }

 private:
  std::shared_ptr<const T> sample_;
};

class Vehicle {
 public:
  virtual ~Vehicle() = default;

  virtual const std::string& robotId() const = 0;

  /// The platform's latest flight status; FAILED_PRECONDITION when no
  /// flight controller is configured, UNAVAILABLE (naming its address)
  /// while it cannot be reached.
  virtual absl::StatusOr<v1::FlightStatus> flightStatus() const = 0;

  /// Takes the vehicle's command lease for `holder` ("drone1/TAKE_OFF").
  virtual absl::StatusOr<std::unique_ptr<VehicleLease>> acquireLease(const std::string& holder,
                                                                     Duration ttl,
                                                                     bool preempt) = 0;

  /// While at least one caller follows the estimate, pose and twist
  /// estimates are kept up to date by subscriptions; otherwise each read
  /// asks the channel for the latest sample.
  virtual void followEstimate(bool follow) = 0;
  /// The latest pose estimate (robots/{id}/self_localization/pose);
  /// NOT_FOUND when none was ever published, FAILED_PRECONDITION without a
  /// data channel, UNAVAILABLE when the channel cannot be reached.
  virtual absl::StatusOr<v1::PoseStamped> poseEstimate() = 0;
  /// The latest velocity estimate (robots/{id}/self_localization/twist).
  virtual absl::StatusOr<v1::TwistStamped> twistEstimate() = 0;
  /// The pose estimate's topic, for messages.
  virtual std::string poseTopic() const = 0;

  /// The same three reads, shared into `out` (Held): what a behavior reads
  /// every tick. `out` is left as it was on an error.
  virtual absl::Status readFlightStatus(Held<v1::FlightStatus>* out) const {
    return holdInto(flightStatus(), out);
  }
  virtual absl::Status readPoseEstimate(Held<v1::PoseStamped>* out) {
    return holdInto(poseEstimate(), out);
  }
  virtual absl::Status readTwistEstimate(Held<v1::TwistStamped>* out) {
    return holdInto(twistEstimate(), out);
  }

 protected:
  template <class T>
  static absl::Status holdInto(absl::StatusOr<T> read, Held<T>* out) {
    if (!read.ok()) return read.status();
    out->hold(std::make_shared<const T>(*std::move(read)));
    return absl::OkStatus();
  }
};

/// A header stamp as a time on the behaviors' clock.
TimePoint stampTime(const v1::Header& header);

}  // namespace behaviorlib::flight
