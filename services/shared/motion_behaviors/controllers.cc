#include "behaviorlib/motion_behaviors/controllers.h"

#include "behaviorlib/flight_common/flight_support.h"

namespace behaviorlib::motion_behaviors {
namespace {

void setAttitude(const motion::AttitudeThrustCommand& command, v1::SetpointRequest* setpoint) {
  auto* sp = setpoint->mutable_attitude_thrust();
  sp->mutable_orientation()->set_w(command.orientation.w());
  sp->mutable_orientation()->set_x(command.orientation.x());
  sp->mutable_orientation()->set_y(command.orientation.y());
  sp->mutable_orientation()->set_z(command.orientation.z());
  sp->set_thrust_ratio(command.thrust_ratio);
}

class PidAttitude final : public ControllerAdapter {
 public:
  PidAttitude(const motion::VehicleModel& model, const motion::PidGains& gains)
      : pid_(model, gains) {}
  v1::SetpointRequest step(const motion::StateEstimate& state,
                           const motion::MotionReference& reference, double dt_s,
                           motion::ControllerDiagnostics* diagnostics,
                           double* thrust_ratio) override {
    const auto command = pid_.update(state, reference, dt_s, diagnostics);
    v1::SetpointRequest setpoint;
    setAttitude(command, &setpoint);
    *thrust_ratio = command.thrust_ratio;
    return setpoint;
  }

 private:
  motion::PidMotionController pid_;
};

class PidThrustRates final : public ControllerAdapter {
 public:
  PidThrustRates(const motion::VehicleModel& model, const motion::PidGains& gains,
                 const Eigen::Vector3d& attitude_p, double max_rate_rad_s)
      : pid_(model, gains), attitude_p_(attitude_p), max_rate_rad_s_(max_rate_rad_s) {}
  v1::SetpointRequest step(const motion::StateEstimate& state,
                           const motion::MotionReference& reference, double dt_s,
                           motion::ControllerDiagnostics* diagnostics,
                           double* thrust_ratio) override {
    const auto command = pid_.update(state, reference, dt_s, diagnostics);
    const Eigen::Vector3d rates = motion::attitudeToBodyRates(
        state.orientation, command.orientation, attitude_p_, max_rate_rad_s_);
    v1::SetpointRequest setpoint;
    auto* sp = setpoint.mutable_thrust_rates();
    sp->set_thrust_ratio(command.thrust_ratio);
    sp->mutable_rates_rad_s()->set_x(rates.x());
    sp->mutable_rates_rad_s()->set_y(rates.y());
    sp->mutable_rates_rad_s()->set_z(rates.z());
    if (diagnostics && !rates.allFinite()) diagnostics->finite = false;
    *thrust_ratio = command.thrust_ratio;
    return setpoint;
  }

 private:
  motion::PidMotionController pid_;
  Eigen::Vector3d attitude_p_;
  double max_rate_rad_s_;
};

class Mpc final : public ControllerAdapter {
 public:
  Mpc(const motion::VehicleModel& model, const motion::MpcParams& params) : mpc_(model, params) {}
  v1::SetpointRequest step(const motion::StateEstimate& state,
                           const motion::MotionReference& reference, double dt_s,
                           motion::ControllerDiagnostics* diagnostics,
                           double* thrust_ratio) override {
    const auto command = mpc_.update(state, reference, dt_s, diagnostics);
    v1::SetpointRequest setpoint;
    setAttitude(command, &setpoint);
    *thrust_ratio = command.thrust_ratio;
    return setpoint;
  }

 private:
  motion::MpcMotionController mpc_;
};

}  // namespace

std::unique_ptr<ControllerAdapter> makePidAttitudeController(const motion::VehicleModel& model,
                                                             const motion::PidGains& gains) {
  return std::make_unique<PidAttitude>(model, gains);
}

std::unique_ptr<ControllerAdapter> makePidThrustRatesController(const motion::VehicleModel& model,
                                                                const motion::PidGains& gains,
                                                                const Eigen::Vector3d& attitude_p,
                                                                double max_rate_rad_s) {
  return std::make_unique<PidThrustRates>(model, gains, attitude_p, max_rate_rad_s);
}

std::unique_ptr<ControllerAdapter> makeMpcController(const motion::VehicleModel& model,
                                                     const motion::MpcParams& params) {
  return std::make_unique<Mpc>(model, params);
}

namespace {
void configureAirframe(const config::v1::MotionControlConfig& config, motion::VehicleModel* model) {
  model->mass_kg = config.flight().mass_kg();
  model->max_thrust_n = config.max_thrust_n();
}
}  // namespace

void ControllerConfig::configure(const config::v1::PidMotionControlConfig& config) {
  configureAirframe(config.control(), &model);
  pid.position_p = {config.position_p_xy(), config.position_p_xy(), config.position_p_z()};
  pid.velocity_p = {config.velocity_p_xy(), config.velocity_p_xy(), config.velocity_p_z()};
  pid.velocity_i = {config.velocity_i_xy(), config.velocity_i_xy(), config.velocity_i_z()};
  attitude_p = {config.attitude_p_xy(), config.attitude_p_xy(), config.attitude_p_z()};
  max_rate_rad_s = config.max_rate_rad_s();
}

void ControllerConfig::configure(const config::v1::MpcMotionControlConfig& config) {
  configureAirframe(config.control(), &model);
  mpc.horizon_steps = config.horizon_steps();
  mpc.step_s = config.step_s();
  mpc.acceleration_lag_s = config.acceleration_lag_s();
  mpc.position_weight = config.position_weight();
  mpc.velocity_weight = config.velocity_weight();
  mpc.input_weight = config.input_weight();
  mpc.input_rate_weight = config.input_rate_weight();
  mpc.max_iterations = config.max_iterations();
  mpc.disturbance_gain = config.disturbance_gain();
}

}  // namespace behaviorlib::motion_behaviors
