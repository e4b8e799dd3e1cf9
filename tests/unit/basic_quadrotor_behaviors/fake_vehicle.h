#pragma once

// A Vehicle driven by the test: flight state, battery, position and velocity
// set by hand, pose stamps from the FakeClock (or frozen), reachability
// switchable; the flight actions and setpoints the behaviors send are
// recorded.

#include <cmath>
#include <cstdio>
#include <mutex>
#include <string>
#include <vector>

#include "behaviorlib/clock.h"
#include "behaviorlib/flight_common/vehicle.h"

namespace behaviorlib::basic::testing {

class FakeVehicle final : public flight::Vehicle {
 public:
  explicit FakeVehicle(const FakeClock& clock) : clock_(clock) {}

  void setState(v1::FlightState state) {
    std::lock_guard lock(mutex_);
    state_ = state;
  }
  void setBattery(double ratio) {
    std::lock_guard lock(mutex_);
    battery_ = ratio;
  }
  void setReachable(bool reachable) {
    std::lock_guard lock(mutex_);
    reachable_ = reachable;
  }
  void setPosition(double x, double y, double z) {
    std::lock_guard lock(mutex_);
    x_ = x;
    y_ = y;
    z_ = z;
  }
  void setVerticalSpeed(double vz) {
    std::lock_guard lock(mutex_);
    vz_ = vz;
  }
  void setVelocity(double vx, double vy, double vz) {
    std::lock_guard lock(mutex_);
    vx_ = vx;
    vy_ = vy;
    vz_ = vz;
  }
  /// Yaw of the pose estimate (rad, counter-clockwise from +x).
  void setYaw(double yaw) {
    std::lock_guard lock(mutex_);
    yaw_ = yaw;
  }
  /// Roll and pitch of the pose estimate (rad; Z-Y-X with the yaw), e.g.
  /// the lean of a vehicle holding against wind.
  void setTilt(double roll, double pitch) {
    std::lock_guard lock(mutex_);
    roll_ = roll;
    pitch_ = pitch;
  }
  /// Frozen: the estimate keeps the stamp it had (its source stopped).
  void freezeEstimate(bool frozen) {
    std::lock_guard lock(mutex_);
    frozen_at_ = clock_.now();
    frozen_ = frozen;
  }
  /// The lease is taken by someone else: renewals fail.
  void loseLease() {
    std::lock_guard lock(mutex_);
    lease_lost_ = true;
  }
  std::vector<std::string> commands() const {
    std::lock_guard lock(mutex_);
    return commands_;
  }
  /// Setpoints streamed under a lease (VehicleLease::send).
  std::vector<v1::SetpointRequest> setpoints() const {
    std::lock_guard lock(mutex_);
    return setpoints_;
  }
  std::string leaseHolder() const {
    std::lock_guard lock(mutex_);
    return holder_;
  }

  const std::string& robotId() const override { return robot_id_; }

  absl::StatusOr<v1::FlightStatus> flightStatus() const override {
    std::lock_guard lock(mutex_);
    if (!reachable_) return absl::UnavailableError("flight controller at fake:1 is unreachable");
    v1::FlightStatus status;
    status.set_state(state_);
    status.set_battery_ratio(battery_);
    status.set_lease_holder(holder_);
    return status;
  }

  absl::StatusOr<std::unique_ptr<flight::VehicleLease>> acquireLease(const std::string& holder,
                                                                     Duration, bool) override {
    std::lock_guard lock(mutex_);
    if (!reachable_) return absl::UnavailableError("flight controller at fake:1 is unreachable");
    holder_ = holder;
    lease_lost_ = false;
    return std::unique_ptr<flight::VehicleLease>(new Lease(this));
  }

  void followEstimate(bool follow) override {
    std::lock_guard lock(mutex_);
    followers_ += follow ? 1 : -1;
  }
  int followers() const {
    std::lock_guard lock(mutex_);
    return followers_;
  }

  absl::StatusOr<v1::PoseStamped> poseEstimate() override {
    std::lock_guard lock(mutex_);
    v1::PoseStamped pose;
    stamp(pose.mutable_header());
    pose.mutable_pose()->mutable_position_m()->set_x(x_);
    pose.mutable_pose()->mutable_position_m()->set_y(y_);
    pose.mutable_pose()->mutable_position_m()->set_z(z_);
    const double cy = std::cos(yaw_ / 2), sy = std::sin(yaw_ / 2);
    const double cp = std::cos(pitch_ / 2), sp = std::sin(pitch_ / 2);
    const double cr = std::cos(roll_ / 2), sr = std::sin(roll_ / 2);
    auto* q = pose.mutable_pose()->mutable_orientation();
    q->set_w(cr * cp * cy + sr * sp * sy);
    q->set_x(sr * cp * cy - cr * sp * sy);
    q->set_y(cr * sp * cy + sr * cp * sy);
    q->set_z(cr * cp * sy - sr * sp * cy);
    return pose;
  }
  absl::StatusOr<v1::TwistStamped> twistEstimate() override {
    std::lock_guard lock(mutex_);
    v1::TwistStamped twist;
    stamp(twist.mutable_header());
    twist.mutable_twist()->mutable_linear_m_s()->set_x(vx_);
    twist.mutable_twist()->mutable_linear_m_s()->set_y(vy_);
    twist.mutable_twist()->mutable_linear_m_s()->set_z(vz_);
    return twist;
  }
  std::string poseTopic() const override { return "robots/drone1/self_localization/pose"; }

 private:
  class Lease final : public flight::VehicleLease {
   public:
    explicit Lease(FakeVehicle* vehicle) : vehicle_(vehicle) {}
    ~Lease() override { release().IgnoreError(); }
    absl::Status status() const override {
      std::lock_guard lock(vehicle_->mutex_);
      if (vehicle_->lease_lost_) return absl::FailedPreconditionError("lease taken by 'intruder'");
      if (!vehicle_->reachable_) return absl::UnavailableError("renewals fail: unreachable");
      return absl::OkStatus();
    }
    absl::StatusOr<v1::FlightState> execute(v1::FlightAction action, double altitude) override {
      std::lock_guard lock(vehicle_->mutex_);
      if (!vehicle_->reachable_) return absl::UnavailableError("unreachable");
      std::string command = v1::FlightAction_Name(action).substr(strlen("FLIGHT_ACTION_"));
      if (action == v1::FLIGHT_ACTION_TAKE_OFF) {
        char text[32];
        std::snprintf(text, sizeof(text), " %.2f", altitude);
        command += text;
      }
      vehicle_->commands_.push_back(command);
      return vehicle_->state_;
    }
    absl::StatusOr<v1::FlightState> goTo(double, double, double z, double) override {
      std::lock_guard lock(vehicle_->mutex_);
      char text[32];
      std::snprintf(text, sizeof(text), "GOTO %.2f", z);
      vehicle_->commands_.push_back(text);
      return vehicle_->state_;
    }
    absl::Status send(v1::SetpointRequest setpoint) override {
      std::lock_guard lock(vehicle_->mutex_);
      if (!vehicle_->reachable_) return absl::UnavailableError("unreachable");
      vehicle_->setpoints_.push_back(std::move(setpoint));
      return absl::OkStatus();
    }
    absl::Status release() override {
      std::lock_guard lock(vehicle_->mutex_);
      if (released_) return absl::OkStatus();
      released_ = true;
      vehicle_->commands_.push_back("RELEASE");
      vehicle_->holder_.clear();
      return absl::OkStatus();
    }

   private:
    FakeVehicle* vehicle_;
    bool released_ = false;
  };

  void stamp(v1::Header* header) const {
    const TimePoint t = frozen_ ? frozen_at_ : clock_.now();
    const auto ns = t.time_since_epoch().count();
    header->mutable_stamp()->set_seconds(ns / 1000000000);
    header->mutable_stamp()->set_nanos(static_cast<int32_t>(ns % 1000000000));
  }

  const FakeClock& clock_;
  const std::string robot_id_ = "drone1";
  mutable std::mutex mutex_;
  v1::FlightState state_ = v1::FLIGHT_STATE_LANDED;
  double battery_ = 1.0;
  bool reachable_ = true;
  double x_ = 0, y_ = 0, z_ = 0, vx_ = 0, vy_ = 0, vz_ = 0, yaw_ = 0, roll_ = 0, pitch_ = 0;
  bool frozen_ = false;
  TimePoint frozen_at_{};
  bool lease_lost_ = false;
  std::string holder_;
  int followers_ = 0;
  std::vector<std::string> commands_;
  std::vector<v1::SetpointRequest> setpoints_;
};

}  // namespace behaviorlib::basic::testing
