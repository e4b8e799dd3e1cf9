#include "behaviorlib/basic_quadrotor_behaviors/hover_with_flight_action_behavior.h"

#include <cmath>

#include "behaviorlib/flight_common/flight_monitoring.h"
#include "behaviorlib/platform/flight_controller_client.h"

namespace behaviorlib::basic {

HoverWithFlightActionControlBehavior::HoverWithFlightActionControlBehavior(flight::Vehicle& vehicle)
    : Behavior(flight::flightBehaviorOptions(Duration::zero())), vehicle_(vehicle) {}

absl::Status HoverWithFlightActionControlBehavior::onConfigure(
    const config::v1::FlightConfig& config) {
  if (auto s = settings_.configure(config); !s.ok()) return s;
  wind_.configure(settings_);
  return absl::OkStatus();
}

absl::Status HoverWithFlightActionControlBehavior::onActivate() {
  vehicle_.followEstimate(true);
  auto fail = [this](absl::Status status) {
    lease_.reset();
    vehicle_.followEstimate(false);
    return status;
  };
  auto pose = vehicle_.poseEstimate();
  if (!pose.ok()) return fail(pose.status());
  hover_x_ = pose->pose().position_m().x();
  hover_y_ = pose->pose().position_m().y();
  hover_z_ = pose->pose().position_m().z();
  auto lease = vehicle_.acquireLease(robotId() + "/HOVER_WITH_FLIGHT_ACTION_CONTROL",
                                     settings_.lease_ttl, settings_.preempt_lease);
  if (!lease.ok()) return fail(lease.status());
  lease_ = std::move(*lease);
  if (auto state = lease_->execute(v1::FLIGHT_ACTION_HOVER); !state.ok()) {
    return fail(state.status());
  }
  seen_hovering_ = false;
  active_ = true;
  return absl::OkStatus();
}

void HoverWithFlightActionControlBehavior::onDeactivate() {
  active_ = false;
  if (lease_) {
    (void)lease_->release();  // the platform keeps hovering
    lease_.reset();
  }
  vehicle_.followEstimate(false);
}

Situation HoverWithFlightActionControlBehavior::checkSituation() {
  if (active_) {
    Situation situation = flight::activeFlightSituation(*status_, lease_.get(), settings_, true);
    wind_.apply(&situation);
    return situation;
  }
  Situation situation;
  auto status =
      flight::checkFlightPreconditions(vehicle_, now(), settings_, true, false, &situation);
  if (status && status->state() != v1::FLIGHT_STATE_FLYING &&
      status->state() != v1::FLIGHT_STATE_HOVERING) {
    flight::refuseFirst(&situation, v1::SITUATION_REASON_FLIGHT_STATE,
                        "HOVER_WITH_FLIGHT_ACTION_CONTROL needs " + robotId() +
                            " FLYING or HOVERING; it is " +
                            platform::flightStateName(status->state()));
  }
  if (status && situation.feasible) {
    wind_.observe(*status, vehicle_);
    wind_.apply(&situation);
  }
  return situation;
}

Verdict HoverWithFlightActionControlBehavior::checkProgress() {
  const auto state = status_->state();
  if (state == v1::FLIGHT_STATE_HOVERING) {
    seen_hovering_ = true;
  } else if (seen_hovering_) {
    return Verdict::finish("the vehicle left the hover: the platform reports " +
                           platform::flightStateName(state));
  }
  const auto& p = pose_->pose().position_m();
  const double drift =
      std::sqrt((p.x() - hover_x_) * (p.x() - hover_x_) + (p.y() - hover_y_) * (p.y() - hover_y_) +
                (p.z() - hover_z_) * (p.z() - hover_z_));
  if (drift > parameters().max_drift_m()) {
    return Verdict::finish("drifted " + flight::fixed2(drift) + " m from the hover point (" +
                           flight::fixed2(hover_x_) + ", " + flight::fixed2(hover_y_) + ", " +
                           flight::fixed2(hover_z_) + "), beyond max_drift_m " +
                           flight::fixed2(parameters().max_drift_m()));
  }
  return Verdict::keepGoing();
}

Verdict HoverWithFlightActionControlBehavior::checkProcesses() {
  flight::Held<v1::TwistStamped> unused;
  if (auto problem = flight::checkFlightInputs(vehicle_, now(), settings_, lease_.get(), false,
                                               &status_, &pose_, &unused)) {
    return Verdict::finish(*problem);
  }
  wind_.observe(*status_, vehicle_);
  return Verdict::keepGoing();
}

}  // namespace behaviorlib::basic
