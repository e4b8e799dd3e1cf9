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

absl::Status ControllerConfig::read(const YAML::Node& config) {
  using flight::readNumber;
  struct Key {
    const char* name;
    double min, max;
    double* value;
  };
  double horizon = mpc.horizon_steps, iterations = mpc.max_iterations;
  const Key keys[] = {
      {"mass_kg", 0.01, 1000, &model.mass_kg},
      {"max_thrust_n", 0.01, 100000, &model.max_thrust_n},
      {"position_p_xy", 0, 100, &pid.position_p.x()},
      {"position_p_z", 0, 100, &pid.position_p.z()},
      {"velocity_p_xy", 0, 100, &pid.velocity_p.x()},
      {"velocity_p_z", 0, 100, &pid.velocity_p.z()},
      {"velocity_i_xy", -1e-9, 100, &pid.velocity_i.x()},
      {"velocity_i_z", -1e-9, 100, &pid.velocity_i.z()},
      {"attitude_p_xy", 0, 100, &attitude_p.x()},
      {"attitude_p_z", 0, 100, &attitude_p.z()},
      {"max_rate_rad_s", 0, 10, &max_rate_rad_s},
      {"horizon_steps", 1, 200, &horizon},
      {"step_s", 0, 1, &mpc.step_s},
      {"acceleration_lag_s", 0, 10, &mpc.acceleration_lag_s},
      {"position_weight", -1e-9, 1e6, &mpc.position_weight},
      {"velocity_weight", -1e-9, 1e6, &mpc.velocity_weight},
      {"input_weight", 0, 1e6, &mpc.input_weight},
      {"input_rate_weight", -1e-9, 1e6, &mpc.input_rate_weight},
      {"max_iterations", 0, 100000, &iterations},
      {"disturbance_gain", -1e-9, 1, &mpc.disturbance_gain},
  };
  for (const Key& key : keys) {
    if (auto s = readNumber(config, key.name, key.min, key.max, key.value); !s.ok()) return s;
  }
  pid.position_p.y() = pid.position_p.x();
  pid.velocity_p.y() = pid.velocity_p.x();
  pid.velocity_i.y() = pid.velocity_i.x();
  attitude_p.y() = attitude_p.x();
  mpc.horizon_steps = static_cast<int>(horizon);
  mpc.max_iterations = static_cast<int>(iterations);
  return absl::OkStatus();
}

}  // namespace behaviorlib::motion_behaviors
