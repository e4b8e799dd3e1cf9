#include "behaviorlib/basic_quadrotor_behaviors/take_off_behavior.h"

#include <algorithm>
#include <cmath>

#include "behaviorlib/platform/flight_controller_client.h"

namespace behaviorlib::basic {

double yawOf(const v1::Quaternion& q) {
  return std::atan2(2.0 * (q.w() * q.z() + q.x() * q.y()),
                    1.0 - 2.0 * (q.y() * q.y() + q.z() * q.z()));
}

TakeOffBehavior::TakeOffBehavior(flight::Vehicle& vehicle)
    : Behavior(flight::flightBehaviorOptions(std::chrono::seconds(60))), vehicle_(vehicle) {}

absl::Status TakeOffBehavior::onConfigure(const config::v1::TakeOffConfig& config) {
  if (auto s = settings_.configure(config.flight()); !s.ok()) return s;
  wind_.configure(settings_);
  altitude_tolerance_m_ = config.altitude_tolerance_m();
  max_vertical_speed_m_s_ = config.max_vertical_speed_m_s();
  min_climb_m_ = config.min_climb_m();
  max_pose_stddev_m_ = config.max_pose_stddev_m();
  dwell_.setDwell(seconds(config.goal_dwell_s()));
  climb_.setWindow(settings_.progress_window);
  return absl::OkStatus();
}

absl::Status TakeOffBehavior::onActivate() {
  vehicle_.followEstimate(true);
  auto fail = [this](absl::Status status) {
    lease_.reset();
    vehicle_.followEstimate(false);
    return status;
  };
  auto pose = vehicle_.poseEstimate();
  if (!pose.ok()) return fail(pose.status());
  origin_x_ = pose->pose().position_m().x();
  origin_y_ = pose->pose().position_m().y();
  origin_z_ = pose->pose().position_m().z();
  origin_yaw_ = yawOf(pose->pose().orientation());
  auto lease =
      vehicle_.acquireLease(robotId() + "/TAKE_OFF", settings_.lease_ttl, settings_.preempt_lease);
  if (!lease.ok()) return fail(lease.status());
  lease_ = std::move(*lease);
  const double altitude = parameters().altitude_m();
  if (auto state = lease_->execute(v1::FLIGHT_ACTION_TAKE_OFF, altitude); !state.ok()) {
    return fail(state.status());
  }
  target_z_ = origin_z_ + altitude;
  commanded_z_ = target_z_;
  seen_airborne_ = false;
  correcting_ = false;
  holding_zero_speed_ = false;
  settled_.reset();
  command_error_.clear();
  dwell_.reset();
  climb_.reset();
  active_ = true;
  return absl::OkStatus();
}

void TakeOffBehavior::onExecute() {
  // Setpoints are accepted once the take-off action has ended (HOVERING).
  if (!lease_) return;
  const auto state = status_->state();
  if (state != v1::FLIGHT_STATE_HOVERING && state != v1::FLIGHT_STATE_FLYING) return;
  if (commanded_z_ == target_z_) {
    correctAltitude();
    return;
  }
  // After a Modify or a Resume the platform has to be sent to the target.
  auto sent = lease_->goTo(origin_x_, origin_y_, target_z_, origin_yaw_);
  if (sent.ok()) {
    commanded_z_ = target_z_;
    holding_zero_speed_ = false;
  } else {
    command_error_ =
        "the platform refused the altitude setpoint: " + std::string(sent.status().message());
  }
}

// The platform's take-off climbs altitude_m in the platform's own frame; the
// goal is judged on the pose estimate. A barometric altitude drifts: the
// lidar SLAM's moved by up to 0.1 m between the ground and 1.2 m, and the
// vehicle then hovered short of the target for good (WRONG_PROGRESS, no
// progress). An EKF's height converges while the vehicle climbs and hovers: in
// the compose stack one hovered 0.11 m short of its target and ended
// WRONG_PROGRESS. Once the platform holds the vehicle still (HOVERING after its
// take-off action, or FLYING on this behavior's own speed of zero) for a
// second beyond the tolerance, the rest is closed with a vertical speed, which
// needs no frame, then a speed of zero; as often as the estimate moves away
// again.
//   - The settle needs the platform's state and a vertical speed within the
//     goal's: a vehicle falling (a motor lost) is not corrected but ends
//     WRONG_PROGRESS on the progress window, before it crashes.
//   - The speed is at least kMinSpeedMS until within half the tolerance, so a
//     few centimetres are closed in a fraction of the progress window.
//   - The progress window restarts when a correction starts: the settle is
//     the behavior waiting, not the vehicle failing to climb. A correction
//     that does not move the estimate still ends WRONG_PROGRESS.
void TakeOffBehavior::correctAltitude() {
  constexpr double kGainPerS = 1.0;
  constexpr double kMinSpeedMS = 0.1;
  constexpr double kMaxSpeedMS = 0.3;
  const double to_go = target_z_ - pose_->pose().position_m().z();
  if (!correcting_) {
    const auto state = status_->state();
    const double vz = twist_->twist().linear_m_s().z();
    const bool still = (state == v1::FLIGHT_STATE_HOVERING ||
                        (state == v1::FLIGHT_STATE_FLYING && holding_zero_speed_)) &&
                       std::abs(vz) <= max_vertical_speed_m_s_;
    if (!settled_.update(now(), still) || std::abs(to_go) <= altitude_tolerance_m_) return;
    correcting_ = true;
    climb_.reset();
  }
  double speed =
      std::copysign(std::clamp(kGainPerS * std::abs(to_go), kMinSpeedMS, kMaxSpeedMS), to_go);
  if (std::abs(to_go) <= 0.5 * altitude_tolerance_m_) {
    speed = 0.0;
    correcting_ = false;
    settled_.reset();
  }
  holding_zero_speed_ = speed == 0.0;
  v1::SetpointRequest setpoint;
  setpoint.mutable_velocity_yaw_rate()->mutable_velocity_m_s()->set_z(speed);
  if (auto sent = lease_->send(std::move(setpoint)); !sent.ok()) {
    command_error_ =
        "the platform refused the vertical speed setpoint: " + std::string(sent.message());
  }
}

void TakeOffBehavior::onDeactivate() {
  active_ = false;
  if (lease_) {
    // Leave the vehicle hovering: the take-off action (or a setpoint) may
    // still be climbing.
    auto status = vehicle_.flightStatus();
    if (status.ok() && (status->state() == v1::FLIGHT_STATE_TAKING_OFF ||
                        status->state() == v1::FLIGHT_STATE_FLYING)) {
      (void)lease_->execute(v1::FLIGHT_ACTION_HOVER);
    }
    (void)lease_->release();
    lease_.reset();
  }
  vehicle_.followEstimate(false);
}

void TakeOffBehavior::onPause() {
  if (lease_) {
    (void)lease_->execute(v1::FLIGHT_ACTION_HOVER);
    commanded_z_ = std::numeric_limits<double>::quiet_NaN();
  }
}

void TakeOffBehavior::onResume() {
  correcting_ = false;
  settled_.reset();
  dwell_.reset();
  climb_.reset();
}

absl::Status TakeOffBehavior::onModify(const v1::TakeOffParameters& p) {
  target_z_ = origin_z_ + p.altitude_m();
  commanded_z_ = std::numeric_limits<double>::quiet_NaN();
  correcting_ = false;
  settled_.reset();
  dwell_.reset();
  climb_.reset();
  return absl::OkStatus();
}

Situation TakeOffBehavior::checkSituation() {
  if (active_) {
    Situation situation = flight::activeFlightSituation(*status_, lease_.get(), settings_, false);
    wind_.apply(&situation);
    return situation;
  }
  Situation situation;
  auto status =
      flight::checkFlightPreconditions(vehicle_, now(), settings_, true, true, &situation);
  if (status && status->state() != v1::FLIGHT_STATE_LANDED) {
    flight::refuseFirst(&situation, v1::SITUATION_REASON_FLIGHT_STATE,
                        "TAKE_OFF needs " + robotId() + " LANDED; it is " +
                            platform::flightStateName(status->state()));
  }
  if (situation.feasible && max_pose_stddev_m_ > 0.0) {
    // The pre-flight check of the estimate (read fresh by the checks above).
    auto pose = vehicle_.poseEstimate();
    if (pose.ok() && pose->has_horizontal_stddev_m() &&
        pose->horizontal_stddev_m() > max_pose_stddev_m_) {
      flight::refuseFirst(&situation, v1::SITUATION_REASON_INPUT_INVALID,
                          "the pose estimate states a horizontal standard deviation of " +
                              flight::fixed2(pose->horizontal_stddev_m()) +
                              " m, above max_pose_stddev_m " + flight::fixed2(max_pose_stddev_m_) +
                              " m: its estimator has not converged (wait, then take off)");
    }
  }
  return situation;
}

Verdict TakeOffBehavior::checkGoal() {
  const double z = pose_->pose().position_m().z();
  const double vz = twist_->twist().linear_m_s().z();
  const auto state = status_->state();
  const bool holds = (state == v1::FLIGHT_STATE_HOVERING || state == v1::FLIGHT_STATE_FLYING) &&
                     std::abs(z - target_z_) <= altitude_tolerance_m_ &&
                     std::abs(vz) <= max_vertical_speed_m_s_;
  if (!dwell_.update(now(), holds)) return Verdict::keepGoing();
  return Verdict::finish("at " + flight::fixed2(z) + " m (target " + flight::fixed2(target_z_) +
                         " m, tolerance " + flight::fixed2(altitude_tolerance_m_) + " m) for " +
                         flight::secondsText(dwell_.dwell()));
}

Verdict TakeOffBehavior::checkProgress() {
  const auto state = status_->state();
  if (state == v1::FLIGHT_STATE_TAKING_OFF || state == v1::FLIGHT_STATE_FLYING ||
      state == v1::FLIGHT_STATE_HOVERING) {
    seen_airborne_ = true;
  } else if (seen_airborne_ &&
             (state == v1::FLIGHT_STATE_LANDING || state == v1::FLIGHT_STATE_LANDED)) {
    return Verdict::finish("unexpected landing: the platform reports " +
                           platform::flightStateName(state) + " during the take-off");
  }
  const double z = pose_->pose().position_m().z();
  climb_.add(now(), z);
  const double to_go = target_z_ - z;
  // A small overshoot at the end of a fast climb is the autopilot settling,
  // not moving away: above the target, only an overshoot beyond this band
  // is judged.
  const double overshoot_band = std::max(0.5, 3.0 * altitude_tolerance_m_);
  const bool judged = to_go > altitude_tolerance_m_ || to_go < -overshoot_band;
  if (climb_.full() && judged) {
    // Progress is movement towards the target (up, or down after a Modify).
    const double towards = to_go > 0 ? climb_.change() : -climb_.change();
    if (towards < min_climb_m_) {
      return Verdict::finish("no progress towards " + flight::fixed2(target_z_) + " m: altitude " +
                             flight::fixed2(z) + " m, moved " + flight::fixed2(towards) +
                             " m towards it in " + flight::secondsText(climb_.window()) +
                             " (minimum " + flight::fixed2(min_climb_m_) + " m)");
    }
  }
  return Verdict::keepGoing();
}

Verdict TakeOffBehavior::checkProcesses() {
  if (auto problem = flight::checkFlightInputs(vehicle_, now(), settings_, lease_.get(), true,
                                               &status_, &pose_, &twist_)) {
    return Verdict::finish(*problem);
  }
  wind_.observe(*status_, *pose_, *twist_);
  if (!command_error_.empty()) return Verdict::finish(command_error_);
  return Verdict::keepGoing();
}

}  // namespace behaviorlib::basic
