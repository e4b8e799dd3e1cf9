#include "behaviorlib/motion_behaviors/motion_control_behavior.h"

#include <algorithm>

#include "behaviorlib/motion_behaviors/motion_messages.h"
#include "behaviorlib/v1/behaviors/quadrotor_motion_with_mpc_control.pb.h"
#include "behaviorlib/v1/behaviors/quadrotor_motion_with_pid_control.pb.h"

namespace behaviorlib::motion_behaviors {

using flight::fixed2;
using flight::secondsText;

namespace {

template <class P>
void applySpeedAndTiltLimits(const P& p, motion::VehicleModel* model) {
  model->max_horizontal_speed_m_s = p.max_horizontal_speed_m_s();
  model->max_vertical_speed_m_s = p.max_vertical_speed_m_s();
  model->max_tilt_rad = p.max_tilt_rad();
}

void applyLimits(const v1::QuadrotorPidMotionControlParameters& p, motion::VehicleModel* model) {
  applySpeedAndTiltLimits(p, model);
}
void applyLimits(const v1::QuadrotorPidThrustControlParameters& p, motion::VehicleModel* model) {
  applySpeedAndTiltLimits(p, model);
}
void applyLimits(const v1::QuadrotorMpcMotionControlParameters& p, motion::VehicleModel* model) {
  model->max_tilt_rad = p.max_tilt_rad();
}

}  // namespace

BehaviorOptions controllerBehaviorOptions() {
  BehaviorOptions options;
  options.frequency_hz = 100.0;
  options.watchdog_timeout = std::chrono::seconds(2);
  return options;
}

template <class Params, class Config>
MotionControlBehavior<Params, Config>::MotionControlBehavior(flight::Vehicle& vehicle,
                                                             MotionLink& link,
                                                             ControllerFactory factory)
    : Behavior<Params, Config>(controllerBehaviorOptions()),
      link_(link),
      factory_(std::move(factory)),
      support_(vehicle) {}

template <class Params, class Config>
absl::Status MotionControlBehavior<Params, Config>::onConfigure(const Config& config) {
  const config::v1::MotionControlConfig& control = config.control();
  if (auto s = support_.configure(control.flight()); !s.ok()) return s;
  controller_config_.configure(config);
  reference_timeout_ = seconds(control.reference_timeout_s());
  status_period_ = seconds(1.0 / control.status_frequency_hz());
  saturation_timeout_ = seconds(control.saturation_timeout_s());
  max_tracking_error_m_ = control.max_tracking_error_m();
  max_pose_extrapolation_s_ = control.max_pose_extrapolation_s();
  off_track_.setDwell(support_.settings().progress_window);
  return absl::OkStatus();
}

template <class Params, class Config>
void MotionControlBehavior<Params, Config>::makeController(const Params& p) {
  motion::VehicleModel model = controller_config_.model;
  applyLimits(p, &model);
  controller_ = factory_(controller_config_, model);
}

template <class Params, class Config>
absl::Status MotionControlBehavior<Params, Config>::onActivate() {
  if (auto s = support_.begin(this->robotId() + "/" + this->name()); !s.ok()) return s;
  link_.followReferences(true);
  makeController(this->parameters());
  hold_ = holdAt(support_.state().position_m, support_.yawRad());
  was_tracking_ = hold_where_stopped_ = false;
  reference_source_.clear();
  reference_header_.Clear();
  last_step_ = this->now();
  last_status_ = TimePoint{};
  saturated_since_.reset();
  off_track_.reset();
  position_error_m_ = thrust_ratio_ = 0.0;
  saturated_ = false;
  setpoints_ = 0;
  return absl::OkStatus();
}

template <class Params, class Config>
motion::MotionReference MotionControlBehavior<Params, Config>::currentReference(TimePoint now,
                                                                                bool* tracking) {
  const auto latest = link_.latestReference();
  if (latest && latest->mode() != v1::MOTION_REFERENCE_MODE_UNSPECIFIED) {
    const double age = ageSeconds(latest->header(), now);
    if (age <= toSeconds(reference_timeout_)) {
      motion::MotionReference reference = advance(fromProto(*latest), std::max(age, 0.0));
      if (reference.mode == motion::MotionReference::Mode::kVelocity) {
        hold_where_stopped_ = true;
      } else {
        // Where to stay if the references stop now.
        hold_ = holdAt(reference.point.position_m, reference.point.yaw_rad);
        hold_where_stopped_ = false;
      }
      reference_source_ = latest->source();
      reference_header_ = latest->header();
      was_tracking_ = *tracking = true;
      return reference;
    }
  }
  if (was_tracking_ && hold_where_stopped_) {
    hold_ = holdAt(support_.state().position_m, support_.yawRad());
  }
  was_tracking_ = hold_where_stopped_ = *tracking = false;
  reference_source_.clear();
  reference_header_.Clear();
  return hold_;
}

template <class Params, class Config>
void MotionControlBehavior<Params, Config>::onExecute() {
  const TimePoint t = this->now();
  const double dt = std::clamp(toSeconds(t - last_step_), 0.001, 0.1);
  last_step_ = t;
  motion::StateEstimate state = support_.state();
  // The estimate is a few hops old: advance it by its age.
  const double pose_age = std::clamp(ageSeconds(support_.pose().header(), t), 0.0,
                                     std::max(max_pose_extrapolation_s_, 0.0));
  state.position_m += state.velocity_m_s * pose_age;

  bool tracking = false;
  const motion::MotionReference reference = currentReference(t, &tracking);
  motion::ControllerDiagnostics diagnostics;
  const v1::SetpointRequest setpoint =
      controller_->step(state, reference, dt, &diagnostics, &thrust_ratio_);
  position_error_m_ = reference.mode == motion::MotionReference::Mode::kVelocity
                          ? 0.0
                          : (state.position_m - reference.point.position_m).norm();
  saturated_ = diagnostics.saturated;
  if (!diagnostics.finite) {
    support_.fail("the controller's output is not finite (estimate at " +
                  pointText(state.position_m) + ", reference at " +
                  pointText(reference.point.position_m) + "); no setpoint sent");
    return;
  }
  if (!saturated_) {
    saturated_since_.reset();
  } else if (!saturated_since_) {
    saturated_since_ = t;
  }
  if (!support_.send(setpoint)) return;
  ++setpoints_;
  if (t - last_status_ >= status_period_) {
    publishStatus(
        t, tracking ? v1::MOTION_CONTROLLER_STATE_TRACKING : v1::MOTION_CONTROLLER_STATE_HOLDING);
  }
}

template <class Params, class Config>
void MotionControlBehavior<Params, Config>::publishStatus(TimePoint now,
                                                          v1::MotionControllerState state) {
  last_status_ = now;
  v1::MotionControlStatus status;
  stampHeader(now, this->robotId(), ++status_seq_, status.mutable_header());
  status.set_controller(this->name());
  status.set_activation_id(this->activationId());
  status.set_state(state);
  if (state == v1::MOTION_CONTROLLER_STATE_TRACKING) {
    status.set_reference_source(reference_source_);
    *status.mutable_reference_header() = reference_header_;
  }
  status.set_position_error_m(position_error_m_);
  status.set_thrust_ratio(thrust_ratio_);
  status.set_saturated(saturated_);
  status.set_setpoints_sent(setpoints_);
  // A refused status is not the controller's failure: the behaviors that
  // watch it report its absence.
  (void)link_.publishStatus(status);
}

template <class Params, class Config>
void MotionControlBehavior<Params, Config>::onDeactivate() {
  if (!support_.active()) return;
  publishStatus(this->now(), v1::MOTION_CONTROLLER_STATE_STOPPED);
  support_.end();  // the platform hovers where the vehicle is
  controller_.reset();
  link_.followReferences(false);
}

template <class Params, class Config>
void MotionControlBehavior<Params, Config>::onPause() {
  support_.holdHere();
  publishStatus(this->now(), v1::MOTION_CONTROLLER_STATE_HOLDING);
}

template <class Params, class Config>
void MotionControlBehavior<Params, Config>::onResume() {
  last_step_ = this->now();
  saturated_since_.reset();
  off_track_.reset();
}

template <class Params, class Config>
absl::Status MotionControlBehavior<Params, Config>::onModify(const Params& new_parameters) {
  makeController(new_parameters);
  return absl::OkStatus();
}

template <class Params, class Config>
Situation MotionControlBehavior<Params, Config>::checkSituation() {
  return support_.active() ? support_.situationActive()
                           : support_.situationBefore(this->now(), this->name());
}

template <class Params, class Config>
Verdict MotionControlBehavior<Params, Config>::checkProgress() {
  if (off_track_.update(this->now(), position_error_m_ > max_tracking_error_m_)) {
    return Verdict::finish("the vehicle has been more than " + fixed2(max_tracking_error_m_) +
                           " m from the reference for " + secondsText(off_track_.dwell()) +
                           " (now " + fixed2(position_error_m_) + " m)");
  }
  return Verdict::keepGoing();
}

template <class Params, class Config>
Verdict MotionControlBehavior<Params, Config>::checkProcesses() {
  if (auto problem = support_.checkProcesses(this->now())) return Verdict::finish(*problem);
  if (saturated_since_ && this->now() - *saturated_since_ > saturation_timeout_) {
    return Verdict::finish(
        "the controller's output has been saturated (tilt or thrust limit) for " +
        secondsText(this->now() - *saturated_since_) + " (saturation_timeout_s " +
        secondsText(saturation_timeout_) + ")");
  }
  return Verdict::keepGoing();
}

template class MotionControlBehavior<v1::QuadrotorPidMotionControlParameters,
                                     config::v1::PidMotionControlConfig>;
template class MotionControlBehavior<v1::QuadrotorPidThrustControlParameters,
                                     config::v1::PidMotionControlConfig>;
template class MotionControlBehavior<v1::QuadrotorMpcMotionControlParameters,
                                     config::v1::MpcMotionControlConfig>;

}  // namespace behaviorlib::motion_behaviors
