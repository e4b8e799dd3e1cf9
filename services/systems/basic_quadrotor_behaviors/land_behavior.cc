#include "behaviorlib/basic_quadrotor_behaviors/land_behavior.h"

#include "behaviorlib/platform/flight_controller_client.h"

namespace behaviorlib::basic {

LandBehavior::LandBehavior(flight::Vehicle& vehicle)
    : Behavior(flight::flightBehaviorOptions(std::chrono::seconds(120))), vehicle_(vehicle) {}

absl::Status LandBehavior::onConfigure(const config::v1::LandConfig& config) {
  if (auto s = settings_.configure(config.flight()); !s.ok()) return s;
  min_descent_m_ = config.min_descent_m();
  descent_.setWindow(settings_.progress_window);
  wind_.configure(settings_);
  return absl::OkStatus();
}

absl::Status LandBehavior::onActivate() {
  vehicle_.followEstimate(true);
  auto lease =
      vehicle_.acquireLease(robotId() + "/LAND", settings_.lease_ttl, settings_.preempt_lease);
  if (!lease.ok()) {
    vehicle_.followEstimate(false);
    return lease.status();
  }
  if (auto state = (*lease)->execute(v1::FLIGHT_ACTION_LAND); !state.ok()) {
    vehicle_.followEstimate(false);
    return state.status();
  }
  lease_ = std::move(*lease);
  seen_landing_ = false;
  command_error_.clear();
  descent_.reset();
  active_ = true;
  return absl::OkStatus();
}

void LandBehavior::onDeactivate() {
  active_ = false;
  if (lease_) {
    auto status = vehicle_.flightStatus();
    if (status.ok() && status->state() == v1::FLIGHT_STATE_LANDING) {
      (void)lease_->execute(v1::FLIGHT_ACTION_HOVER);
    }
    (void)lease_->release();
    lease_.reset();
  }
  vehicle_.followEstimate(false);
}

void LandBehavior::onPause() {
  if (lease_) (void)lease_->execute(v1::FLIGHT_ACTION_HOVER);
}

void LandBehavior::onResume() {
  descent_.reset();
  seen_landing_ = false;
  if (!lease_) return;
  if (auto state = lease_->execute(v1::FLIGHT_ACTION_LAND); !state.ok()) {
    command_error_ =
        "the platform refused LAND on resume: " + std::string(state.status().message());
  }
}

Situation LandBehavior::checkSituation() {
  if (active_) {
    Situation situation = flight::activeFlightSituation(*status_, lease_.get(), settings_, false);
    wind_.apply(&situation);
    return situation;
  }
  Situation situation;
  auto status =
      flight::checkFlightPreconditions(vehicle_, now(), settings_, false, false, &situation);
  if (status && !flight::airborne(status->state())) {
    flight::refuseFirst(&situation, v1::SITUATION_REASON_FLIGHT_STATE,
                        "LAND needs " + robotId() + " in the air; it is " +
                            platform::flightStateName(status->state()));
  }
  if (status && situation.feasible) {
    wind_.observe(*status, vehicle_);
    wind_.apply(&situation);
  }
  return situation;
}

Verdict LandBehavior::checkGoal() {
  // The vehicle was in the air when LAND was activated (checkSituation), so
  // LANDED is always news, even if the LANDING in between was not seen.
  if (status_->state() != v1::FLIGHT_STATE_LANDED) return Verdict::keepGoing();
  return Verdict::finish("landed at altitude " + flight::fixed2(pose_->pose().position_m().z()) +
                         " m");
}

Verdict LandBehavior::checkProgress() {
  const auto state = status_->state();
  // Until LANDING is seen, an airborne state may be the status from before
  // the action (the watcher follows the platform by a few milliseconds).
  if (state == v1::FLIGHT_STATE_LANDING) {
    seen_landing_ = true;
  } else if (seen_landing_ && state != v1::FLIGHT_STATE_LANDED) {
    return Verdict::finish("the vehicle stopped landing: the platform reports " +
                           platform::flightStateName(state));
  }
  const double z = pose_->pose().position_m().z();
  descent_.add(now(), z);
  if (descent_.full() && state == v1::FLIGHT_STATE_LANDING) {
    const double descended = -descent_.change();
    if (descended < min_descent_m_) {
      return Verdict::finish("descent stalled: altitude " + flight::fixed2(z) + " m, descended " +
                             flight::fixed2(descended) + " m in " +
                             flight::secondsText(descent_.window()) + " (minimum " +
                             flight::fixed2(min_descent_m_) + " m)");
    }
  }
  return Verdict::keepGoing();
}

Verdict LandBehavior::checkProcesses() {
  flight::Held<v1::TwistStamped> unused;
  if (auto problem = flight::checkFlightInputs(vehicle_, now(), settings_, lease_.get(), false,
                                               &status_, &pose_, &unused)) {
    return Verdict::finish(*problem);
  }
  wind_.observe(*status_, vehicle_);
  if (!command_error_.empty()) return Verdict::finish(command_error_);
  return Verdict::keepGoing();
}

}  // namespace behaviorlib::basic
