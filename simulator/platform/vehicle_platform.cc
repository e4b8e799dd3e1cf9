#include "simulator/platform/vehicle_platform.h"

#include <cmath>
#include <sstream>

#include "behaviorlib/error_details.h"

namespace behaviorlib::sim {
namespace {

bool airborne(v1::FlightState s) {
  return s == v1::FLIGHT_STATE_TAKING_OFF || s == v1::FLIGHT_STATE_FLYING ||
         s == v1::FLIGHT_STATE_HOVERING;
}

std::string stateName(v1::FlightState s) {
  std::string name = v1::FlightState_Name(s);
  constexpr std::string_view kPrefix = "FLIGHT_STATE_";
  return name.rfind(kPrefix, 0) == 0 ? name.substr(kPrefix.size()) : name;
}

// A crashed vehicle takes no lease and no action until a reset.
absl::Status crashed(const std::string& robot_id) {
  return errors::withReason(
      absl::FailedPreconditionError(robot_id + " has crashed; reset the simulation"),
      v1::SAFETY_REFUSED, {{"robot", robot_id}});
}

// The vehicle's flight state does not allow the action.
absl::Status stateConflict(const std::string& robot_id, v1::FlightState state,
                           const std::string& message) {
  return errors::withReason(absl::FailedPreconditionError(message), v1::FLIGHT_STATE_CONFLICT,
                            {{"robot", robot_id}, {"flight_state", v1::FlightState_Name(state)}});
}

std::string seconds(SimDuration d) {
  std::ostringstream out;
  out << std::chrono::duration<double>(d).count() << " s";
  return out.str();
}

google::protobuf::Timestamp toTimestamp(SimTime t) {
  google::protobuf::Timestamp ts;
  ts.set_seconds(std::chrono::duration_cast<std::chrono::seconds>(t).count());
  ts.set_nanos(
      static_cast<int32_t>((t - std::chrono::duration_cast<std::chrono::seconds>(t)).count()));
  return ts;
}

// Checks a vector field: finite, and |each component| <= limit.
absl::Status checkVector(const v1::Vector3& v, const std::string& field, double limit) {
  for (double c : {v.x(), v.y(), v.z()}) {
    if (!std::isfinite(c)) return absl::InvalidArgumentError(field + " must be finite numbers");
    if (std::abs(c) > limit) {
      return absl::InvalidArgumentError(field + " component " + std::to_string(c) +
                                        " is beyond the limit " + std::to_string(limit));
    }
  }
  return absl::OkStatus();
}

absl::Status checkRatio(double value, const std::string& field) {
  if (!std::isfinite(value) || value < 0.0 || value > 1.0) {
    return absl::InvalidArgumentError(field + " must be within [0, 1], got " +
                                      std::to_string(value));
  }
  return absl::OkStatus();
}

absl::Status checkFinite(double value, const std::string& field) {
  return std::isfinite(value) ? absl::OkStatus()
                              : absl::InvalidArgumentError(field + " must be a finite number");
}

}  // namespace

VehiclePlatform::VehiclePlatform(std::string robot_id, PlatformOptions options)
    : robot_id_(std::move(robot_id)), options_(options) {}

void VehiclePlatform::hoverHere() {
  command_ = PlatformCommand();
  command_.kind = PlatformCommand::Kind::kPositionYaw;
  command_.vector = vehicle_.position_m;
  command_.yaw_rad = vehicle_.yaw_rad;
}

void VehiclePlatform::expireLease(SimTime now) {
  lease_id_.clear();
  lease_holder_.clear();
  if (state_ == v1::FLIGHT_STATE_FLYING || state_ == v1::FLIGHT_STATE_HOVERING) {
    // Offboard loss: hold position, and land if nobody takes over.
    state_ = v1::FLIGHT_STATE_HOVERING;
    hoverHere();
    failsafe_active_ = true;
    failsafe_since_ = now;
  }
}

void VehiclePlatform::update(SimTime now, const VehicleSnapshot& vehicle) {
  vehicle_ = vehicle;
  if (vehicle.crashed) {
    state_ = v1::FLIGHT_STATE_CRASHED;
    command_ = PlatformCommand();
    failsafe_active_ = false;
    return;
  }
  if (!lease_id_.empty() && now >= lease_expiry_) expireLease(now);
  if (failsafe_active_ && state_ == v1::FLIGHT_STATE_HOVERING &&
      now - failsafe_since_ >= options_.failsafe_hover_time) {
    state_ = v1::FLIGHT_STATE_LANDING;
  }
  switch (state_) {
    case v1::FLIGHT_STATE_TAKING_OFF: {
      const double target_z = takeoff_origin_m_.z() + takeoff_altitude_m_;
      if (vehicle.position_m.z() >= target_z - options_.takeoff_tolerance_m) {
        state_ = v1::FLIGHT_STATE_HOVERING;
        command_ = PlatformCommand();
        command_.kind = PlatformCommand::Kind::kPositionYaw;
        command_.vector = {takeoff_origin_m_.x(), takeoff_origin_m_.y(), target_z};
        command_.yaw_rad = vehicle.yaw_rad;
      } else {
        command_ = PlatformCommand();
        command_.kind = PlatformCommand::Kind::kVelocityYawRate;
        command_.vector = {0.0, 0.0, options_.takeoff_speed_m_s};
      }
      break;
    }
    case v1::FLIGHT_STATE_LANDING:
    case v1::FLIGHT_STATE_EMERGENCY:
      if (vehicle.on_ground) {
        state_ = v1::FLIGHT_STATE_LANDED;
        command_ = PlatformCommand();
        failsafe_active_ = false;
      } else if (command_.kind != PlatformCommand::Kind::kIdle ||
                 state_ == v1::FLIGHT_STATE_LANDING) {
        command_ = PlatformCommand();
        command_.kind = PlatformCommand::Kind::kVelocityYawRate;
        command_.vector = {0.0, 0.0,
                           state_ == v1::FLIGHT_STATE_LANDING ? -options_.land_speed_m_s
                                                              : -options_.emergency_descent_m_s};
      }
      break;
    case v1::FLIGHT_STATE_LANDED:
      command_ = PlatformCommand();
      break;
    default:
      break;
  }
}

absl::Status VehiclePlatform::checkLease(const std::string& lease_id, SimTime now) const {
  if (lease_id.empty()) {
    return errors::withReason(
        absl::FailedPreconditionError("no lease_id given: call AcquireLease for " + robot_id_ +
                                      " first"),
        v1::LEASE_INVALID, {{"robot", robot_id_}});
  }
  if (lease_id != lease_id_ || now >= lease_expiry_) {
    return errors::withReason(
        absl::FailedPreconditionError(
            "lease " + lease_id + " does not command " + robot_id_ + " (" +
            (lease_id_.empty() ? std::string("no live lease; it expired or was released")
                               : "commanded by '" + lease_holder_ + "'") +
            "); acquire the lease again"),
        v1::LEASE_INVALID, {{"robot", robot_id_}});
  }
  return absl::OkStatus();
}

absl::StatusOr<v1::AcquireLeaseResponse> VehiclePlatform::acquireLease(const std::string& holder,
                                                                       SimDuration ttl,
                                                                       bool preempt, SimTime now) {
  if (holder.empty()) return absl::InvalidArgumentError("holder must name who commands");
  if (ttl == SimDuration::zero()) ttl = options_.default_lease_ttl;
  if (ttl < std::chrono::milliseconds(50) || ttl > std::chrono::seconds(10)) {
    return absl::InvalidArgumentError("ttl must be within [0.05 s, 10 s], got " + seconds(ttl));
  }
  if (state_ == v1::FLIGHT_STATE_CRASHED) return crashed(robot_id_);
  if (!lease_id_.empty() && now < lease_expiry_ && holder != lease_holder_ && !preempt) {
    return errors::withReason(
        absl::FailedPreconditionError(robot_id_ + " is commanded by '" + lease_holder_ +
                                      "' (lease expires in " + seconds(lease_expiry_ - now) +
                                      " unless renewed); set preempt to take over"),
        v1::LEASE_HELD, {{"robot", robot_id_}});
  }
  lease_id_ = robot_id_ + "-lease-" + std::to_string(++lease_counter_);
  lease_holder_ = holder;
  lease_ttl_ = ttl;
  lease_expiry_ = now + ttl;
  failsafe_active_ = false;  // someone took over: no failsafe landing
  v1::AcquireLeaseResponse response;
  response.set_lease_id(lease_id_);
  *response.mutable_expire_time() = toTimestamp(lease_expiry_);
  return response;
}

absl::StatusOr<v1::RenewLeaseResponse> VehiclePlatform::renewLease(const std::string& lease_id,
                                                                   SimTime now) {
  if (absl::Status s = checkLease(lease_id, now); !s.ok()) return s;
  lease_expiry_ = now + lease_ttl_;
  v1::RenewLeaseResponse response;
  *response.mutable_expire_time() = toTimestamp(lease_expiry_);
  return response;
}

absl::Status VehiclePlatform::releaseLease(const std::string& lease_id, SimTime now) {
  if (absl::Status s = checkLease(lease_id, now); !s.ok()) return s;
  lease_id_.clear();
  lease_holder_.clear();
  if (state_ == v1::FLIGHT_STATE_FLYING) {
    state_ = v1::FLIGHT_STATE_HOVERING;  // a clean hand-over: hold, no failsafe
    hoverHere();
  }
  return absl::OkStatus();
}

absl::StatusOr<v1::FlightState> VehiclePlatform::executeAction(v1::FlightAction action,
                                                               const std::string& lease_id,
                                                               double altitude_m, bool confirm,
                                                               SimTime now) {
  if (state_ == v1::FLIGHT_STATE_CRASHED) return crashed(robot_id_);
  switch (action) {
    case v1::FLIGHT_ACTION_KILL:
      if (!confirm) {
        return errors::withReason(
            absl::InvalidArgumentError("KILL stops the motors in flight; set confirm = true"),
            v1::CONFIRMATION_REQUIRED, {{"robot", robot_id_}});
      }
      command_ = PlatformCommand();  // motors off
      state_ = vehicle_.on_ground ? v1::FLIGHT_STATE_LANDED : v1::FLIGHT_STATE_EMERGENCY;
      failsafe_active_ = false;
      return state_;
    case v1::FLIGHT_ACTION_EMERGENCY_LAND:
      if (state_ == v1::FLIGHT_STATE_LANDED) return state_;
      state_ = v1::FLIGHT_STATE_EMERGENCY;
      command_ = PlatformCommand();
      command_.kind = PlatformCommand::Kind::kVelocityYawRate;
      command_.vector = {0.0, 0.0, -options_.emergency_descent_m_s};
      failsafe_active_ = false;
      return state_;
    case v1::FLIGHT_ACTION_TAKE_OFF:
    case v1::FLIGHT_ACTION_LAND:
    case v1::FLIGHT_ACTION_HOVER:
      break;
    default:
      return absl::InvalidArgumentError(
          "action must be TAKE_OFF, LAND, HOVER, EMERGENCY_LAND or "
          "KILL");
  }
  if (absl::Status s = checkLease(lease_id, now); !s.ok()) return s;
  if (action == v1::FLIGHT_ACTION_TAKE_OFF) {
    if (state_ != v1::FLIGHT_STATE_LANDED) {
      return stateConflict(robot_id_, state_,
                           "TAKE_OFF needs " + robot_id_ + " LANDED; it is " + stateName(state_));
    }
    if (altitude_m == 0.0) altitude_m = 1.0;
    if (!std::isfinite(altitude_m) || altitude_m < 0.2 || altitude_m > 100.0) {
      return absl::InvalidArgumentError("takeoff_altitude_m must be within [0.2, 100], got " +
                                        std::to_string(altitude_m));
    }
    takeoff_altitude_m_ = altitude_m;
    takeoff_origin_m_ = vehicle_.position_m;
    state_ = v1::FLIGHT_STATE_TAKING_OFF;
    lease_expiry_ = now + lease_ttl_;
    return state_;
  }
  if (!airborne(state_) && state_ != v1::FLIGHT_STATE_LANDING) {
    return stateConflict(robot_id_, state_,
                         std::string(action == v1::FLIGHT_ACTION_LAND ? "LAND" : "HOVER") +
                             " needs " + robot_id_ + " in the air; it is " + stateName(state_));
  }
  lease_expiry_ = now + lease_ttl_;
  if (action == v1::FLIGHT_ACTION_LAND) {
    state_ = v1::FLIGHT_STATE_LANDING;
  } else {
    state_ = v1::FLIGHT_STATE_HOVERING;
    hoverHere();
  }
  failsafe_active_ = false;
  return state_;
}

absl::StatusOr<v1::FlightState> VehiclePlatform::setpoint(const v1::SetpointRequest& request,
                                                          SimTime now) {
  if (absl::Status s = checkLease(request.lease_id(), now); !s.ok()) return s;
  if (state_ != v1::FLIGHT_STATE_FLYING && state_ != v1::FLIGHT_STATE_HOVERING) {
    return stateConflict(robot_id_, state_,
                         "setpoints need " + robot_id_ + " FLYING or HOVERING; it is " +
                             stateName(state_) +
                             (state_ == v1::FLIGHT_STATE_LANDED ? " (TAKE_OFF first)" : ""));
  }
  PlatformCommand next;
  switch (request.setpoint_case()) {
    case v1::SetpointRequest::kThrustRates: {
      const auto& sp = request.thrust_rates();
      if (auto s = checkRatio(sp.thrust_ratio(), "thrust_rates.thrust_ratio"); !s.ok()) return s;
      if (auto s =
              checkVector(sp.rates_rad_s(), "thrust_rates.rates_rad_s", options_.max_rate_rad_s);
          !s.ok()) {
        return s;
      }
      next.kind = PlatformCommand::Kind::kThrustRates;
      next.thrust_ratio = sp.thrust_ratio();
      next.vector = {sp.rates_rad_s().x(), sp.rates_rad_s().y(), sp.rates_rad_s().z()};
      break;
    }
    case v1::SetpointRequest::kAttitudeThrust: {
      const auto& sp = request.attitude_thrust();
      if (auto s = checkRatio(sp.thrust_ratio(), "attitude_thrust.thrust_ratio"); !s.ok()) {
        return s;
      }
      const auto& q = sp.orientation();
      const double norm = std::sqrt(q.w() * q.w() + q.x() * q.x() + q.y() * q.y() + q.z() * q.z());
      if (!std::isfinite(norm) || std::abs(norm - 1.0) > 0.01) {
        return absl::InvalidArgumentError(
            "attitude_thrust.orientation must be a unit quaternion (w, x, y, z); its norm is " +
            std::to_string(norm));
      }
      next.kind = PlatformCommand::Kind::kAttitudeThrust;
      next.thrust_ratio = sp.thrust_ratio();
      next.orientation = Eigen::Quaterniond(q.w(), q.x(), q.y(), q.z()).normalized();
      break;
    }
    case v1::SetpointRequest::kVelocityYawRate: {
      const auto& sp = request.velocity_yaw_rate();
      if (auto s = checkVector(sp.velocity_m_s(), "velocity_yaw_rate.velocity_m_s",
                               options_.max_speed_m_s);
          !s.ok()) {
        return s;
      }
      if (auto s = checkFinite(sp.yaw_rate_rad_s(), "velocity_yaw_rate.yaw_rate_rad_s"); !s.ok()) {
        return s;
      }
      if (std::abs(sp.yaw_rate_rad_s()) > options_.max_rate_rad_s) {
        return absl::InvalidArgumentError("velocity_yaw_rate.yaw_rate_rad_s is beyond the limit " +
                                          std::to_string(options_.max_rate_rad_s));
      }
      next.kind = PlatformCommand::Kind::kVelocityYawRate;
      next.vector = {sp.velocity_m_s().x(), sp.velocity_m_s().y(), sp.velocity_m_s().z()};
      next.yaw_rate_rad_s = sp.yaw_rate_rad_s();
      break;
    }
    case v1::SetpointRequest::kPositionYaw: {
      const auto& sp = request.position_yaw();
      if (auto s = checkVector(sp.position_m(), "position_yaw.position_m", 1e5); !s.ok()) return s;
      if (auto s = checkFinite(sp.yaw_rad(), "position_yaw.yaw_rad"); !s.ok()) return s;
      if (sp.position_m().z() > options_.max_altitude_m) {
        return absl::InvalidArgumentError("position_yaw.position_m.z is above the ceiling of " +
                                          std::to_string(options_.max_altitude_m) + " m");
      }
      next.kind = PlatformCommand::Kind::kPositionYaw;
      next.vector = {sp.position_m().x(), sp.position_m().y(), sp.position_m().z()};
      next.yaw_rad = sp.yaw_rad();
      break;
    }
    default:
      return absl::InvalidArgumentError(
          "no setpoint given: set one of thrust_rates, attitude_thrust, velocity_yaw_rate, "
          "position_yaw");
  }
  command_ = next;
  state_ = v1::FLIGHT_STATE_FLYING;
  lease_expiry_ = now + lease_ttl_;
  failsafe_active_ = false;
  return state_;
}

}  // namespace behaviorlib::sim
