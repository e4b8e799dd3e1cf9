#include "behaviorlib/motion_behaviors/commander_support.h"

#include "behaviorlib/motion_behaviors/motion_messages.h"
#include "behaviorlib/platform/flight_controller_client.h"

namespace behaviorlib::motion_behaviors {

absl::Status CommanderSupport::configure(const config::v1::FlightConfig& config) {
  if (auto s = settings_.configure(config); !s.ok()) return s;
  wind_.configure(settings_);
  return absl::OkStatus();
}

Situation CommanderSupport::situationBefore(TimePoint now, const std::string& behavior) {
  Situation situation;
  auto status = flight::checkFlightPreconditions(vehicle_, now, settings_, true, true, &situation);
  if (!status) return situation;
  if (!flight::flying(status->state())) {
    flight::refuseFirst(&situation, v1::SITUATION_REASON_FLIGHT_STATE,
                        behavior + " needs " + vehicle_.robotId() + " FLYING or HOVERING; it is " +
                            platform::flightStateName(status->state()));
  } else if (!status->lease_holder().empty() && !settings_.preempt_lease) {
    flight::refuseFirst(&situation, v1::SITUATION_REASON_PLATFORM_UNAVAILABLE,
                        "the command lease of " + vehicle_.robotId() + " is held by " +
                            status->lease_holder() +
                            ": only one commander at a time (deactivate it first)");
  }
  if (situation.feasible) {
    wind_.observe(*status, vehicle_);
    wind_.apply(&situation);
  }
  return situation;
}

Situation CommanderSupport::situationActive() const {
  Situation situation = flight::activeFlightSituation(*status_, nullptr, settings_, true);
  if (situation.feasible && !flight::flying(status_->state())) {
    return Situation::infeasible(v1::SITUATION_REASON_FLIGHT_STATE,
                                 "the vehicle is no longer flying: the platform reports " +
                                     platform::flightStateName(status_->state()));
  }
  wind_.apply(&situation);
  return situation;
}

absl::Status CommanderSupport::begin(const std::string& holder,
                                     const std::function<absl::Status()>& check) {
  vehicle_.followEstimate(true);
  auto fail = [this](absl::Status status) {
    lease_.reset();
    vehicle_.followEstimate(false);
    return status;
  };
  if (absl::Status s = vehicle_.readPoseEstimate(&pose_); !s.ok()) return fail(s);
  if (absl::Status s = vehicle_.readTwistEstimate(&twist_); !s.ok()) return fail(s);
  state_ = stateOf(*pose_, *twist_);
  if (check) {
    if (absl::Status s = check(); !s.ok()) return fail(s);
  }
  auto lease = vehicle_.acquireLease(holder, settings_.lease_ttl, settings_.preempt_lease);
  if (!lease.ok()) return fail(lease.status());
  lease_ = std::move(*lease);
  failure_.clear();
  return absl::OkStatus();
}

void CommanderSupport::end() {
  if (!lease_) return;
  (void)lease_->release();
  lease_.reset();
  vehicle_.followEstimate(false);
}

std::optional<std::string> CommanderSupport::checkProcesses(TimePoint now) {
  if (auto problem = flight::checkFlightInputs(vehicle_, now, settings_, lease_.get(), true,
                                               &status_, &pose_, &twist_)) {
    return problem;
  }
  state_ = stateOf(*pose_, *twist_);
  wind_.observe(*status_, *pose_, *twist_);
  if (lease_) {
    if (absl::Status s = lease_->status(); !s.ok()) return std::string(s.message());
  }
  if (!failure_.empty()) return failure_;
  return std::nullopt;
}

void CommanderSupport::fail(std::string problem) {
  if (failure_.empty()) failure_ = std::move(problem);
}

bool CommanderSupport::send(v1::SetpointRequest setpoint) {
  if (!lease_ || !failure_.empty()) return false;
  if (absl::Status s = lease_->send(std::move(setpoint)); !s.ok()) {
    fail("the platform refused a setpoint: " + std::string(s.message()));
    return false;
  }
  return true;
}

void CommanderSupport::goTo(const Eigen::Vector3d& position_m, double yaw_rad) {
  v1::SetpointRequest setpoint;
  toProto(position_m, setpoint.mutable_position_yaw()->mutable_position_m());
  setpoint.mutable_position_yaw()->set_yaw_rad(yaw_rad);
  send(std::move(setpoint));
}

void CommanderSupport::holdHere() { goTo(state_.position_m, state_.yawRad()); }

}  // namespace behaviorlib::motion_behaviors
