#include "behaviorlib/motion_behaviors/reference_support.h"

#include "behaviorlib/flight_common/flight_monitoring.h"
#include "behaviorlib/motion_behaviors/motion_messages.h"
#include "behaviorlib/platform/flight_controller_client.h"

namespace behaviorlib::motion_behaviors {
absl::Status MotionSettings::configure(const config::v1::MotionConfig& config) {
  if (auto s = flight.configure(config.flight()); !s.ok()) return s;
  controller_timeout = seconds(config.controller_timeout_s());
  controller_grace = seconds(config.controller_grace_s());
  goal_dwell = seconds(config.goal_dwell_s());
  min_altitude_m = config.min_altitude_m();
  return absl::OkStatus();
}

BehaviorOptions referenceBehaviorOptions(Duration maximum_execution_time) {
  BehaviorOptions options;
  options.frequency_hz = 50.0;
  options.maximum_execution_time = maximum_execution_time;
  options.watchdog_timeout = std::chrono::seconds(2);
  return options;
}

ReferenceSupport::ReferenceSupport(flight::Vehicle& vehicle, MotionLink& link)
    : vehicle_(vehicle), link_(link) {}

absl::Status ReferenceSupport::configure(const config::v1::MotionConfig& config) {
  if (auto s = settings_.configure(config); !s.ok()) return s;
  wind_.configure(settings_.flight);
  return absl::OkStatus();
}

Situation ReferenceSupport::situationBefore(TimePoint now, const std::string& behavior) {
  Situation situation;
  auto status =
      flight::checkFlightPreconditions(vehicle_, now, settings_.flight, true, true, &situation);
  if (status && !flight::flying(status->state())) {
    flight::refuseFirst(&situation, v1::SITUATION_REASON_FLIGHT_STATE,
                        behavior + " needs " + vehicle_.robotId() + " FLYING or HOVERING; it is " +
                            platform::flightStateName(status->state()));
  }
  if (status && situation.feasible) {
    wind_.observe(*status, vehicle_);
    wind_.apply(&situation);
  }
  return situation;
}

Situation ReferenceSupport::situationActive() const {
  Situation situation = flight::activeFlightSituation(*status_, nullptr, settings_.flight, true);
  if (situation.feasible && !flight::flying(status_->state())) {
    return Situation::infeasible(v1::SITUATION_REASON_FLIGHT_STATE,
                                 "the vehicle is no longer flying: the platform reports " +
                                     platform::flightStateName(status_->state()));
  }
  wind_.apply(&situation);
  return situation;
}

absl::Status ReferenceSupport::begin(TimePoint now, const std::string& source) {
  vehicle_.followEstimate(true);
  link_.followStatus(true);
  active_ = true;
  for (absl::Status s : {vehicle_.readPoseEstimate(&pose_), vehicle_.readTwistEstimate(&twist_)}) {
    if (!s.ok()) {
      end();
      return s;
    }
  }
  state_ = stateOf(*pose_, *twist_);
  source_ = source;
  began_ = now;
  last_followed_ = now;
  controller_.clear();
  seq_ = 0;
  return absl::OkStatus();
}

void ReferenceSupport::end() {
  if (!active_) return;
  active_ = false;
  link_.followStatus(false);
  vehicle_.followEstimate(false);
}

std::optional<std::string> ReferenceSupport::checkProcesses(TimePoint now) {
  if (auto problem = flight::checkFlightInputs(vehicle_, now, settings_.flight, nullptr, true,
                                               &status_, &pose_, &twist_)) {
    return problem;
  }
  state_ = stateOf(*pose_, *twist_);
  wind_.observe(*status_, *pose_, *twist_);
  return checkController(now);
}

std::optional<std::string> ReferenceSupport::checkController(TimePoint now) {
  const auto status = link_.latestStatus();
  if (status && status->reference_source() == source_ &&
      status->state() == v1::MOTION_CONTROLLER_STATE_TRACKING &&
      ageSeconds(status->header(), now) <=
          std::chrono::duration<double>(settings_.controller_timeout).count()) {
    last_followed_ = now;
    controller_ = status->controller();
  }
  // The grace runs from when statuses can arrive: a subscription that takes
  // long to establish (a busy host, the deterministic mode running ahead of
  // the wall clock) is not a controller that does not follow.
  if (!link_.statusFollowed()) began_ = now;
  if (now - began_ < settings_.controller_grace) return std::nullopt;
  if (now - last_followed_ <= settings_.controller_timeout) return std::nullopt;
  const std::string activate =
      "; activate a motion controller (QUADROTOR_PID_MOTION_CONTROL, "
      "QUADROTOR_PID_THRUST_CONTROL or QUADROTOR_MPC_MOTION_CONTROL)";
  if (!status) {
    return "no motion controller follows the references on " + link_.referenceTopic() +
           ": nothing on " + link_.statusTopic() + activate;
  }
  const Duration age = now - flight::stampTime(status->header());
  if (status->state() == v1::MOTION_CONTROLLER_STATE_STOPPED) {
    return "the motion controller " + status->controller() + " stopped" + activate;
  }
  if (age > settings_.controller_timeout) {
    return "no motion controller follows the references on " + link_.referenceTopic() +
           ": the last status of " + status->controller() + " on " + link_.statusTopic() + " is " +
           flight::secondsText(age) + " old (limit " +
           flight::secondsText(settings_.controller_timeout) + ")" + activate;
  }
  return "the motion controller " + status->controller() + " has not followed the references of " +
         source_ + " for " + flight::secondsText(now - last_followed_) + " (it follows '" +
         status->reference_source() + "')";
}

absl::Status ReferenceSupport::publish(const motion::MotionReference& reference, TimePoint now) {
  v1::MotionReference message = toProto(reference);
  stampHeader(now, vehicle_.robotId(), ++seq_, message.mutable_header());
  message.set_source(source_);
  return link_.publishReference(message);
}

}  // namespace behaviorlib::motion_behaviors
